"""The LPIPS feature cache's saving: `python -m nerfgauge.eval.lpips_cache_bench DATASET
[--protocol nerfbaselines] [--split test] [--repeats 1] [--uncached] [--work DIR]`.

Scores two "methods" against DATASET's `split` with `evaluate`, one after the other, with
a fresh feature cache (eval.lpips_cache) in a scratch folder: the first evaluate computes
and stores the ground truth's LPIPS features, the second (another method, the same ground
truth) reads them. Prints both evaluates' wall and CPU seconds and their ratio (second /
first; the target at 800 x 800 under NerfBaselines' protocol: at most 0.6; --repeats N
pairs, each with a fresh cache, and the median ratio), then scores the first method again
from the warm cache and says whether its LPIPS values are the same, bit for bit.
--uncached also times the first method with the cache off (what every evaluate cost
before). The two methods are the ground truth plus seeded Gaussian noise (sigma 0.02 and
0.05), alpha kept.

A dataset at the field's resolution with few test views:

    nerfgauge generate primitives --res 800 --views 4 --test-views 3 --val-views 1 --spp 4 --out DS
    python -m nerfgauge.eval.lpips_cache_bench DS [--repeats 3]

Needs the LPIPS weights (`nerfgauge lpips install --net all`).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from nerfgauge.core import dataset, owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.images import write_png
from nerfgauge.eval import lpips_cache
from nerfgauge.eval.evaluate import evaluate
from nerfgauge.eval.lpips import NOT_AVAILABLE
from nerfgauge.eval.protocols import get

METHOD_NOISE = {"method_a": 0.02, "method_b": 0.05}  # sigma of each method's noise on [0, 1]


def write_methods(root, split: str, folder: Path) -> dict:
    """{method: prediction folder}: the split's ground truth plus seeded Gaussian noise per
    method, 8-bit RGBA PNGs named as evaluate looks for them."""
    ds = dataset.Dataset(root)
    cameras = ds.cameras(split)
    folders = {}
    for index, (method, sigma) in enumerate(METHOD_NOISE.items()):
        rng = np.random.default_rng(index)
        out = folder / method
        for stem in cameras.stems:
            rgba = ds.rgba_of(stem, cameras.intrinsics)
            noisy = np.clip(rgba[..., :3] + rng.normal(0.0, sigma, rgba[..., :3].shape), 0.0, 1.0)
            image = np.concatenate([noisy, rgba[..., 3:]], -1)
            owned.make_folder((out / stem).parent)
            write_png(out / f"{stem}.png", np.round(image * 255).astype(np.uint8))
        folders[method] = out
    return folders


@contextmanager
def _environment(name: str, value: str):
    before = os.environ.get(name)
    os.environ[name] = value
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = before


def _timed_evaluate(root, pred: Path, split: str, protocol: str, out: Path) -> tuple[dict, dict]:
    """({"seconds": wall, "cpu_seconds": this process's CPU time, all threads}, the document)."""
    wall, cpu = time.perf_counter(), time.process_time()
    document = evaluate(root, pred, split, out=out, protocol=protocol, held_out=False)
    return {"seconds": time.perf_counter() - wall, "cpu_seconds": time.process_time() - cpu}, document


def _lpips_columns(document: dict) -> dict:
    metrics = [m for m in document["mean"] if m.startswith("lpips")]
    return {m: [frame[m] for frame in document["frames"]] for m in metrics}


def bench_lpips_cache(root, *, protocol: str = "nerfbaselines", split: str = "test", work=None,
                      uncached: bool = False, repeats: int = 1) -> dict:
    """Time two methods' evaluates against `root`'s `split`, each repeat with a fresh LPIPS
    feature cache: {"runs": [{"first": {"seconds", "cpu_seconds"}, "second": {...}}, ...],
    "ratio" and "cpu_ratio" (the median over the repeats of second / first, wall and CPU
    time: on a shared machine the CPU time says more), "uncached" (the first method with
    the cache off, or None), "frames", "width", "height", "protocol", "same_with_cache" (the
    first method's LPIPS equal, bit for bit, scored again from the warm cache and cold)}.
    work: a folder for the predictions and the caches (default a temporary one, removed)."""
    import torch  # noqa: F401  torch: imported before the clock starts, not inside the first evaluate

    get(protocol)
    if not isinstance(repeats, int) or repeats < 1:
        raise InputError(f"repeats must be a whole number of at least 1, got {repeats!r}")
    if work is None:
        with tempfile.TemporaryDirectory(prefix="nerfgauge-lpips-cache-bench-") as scratch:
            return bench_lpips_cache(root, protocol=protocol, split=split, work=Path(scratch), uncached=uncached,
                                     repeats=repeats)
    work = owned.make_folder(Path(work))
    methods = write_methods(root, split, work / "predictions")
    first, second = methods.values()
    cameras = dataset.Dataset(root).cameras(split)
    result = {"protocol": protocol, "split": split, "frames": len(cameras.stems),
              "width": cameras.intrinsics.width, "height": cameras.intrinsics.height, "uncached": None, "runs": []}
    if uncached:
        with _environment(lpips_cache.FOLDER_ENV, lpips_cache.OFF):
            result["uncached"], _ = _timed_evaluate(root, first, split, protocol, work / "uncached.json")
    for repeat in range(repeats):
        cache = work / f"cache-{repeat}"
        owned.remove_tree(cache)  # each repeat starts cold
        with _environment(lpips_cache.FOLDER_ENV, str(cache)):
            run = {}
            run["first"], cold = _timed_evaluate(root, first, split, protocol, work / "first.json")
            if any(note.startswith("n/a") for note in cold["notes"].values() if isinstance(note, str)):
                raise InputError(f"LPIPS {NOT_AVAILABLE}: nothing to cache")
            run["second"], _ = _timed_evaluate(root, second, split, protocol, work / "second.json")
            result["runs"].append(run)
    with _environment(lpips_cache.FOLDER_ENV, str(work / f"cache-{repeats - 1}")):
        _, warm = _timed_evaluate(root, first, split, protocol, work / "first-again.json")
    for name, unit in (("ratio", "seconds"), ("cpu_ratio", "cpu_seconds")):
        result[name] = float(np.median([run["second"][unit] / run["first"][unit] for run in result["runs"]]))
    result["same_with_cache"] = _lpips_columns(cold) == _lpips_columns(warm)
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--protocol", default="nerfbaselines")
    parser.add_argument("--split", default="test")
    parser.add_argument("--repeats", type=int, default=1, help="cold-then-warm pairs, each with a fresh cache")
    parser.add_argument("--uncached", action="store_true", help="also time the first method with the cache off")
    parser.add_argument("--work", type=Path, default=None, help="keep predictions and caches here (default: temporary)")
    args = parser.parse_args(argv)
    try:
        result = bench_lpips_cache(args.dataset, protocol=args.protocol, split=args.split, work=args.work,
                                   uncached=args.uncached, repeats=args.repeats)
    except InputError as error:
        print(f"lpips_cache_bench: error: {error}", file=sys.stderr)
        return 2

    def times(t):
        return f"{t['seconds']:8.2f} s wall {t['cpu_seconds']:8.2f} s CPU"

    print(f"LPIPS feature cache, {result['frames']} frames of {result['width']} x {result['height']}, "
          f"protocol {result['protocol']}:")
    if result["uncached"] is not None:
        print(f"  first method, cache off:           {times(result['uncached'])}")
    for run in result["runs"]:
        print(f"  first method, cold cache (stores): {times(run['first'])}")
        print(f"  second method, warm cache:         {times(run['second'])}")
    print(f"  ratio second / first:              {result['ratio']:8.3f} wall {result['cpu_ratio']:8.3f} CPU"
          + (f" (median of {len(result['runs'])})" if len(result["runs"]) > 1 else ""))
    print(f"  LPIPS warm == cold, bit for bit:   {result['same_with_cache']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
