"""`nerfgauge bench lpips-cache DATASET`: what the ground truth's LPIPS feature cache
(eval.lpips_cache) saves when a second method is scored against the same ground truth.

    nerfgauge bench lpips-cache DATASET [--protocol nerfbaselines] [--split test] [--repeats 1]
                                        [--uncached] [--out bench-out/lpips-cache]

Scores two "methods" against DATASET's `split` with `evaluate`, one after the other, with a
fresh feature cache in OUT: the first evaluate computes and stores the ground truth's
features, the second (another method, the same ground truth) reads them. Prints both
evaluates' wall and CPU seconds (this process, every thread) and their ratios, second /
first: the target at 800 x 800 under NerfBaselines' protocol is at most 0.6 (issue 49).
--repeats N: N pairs, each with a fresh cache, and the median ratios. Then scores the
first method again from the warm cache and says whether its LPIPS values are the same,
bit for bit. --uncached also times the first method with the cache off (what every
evaluate cost before). The two methods are the ground truth plus seeded Gaussian noise
(sigma 0.02 and 0.05), alpha kept. The load average before and after is recorded: on a
shared machine the CPU seconds say more than the wall seconds.

OUT (a bench folder) gets lpips-cache.json (every time, the ratios, the command) and
lpips-cache.png; the methods' renders and the evaluations stay in it, the caches do not
(about 340 MB a frame at 800 x 800 under NerfBaselines' protocol). The cache's size cap
is the environment's (NERFGAUGE_LPIPS_CACHE_GB): a split whose features exceed it is
partly computed again, which the ratio shows.

A dataset at the field's resolution (needs `nerfgauge lpips install --net all`):

    nerfgauge generate primitives --res 800 --views 4 --test-views 20 --val-views 1 --spp 4 --out DS
    nerfgauge bench lpips-cache DS
"""

from __future__ import annotations

import os
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from nerfgauge.core import dataset, owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_json
from nerfgauge.core.images import write_png
from nerfgauge.eval import lpips_cache
from nerfgauge.eval.evaluate import evaluate
from nerfgauge.eval.lpips import LABELS, NOT_AVAILABLE, weights_path
from nerfgauge.eval.protocols import get
from nerfgauge.eval.report import plain_text, save_png
from nerfgauge.orchestrate.bench.common import claim_bench_folder

METHOD_NOISE = {"method_a": 0.02, "method_b": 0.05}  # sigma of each method's noise on [0, 1]


def write_methods(root, split: str, folder: Path) -> dict:
    """{method: prediction folder}: the split's ground truth plus seeded Gaussian noise per
    method, 8-bit RGBA PNGs named as evaluate looks for them (each folder made afresh)."""
    ds = dataset.Dataset(root)
    cameras = ds.cameras(split)
    made = {}
    for index, (method, sigma) in enumerate(METHOD_NOISE.items()):
        rng = np.random.default_rng(index)
        out = folder / method
        owned.remove_tree(out)
        for stem in cameras.stems:
            rgba = ds.rgba_of(stem, cameras.intrinsics)
            noisy = np.clip(rgba[..., :3] + rng.normal(0.0, sigma, rgba[..., :3].shape), 0.0, 1.0)
            image = np.concatenate([noisy, rgba[..., 3:]], -1)
            owned.make_folder((out / stem).parent)
            write_png(out / f"{stem}.png", np.round(image * 255).astype(np.uint8))
        made[method] = out
    return made


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


