"""What the COLMAP export adds to `generate` (issue 32: at most 5% at 128 px, `sfm` excluded):

    python -m nerfgauge.generate.bench_colmap [--pairs 3] [--res 128] [--views 100] [--points surface]

Each run is a fresh process generating `primitives` into a new folder; a pair is one run
with the export and one with `generate.export.export_colmap` replaced by a no-op, their
order alternating from pair to pair, so a machine whose load drifts hurts both alike.
Prints every run, the ratio of the means and of the medians, and the export's own seconds
as `generate` measured them inside the runs with it.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

RUN = r'''
import json, sys, time
from nerfgauge.generate import export
from nerfgauge.generate.pipeline import GenerateConfig, generate
out, mode, res, views, points = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
if mode == "without":
    export.export_colmap = lambda *args, **kwargs: None
    export.export_current = lambda *args, **kwargs: True
start = time.perf_counter()
result = generate(GenerateConfig(scene="primitives", width=res, height=res, views=views), out, progress=False,
                  points=points)
print(json.dumps({"seconds": time.perf_counter() - start, "export_seconds": (result["export"] or {}).get("seconds", 0.0)}))
'''


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--res", type=int, default=128)
    parser.add_argument("--views", type=int, default=100)
    parser.add_argument("--points", default="surface")
    args = parser.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="nerfgauge-bench-colmap-") as work:
        for pair in range(args.pairs):
            for mode in ("with", "without") if pair % 2 == 0 else ("without", "with"):
                out = Path(work) / f"{mode}-{pair}"
                done = subprocess.run([sys.executable, "-c", RUN, str(out), mode, str(args.res), str(args.views),
                                       args.points], capture_output=True, text=True, check=True)
                rows.append({"pair": pair, "mode": mode, **json.loads(done.stdout.splitlines()[-1])})
                print(json.dumps(rows[-1]), flush=True)
    with_export = [r["seconds"] for r in rows if r["mode"] == "with"]
    without = [r["seconds"] for r in rows if r["mode"] == "without"]
    export_seconds = [r["export_seconds"] for r in rows if r["mode"] == "with"]
    print(json.dumps({"ratio_of_means": statistics.mean(with_export) / statistics.mean(without),
                      "ratio_of_medians": statistics.median(with_export) / statistics.median(without),
                      "export_seconds_mean": statistics.mean(export_seconds),
                      "export_share": statistics.mean(export_seconds) / statistics.mean(with_export)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
