"""Benchmark suite definitions (*.toml), shipped as package data: nerfgauge.orchestrate.suite reads them."""
