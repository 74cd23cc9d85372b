"""Scoring predictions against a dataset: metrics, baselines, reports, benchmark, CI thresholds."""