def bench_lpips_cache(root, out: Path, *, protocol: str = "nerfbaselines", split: str = "test",
                      uncached: bool = False, repeats: int = 1) -> dict:
    """Time two methods' evaluates against `root`'s `split`, each repeat with a fresh LPIPS
    feature cache in OUT (a bench folder), and write OUT/lpips-cache.json and .png. Returns
    {"runs": [{"first": {"seconds", "cpu_seconds"}, "second": {...}}, ...], "ratio" and
    "cpu_ratio" (the median over the repeats of second / first, wall and CPU time),
    "uncached" (the first method with the cache off, or None), "frames", "width", "height",
    "protocol", "split", "same_with_cache" (the first method's LPIPS equal, bit for bit,
    scored again from the warm cache and cold), "load_average" (before, after), "command"}."""
    import torch  # noqa: F401  torch: imported before the clock starts, not inside the first evaluate

    chosen = get(protocol)
    if not isinstance(repeats, int) or isinstance(repeats, bool) or repeats < 1:
        raise InputError(f"repeats must be a whole number of at least 1, got {repeats!r}")
    for net in dict.fromkeys((chosen.lpips_net, *(net for _, net in chosen.extra_lpips))):
        if not weights_path(net).is_file():  # refused before minutes of work, not after the first evaluate
            raise InputError(f"bench lpips-cache: {LABELS[net]}: {NOT_AVAILABLE}")
    cameras = dataset.Dataset(root).cameras(split)
    out = Path(out)
    with claim_bench_folder(out, "lpips-cache"):
        first, second = write_methods(root, split, out / "predictions").values()
        evaluations = owned.make_folder(out / "evaluations")
        result = {"protocol": protocol, "split": split, "frames": len(cameras.stems),
                  "width": cameras.intrinsics.width, "height": cameras.intrinsics.height, "uncached": None,
                  "runs": [], "load_average": [os.getloadavg()], "cpu_count": os.cpu_count(),
                  "command": f"nerfgauge bench lpips-cache {root} --protocol {protocol} --split {split} "
                             f"--repeats {repeats}" + (" --uncached" if uncached else "") + f" --out {out}"}
        if uncached:
            with _environment(lpips_cache.FOLDER_ENV, lpips_cache.OFF):
                result["uncached"], _ = _timed_evaluate(root, first, split, protocol, evaluations / "uncached.json")
        for repeat in range(repeats):
            cache = out / "cache"
            owned.remove_tree(cache)  # each repeat starts cold
            with _environment(lpips_cache.FOLDER_ENV, str(cache)):
                run = {}
                run["first"], cold = _timed_evaluate(root, first, split, protocol, evaluations / "first.json")
                if any(note.startswith("n/a") for note in cold["notes"].values() if isinstance(note, str)):
                    raise InputError(f"bench lpips-cache: LPIPS {NOT_AVAILABLE}: nothing to cache")
                run["second"], _ = _timed_evaluate(root, second, split, protocol, evaluations / "second.json")
                result["runs"].append(run)
        with _environment(lpips_cache.FOLDER_ENV, str(out / "cache")):
            _, warm = _timed_evaluate(root, first, split, protocol, evaluations / "first-again.json")
        owned.remove_tree(out / "cache")  # gigabytes at the field's resolution
        result["load_average"].append(os.getloadavg())
        for name, unit in (("ratio", "seconds"), ("cpu_ratio", "cpu_seconds")):
            result[name] = float(np.median([run["second"][unit] / run["first"][unit] for run in result["runs"]]))
        result["same_with_cache"] = _lpips_columns(cold) == _lpips_columns(warm)
        write_json(out / "lpips-cache.json", result)
        plot(result, out / "lpips-cache.png")
    return result


def plot(result: dict, path: Path) -> None:
    """Wall and CPU seconds of each evaluate (the cache off, cold, warm), PNG."""
    from matplotlib.figure import Figure  # matplotlib: only when a bench draws

    bars = ([("cache off", result["uncached"])] if result["uncached"] else []) + \
        [(f"{label} ({i + 1})", run[key]) for i, run in enumerate(result["runs"])
         for key, label in (("first", "first, cold"), ("second", "second, warm"))]
    figure = Figure(figsize=(6.4, 3.6), dpi=100)
    axes = figure.add_subplot()
    x = np.arange(len(bars))
    axes.bar(x - 0.2, [t["seconds"] for _, t in bars], 0.4, label="wall")
    axes.bar(x + 0.2, [t["cpu_seconds"] for _, t in bars], 0.4, label="CPU")
    axes.set_xticks(x, [label for label, _ in bars], fontsize=8)
    axes.set_ylabel("seconds per evaluate")
    axes.set_title(plain_text(f"LPIPS feature cache: {result['frames']} frames of {result['width']} x "
                              f"{result['height']}, {result['protocol']}\nsecond / first {result['ratio']:.3f} "
                              f"wall, {result['cpu_ratio']:.3f} CPU"), fontsize=9)
    axes.legend()
    figure.tight_layout()
    save_png(figure, path)


def summary(result: dict) -> str:
    """The printed table: every evaluate's seconds, the ratios, the exactness check."""
    def times(t):
        return f"{t['seconds']:8.2f} s wall {t['cpu_seconds']:8.2f} s CPU"

    lines = [f"LPIPS feature cache, {result['frames']} frames of {result['width']} x {result['height']}, "
             f"protocol {result['protocol']} (load average {result['load_average'][0][0]:.2f} before, "
             f"{result['load_average'][-1][0]:.2f} after, {result['cpu_count']} CPUs):"]
    if result["uncached"] is not None:
        lines.append(f"  first method, cache off:           {times(result['uncached'])}")
    for run in result["runs"]:
        lines.append(f"  first method, cold cache (stores): {times(run['first'])}")
        lines.append(f"  second method, warm cache:         {times(run['second'])}")
    lines.append(f"  ratio second / first:              {result['ratio']:8.3f} wall {result['cpu_ratio']:8.3f} CPU"
                 + (f" (median of {len(result['runs'])})" if len(result["runs"]) > 1 else ""))
    lines.append(f"  LPIPS warm == cold, bit for bit:   {result['same_with_cache']}")
    return "\n".join(lines)
