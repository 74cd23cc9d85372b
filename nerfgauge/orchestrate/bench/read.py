"""`nerfgauge bench read`: what validating a dataset on load costs (RELIABILITY.md;
BENCHMARKS.md, "Reading a dataset with validation on load").

Every file a command reads is confined to the dataset root, checked against the
manifest's size and (by default) sha256, and its header checked before decoding. This
bench reads a dataset the way training does (every PNG of a split) and the way evaluate
does (PNG, distance, z-depth and mask of every frame), with the sha256 check on and off,
interleaved so both see the same machine load. CPU seconds of this process, best of
`repeats`: the machine is shared, and the best run is the least disturbed one.
"""

from __future__ import annotations

import time

from nerfgauge.core.dataset import Dataset

READS = {
    "training (PNG of every frame)": lambda ds, split, i: ds.image(split, i),
    "evaluate (PNG, distance, z-depth, mask)": lambda ds, split, i: (ds.image(split, i), ds.depth(split, i),
                                                                     ds.depth(split, i, kind="z"), ds.mask(split, i)),
}


def time_read(root, split: str, read, verify_hashes: bool) -> float:
    """CPU seconds to open `root` and apply `read` to every frame of `split`."""
    start = time.process_time()
    ds = Dataset(root, verify_hashes=verify_hashes)
    for index in range(len(ds.frames(split))):
        read(ds, split, index)
    return time.process_time() - start


def bench_read(root, split: str = "train", repeats: int = 15) -> list[dict]:
    """Rows {"read", "frames", "ms_sizes_only", "ms_sha256"}: best-of-`repeats` CPU ms."""
    frames = len(Dataset(root).frames(split))
    rows = []
    for name, read in READS.items():
        best = {False: float("inf"), True: float("inf")}
        for _ in range(repeats):
            for verify in (False, True):
                best[verify] = min(best[verify], time_read(root, split, read, verify))
        rows.append({"read": name, "frames": frames, "ms_sizes_only": 1e3 * best[False], "ms_sha256": 1e3 * best[True]})
    return rows


def table_markdown(rows: list[dict]) -> str:
    lines = ["| read | frames | CPU ms, sizes only | CPU ms, sizes + sha256 | sha256 cost |", "|---|---|---|---|---|"]
    for row in rows:
        lines.append(f"| {row['read']} | {row['frames']} | {row['ms_sizes_only']:.1f} | {row['ms_sha256']:.1f} | "
                     f"{row['ms_sha256'] / row['ms_sizes_only']:.2f}x |")
    return "\n".join(lines)
