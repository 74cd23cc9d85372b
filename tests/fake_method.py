"""A user's method as a Python class for the suite tests (tests/test_suite_methods.py),
named in a suite as `fake_method:Grey`: a constant grey image per frame, no training."""

from __future__ import annotations

import time
from pathlib import Path

from fake_tool import frames
from PIL import Image

from nerfgauge.methods import Method, Needs, RenderResult, TrainResult


class Grey(Method):
    """A constant mid-grey image per frame, opaque: a non-learned method of the user's."""

    name = "grey"
    summary = "a constant grey image (tests)"
    needs = Needs()
    learned = False
    accepts_budget = False

    def train(self, request):
        return TrainResult(seconds=0.0, steps=None)

    def render(self, run, dataset, split, out, *, overwrite=False, progress=False):
        start = time.perf_counter()
        names = frames(Path(dataset), split)
        for rel in names:
            size = Image.open(Path(dataset) / f"{rel}.png").size
            target = Path(out) / f"{rel}.png"
            target.parent.mkdir(parents=True, exist_ok=True)
            Image.new("RGBA", size, (128, 128, 128, 255)).save(target)
        return RenderResult(out=Path(out), frames=len(names), seconds=time.perf_counter() - start)
