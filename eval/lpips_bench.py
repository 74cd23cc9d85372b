"""LPIPS-Alex speed: `python -m nerfgauge.eval.lpips_bench [--frames 100] [--res 128] [--repeats 3]`.

Scores `frames` random image pairs of res x res pixels through eval.lpips.LpipsBatch (as
evaluate does) and prints the wall time of each repeat and the best. Needs the weights
(`nerfgauge lpips install`).
"""

from __future__ import annotations

import argparse
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


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--res", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    model = load_lpips()
    if model is None:
        raise SystemExit(f"LPIPS {NOT_AVAILABLE}")
    rng = np.random.default_rng(0)
    pred = rng.random((args.frames, args.res, args.res, 3), dtype=np.float32)
    gt = np.clip(pred + rng.normal(0, 0.1, pred.shape).astype(np.float32), 0, 1)
    times = [seconds_for(model, pred, gt) for _ in range(args.repeats)]
    print(f"LPIPS-Alex, {args.frames} frames of {args.res} px: " + ", ".join(f"{t:.2f}" for t in times)
          + f" s (best {min(times):.2f} s)")


if __name__ == "__main__":
    try:
        main()
    except InputError as error:
        raise SystemExit(str(error)) from None
