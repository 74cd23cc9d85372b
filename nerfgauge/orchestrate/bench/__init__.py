"""The benchmarks, every one run as `nerfgauge bench NAME` (`commands`): speed against error,
measured in one run on this machine, each into its own bench folder (`common`).

- `generate`: the generator's time against Mitsuba's own render time (the overhead ratio).
- `train`: scenes x variants x budgets: PSNR, SSIM, depth, time, size, memory; Pareto plots.
- `scaling`: time-to-PSNR and render time against resolution and views; generation time
  against views and spp.
- `hard`: the hard scenes through generate, brief training and evaluate, audited for NaN/inf.
- `targets`: the reference NeRF's targets in one command.
- `parametrisation`: the automatic parametrisation against each forced one on captures in no
  bench (issue 52).
- `lens`: defocus: the NeRF through a thin lens against refocused light fields.
- `read`: what validating a dataset on load costs.
- `colmap`: what the COLMAP export adds to `generate`.
- `dask`: views per second on a local dask cluster of 1 and of 2 workers.
- `lpips`: LPIPS-Alex speed, as evaluate batches it.
- `lpips-cache`: what the ground truth's LPIPS feature cache saves a second method scored
  against the same ground truth.
"""
