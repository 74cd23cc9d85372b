"""Benchmark suite definitions (*.toml), shipped as package data: nerfgauge.eval.suite reads them."""
