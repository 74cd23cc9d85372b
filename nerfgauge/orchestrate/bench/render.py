"""`nerfgauge bench render RUN [RUN ...]`: an edges run's default render against the render
before issue 52 (3 x 3 rays on every edge pixel of the centre render) and the centre rays
alone, on the same model in one process: milliseconds a frame and test PSNR of each, and
the ratios. Trains nothing.

    nerfgauge bench render RUN [RUN ...] [--split test] [--repeats 3] [--threads N]
                           [--out bench-out/render]

Each run is a compact NeRF trained with the `edges` pixel filter (`nerfgauge train DATASET
--steps N`, the automatic filter on most scenes). Its split is rendered by each render in
turn, `repeats` times, the order rotating each repeat so that every render sees the same
machine load on average; a render's time is the median over the repeats of timing.json's
ms_per_frame (model time, after a warm-up frame: nerf.render_views), and of its
cpu_ms_per_frame (every thread's CPU time: the work, which a loaded machine does not
inflate; the wall time is the figure on an idle one). Renders are
deterministic, so each is scored once, by `nerfgauge evaluate` (PSNR on white, the edge
and interior pixels apart).

OUT (a bench folder) gets render.json (every time, the scores, the ratios, the command)
and render.md; each run's renders and metrics stay in OUT/runs/<name>/<render>/.
"""

from __future__ import annotations

import os
import statistics
from pathlib import Path

from nerfgauge.core import owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_bytes_atomic, write_json
from nerfgauge.eval.evaluate import evaluate
from nerfgauge.nerf.config import RENDER_FILTERS, pixel_filter_for
from nerfgauge.orchestrate.bench.common import claim_bench_folder

# name -> render_split's settings: the run's default render (its chosen filter, sub-rays
# where the centre render changes), the render before issue 52, the centre rays alone
RENDERS = {
    "default": {},
    "edge-pixels-3x3": {"pixel_samples": 3, "sub_rays": "edge-pixels"},
    "centre": {"pixel_samples": 1},
}
BEFORE = "edge-pixels-3x3"


def _check_run(run: Path) -> dict:
    """The run's settings that the bench reports; InputError unless it is an edges run whose
    render gives edge pixels more rays (a centre-chosen run renders its centre rays only)."""
    from nerfgauge.nerf.checkpoint import load_model  # torch: kept off `nerfgauge --help`'s import path

    if not (run / "model.pt").is_file():
        raise InputError(f"bench render: {run} holds no model.pt (a run folder of nerfgauge train)")
    _, config = load_model(run / "model.pt")
    if pixel_filter_for(config)[0] != "edges" or RENDER_FILTERS.get(config.render_filter, 2) == 1:
        raise InputError(f"bench render: {run} is not an edges run that renders edge pixels with more rays "
                         f"(pixel filter {config.pixel_filter}, render filter {config.render_filter})")
    return {"dataset": config.dataset, "render_filter": config.render_filter, "steps": config.steps,
            "budget_seconds": config.budget_seconds}


def _names(runs: list) -> list:
    """A folder name per run: its own, numbered where two runs share one."""
    names = [Path(run).name or "run" for run in runs]
    return [f"{i}-{name}" if names.count(name) > 1 else name for i, name in enumerate(names)]


