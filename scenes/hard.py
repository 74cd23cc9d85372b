"""Hard cases that break NeRFs and harnesses (filled in by the hard-cases work)."""

RECIPES: dict = {}
