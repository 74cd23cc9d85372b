"""Scoring predictions against a dataset: metrics, prediction files, geometry, baselines,
reports, the CI gate (benchmarks and suites: nerfgauge.orchestrate)."""
