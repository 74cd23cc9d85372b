"""What every bench shares: its output folder (a nerfgauge "bench" folder of its kind), its
figures, and commands run as measured child processes.

Every bench writes into its own OUT, claimed as a nerfgauge "bench" folder of its kind
(`claim_bench_folder`: marker and lock), so reruns of the same bench continue in it and
a folder that is not a bench's is refused untouched. A case's dataset and run from an
earlier run are deleted only through their own markers (`core.folders.remove_owned`).
Figures are ratios and orderings within one run; absolute seconds depend on the machine.
"""

from __future__ import annotations

import sys

from nerfgauge.core.folders import claim_folder, recipe_hash
from nerfgauge.methods.measure import run_process


def claim_bench_folder(out, bench: str):
    """claim_folder(out) as a "bench" folder of `bench` ("train", "scaling", "hard"): a rerun
    of the same bench continues in it (each case replaces its own outputs), another bench's
    folder or anyone else's is refused."""
    return claim_folder(out, "bench", recipe_hash({"bench": bench}))


def run_child(argv: list) -> tuple[int, float, float]:
    """Run `python -m nerfgauge.cli ARGV`; returns (exit code, wall seconds, peak RSS MB),
    the peak the child's own (methods.measure.run_process), not this process's carried into it."""
    finished = run_process([sys.executable, "-m", "nerfgauge.cli", *argv])
    return finished.status, finished.seconds, (finished.peak_memory_bytes or 0) / 2**20


def first_time_reaching(log: list, psnr: float):
    """Training seconds of the first log entry whose val PSNR is at least `psnr`; None if none is."""
    for entry in log:
        if entry["val_psnr"] >= psnr:
            return entry["seconds"]
    return None
