"""The `nerfgauge` command: a thin dispatcher over the stage packages."""
