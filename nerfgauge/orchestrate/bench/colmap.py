"""`nerfgauge bench colmap`: what the COLMAP export adds to `generate` (at most 5% at 128 px,
`sfm` excluded):

    nerfgauge bench colmap [--pairs 3] [--res 128] [--views 100] [--points surface] [--out DIR]

Each run is a fresh process generating `primitives` into a new folder; a pair is one run
with the export and one with `generate.export.export_colmap` replaced by a no-op, their
order alternating from pair to pair, so a machine whose load drifts hurts both alike.
Prints every run, the ratio of the means and of the medians, and the export's own seconds
as `generate` measured them inside the runs with it.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
from pathlib import Path

from nerfgauge.core import owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_json
from nerfgauge.orchestrate.bench.common import claim_bench_folder

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


def bench_colmap(out: Path, pairs: int, res: int, views: int, points: str, log=print) -> dict:
    """Generate `pairs` x (with, without the export) into OUT/runs/ (a bench folder) and
    write OUT/colmap.json: every run and the ratios. Returns that document."""
    rows = []
    with claim_bench_folder(out, "colmap"):
        runs = owned.make_folder(out / "runs")
        for pair in range(pairs):
            for mode in ("with", "without") if pair % 2 == 0 else ("without", "with"):
                folder = runs / f"{mode}-{pair}"
                owned.remove_tree(folder)
                done = subprocess.run([sys.executable, "-c", RUN, str(folder), mode, str(res), str(views), points],
                                      capture_output=True, text=True)
                if done.returncode != 0:
                    raise InputError(f"bench colmap: generate {mode} the export failed: "
                                     + (done.stderr.strip().splitlines() or ["no message"])[-1])
                rows.append({"pair": pair, "mode": mode, **json.loads(done.stdout.splitlines()[-1])})
                log(json.dumps(rows[-1]))
        with_export = [r["seconds"] for r in rows if r["mode"] == "with"]
        without = [r["seconds"] for r in rows if r["mode"] == "without"]
        export_seconds = [r["export_seconds"] for r in rows if r["mode"] == "with"]
        document = {"runs": rows, "ratio_of_means": statistics.mean(with_export) / statistics.mean(without),
                    "ratio_of_medians": statistics.median(with_export) / statistics.median(without),
                    "export_seconds_mean": statistics.mean(export_seconds),
                    "export_share": statistics.mean(export_seconds) / statistics.mean(with_export),
                    "command": f"nerfgauge bench colmap --pairs {pairs} --res {res} --views {views} --points {points}"}
        write_json(out / "colmap.json", document)
    return document
