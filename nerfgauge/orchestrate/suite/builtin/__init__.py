"""Benchmark suite definitions (*.toml), shipped as package data: nerfgauge.orchestrate.suite.definition reads them."""
