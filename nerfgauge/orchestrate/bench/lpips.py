"""`nerfgauge bench lpips [--frames 100] [--res 128] [--repeats 3]`: LPIPS-Alex speed.

Scores `frames` random image pairs of res x res pixels through eval.lpips.LpipsBatch (as
evaluate does) and prints the wall time of each repeat and the best. Needs the weights
(`nerfgauge lpips install`).
"""

from __future__ import annotations

import time

import numpy as np

from nerfgauge.core.errors import InputError
from nerfgauge.eval.lpips import NOT_AVAILABLE, LpipsBatch, load_lpips


def seconds_for(model, pred: np.ndarray, gt: np.ndarray) -> float:
    """Wall seconds to score [N, H, W, 3] pairs frame by frame through LpipsBatch."""
    start = time.perf_counter()
    batch = LpipsBatch(model)
    for p, g in zip(pred, gt):
        batch.add(p, g)
    batch.scores()
    return time.perf_counter() - start


def bench_lpips(frames: int, res: int, repeats: int) -> list:
    """Seconds of each repeat to score `frames` random pairs of res x res pixels (LPIPS-Alex)."""
    model = load_lpips()
    if model is None:
        raise InputError(f"bench lpips needs the LPIPS weights: {NOT_AVAILABLE}")
    rng = np.random.default_rng(0)
    pred = rng.random((frames, res, res, 3), dtype=np.float32)
    gt = np.clip(pred + rng.normal(0, 0.1, pred.shape).astype(np.float32), 0, 1)
    return [seconds_for(model, pred, gt) for _ in range(repeats)]
