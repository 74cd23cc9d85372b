"""Orchestration, the layer above the stages: benchmarks (`bench*`) and benchmark suites
(`suite*`, definitions in `suites/*.toml`) that generate datasets, train models, and score
them through each stage's public functions. `nerfgauge.run` (the `run` pipeline) and
`nerfgauge.api` sit on this layer too; the stages never import it."""