def bench_render(runs: list, out: Path, *, split: str = "test", repeats: int = 3, threads: int | None = None) -> dict:
    """Render every run's `split` by each of RENDERS, `repeats` times in rotating order, and
    score each once. Returns the document written to OUT/render.json: {"rows": [{"run",
    "name", "settings", "renders": {render: {"ms_per_frame": [each repeat], "ms": median,
    "psnr", "psnr_edges", "psnr_interior", "resolution"}}, "ms_ratio" and "psnr_change":
    default against BEFORE}], "command", "load_average"}."""
    from nerfgauge.nerf.render_views import render_split  # torch: kept off `nerfgauge --help`'s import path

    if not isinstance(repeats, int) or isinstance(repeats, bool) or repeats < 1:
        raise InputError(f"repeats must be a whole number of at least 1, got {repeats!r}")
    runs = [Path(run) for run in runs]
    if not runs:
        raise InputError("bench render: name at least one run folder")
    settings = [_check_run(run) for run in runs]  # every run refused before minutes of work
    out = Path(out)
    command = (f"nerfgauge bench render {' '.join(map(str, runs))} --split {split} --repeats {repeats}"
               + (f" --threads {threads}" if threads else "") + f" --out {out}")
    document = {"rows": [], "command": command, "load_average": [os.getloadavg()], "cpu_count": os.cpu_count()}
    with claim_bench_folder(out, "render"):
        for run, name, setting in zip(runs, _names(runs), settings):
            folder = owned.make_folder(out / "runs" / name)
            times, cpu_times = {render: [] for render in RENDERS}, {render: [] for render in RENDERS}
            timing = {}
            order = list(RENDERS)
            for repeat in range(repeats):
                for render in order[repeat % len(order):] + order[:repeat % len(order)]:
                    timing[render] = render_split(run, split, folder / render, threads=threads, overwrite=True,
                                                  progress=False, **RENDERS[render])
                    times[render].append(timing[render]["ms_per_frame"])
                    cpu_times[render].append(timing[render]["cpu_ms_per_frame"])
            renders = {}
            for render in RENDERS:
                scores = evaluate(timing[render]["dataset"], folder / render, split,
                                  out=folder / f"{render}-metrics.json", held_out=False)["mean"]
                renders[render] = {"ms_per_frame": times[render], "ms": statistics.median(times[render]),
                                   "cpu_ms_per_frame": cpu_times[render], "cpu_ms": statistics.median(cpu_times[render]),
                                   "psnr": scores.get("psnr"), "psnr_edges": scores.get("psnr_edges"),
                                   "psnr_interior": scores.get("psnr_interior"),
                                   "resolution": timing[render]["resolution"], "frames": timing[render]["frames"],
                                   "pixel_samples": timing[render]["pixel_samples"],
                                   "sub_rays": timing[render].get("sub_rays"),
                                   "change_step": timing[render].get("change_step")}
            document["rows"].append({"run": str(run), "name": name, "settings": setting, "renders": renders,
                                     "ms_ratio": renders["default"]["ms"] / renders[BEFORE]["ms"],
                                     "cpu_ratio": renders["default"]["cpu_ms"] / renders[BEFORE]["cpu_ms"],
                                     "psnr_change": renders["default"]["psnr"] - renders[BEFORE]["psnr"]})
        document["load_average"].append(os.getloadavg())
        write_json(out / "render.json", document)
        write_bytes_atomic(out / "render.md", (table_markdown(document) + "\n").encode())
    return document


def table_markdown(document: dict) -> str:
    """One row per run and render: resolution, ms a frame (median, and every repeat), PSNR."""
    lines = ["| run | resolution | render | ms a frame (median; each repeat) | CPU ms a frame | test PSNR | edges | "
             "interior |", "|---|---|---|---|---|---|---|---|"]
    for row in document["rows"]:
        for render, r in row["renders"].items():
            each = ", ".join(f"{ms:.1f}" for ms in r["ms_per_frame"])
            step = f" (change step {r['change_step']:g})" if r.get("change_step") is not None else ""
            lines.append(f"| {row['name']} | {r['resolution'][0]} x {r['resolution'][1]} | {render}{step} | "
                         f"{r['ms']:.1f} ({each}) | {r['cpu_ms']:.1f} | {_db(r['psnr'])} | {_db(r['psnr_edges'])} | "
                         f"{_db(r['psnr_interior'])} |")
    lines.append("")
    for row in document["rows"]:
        lines.append(f"- {row['name']}: default / {BEFORE} time {row['ms_ratio']:.3f} (CPU time {row['cpu_ratio']:.3f}), PSNR "
                     f"{row['psnr_change']:+.3f} dB")
    lines.append(f"\nCommand: `{document['command']}` (load average {document['load_average'][0][0]:.2f} before, "
                 f"{document['load_average'][-1][0]:.2f} after, {document['cpu_count']} CPUs)")
    return "\n".join(lines)


def _db(value) -> str:
    return "n/a" if value is None else f"{value:.2f}"
