"""Benchmark suites: versioned sets of datasets, methods run over them with seeds, and a
leaderboard (`nerfgauge suite ...`).

- `definition`: the suite file (TOML) and its folder: reading, generating the datasets,
  scoring, reading results back (checked as on entry);
- `run`: `suite run`: every (dataset, method, seed) job, here or on a dask cluster (`jobs`);
- `report`: the leaderboard with intervals and paired comparisons;
- `robustness`: robustness curves over degradation levels;
- `builtin/`: the suites nerfgauge ships (smoke, standard, robustness);
- `commands`: the `suite` subcommands.
"""
