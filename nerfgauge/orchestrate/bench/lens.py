"""Defocus bench: NeRF through a thin lens vs the refocused light field vs the nearest view,
all scored against Mitsuba's thin-lens ground truth, at several aperture radii.

    nerfgauge bench lens --out DIR [--apertures 0.1,0.2] [--budget-seconds 120]

One light-field capture of the scene (--layout lightfield: a grid of --views training
cameras facing +Y, off-grid test cameras on the same plane) is generated once per aperture
(aperture 0 is the pinhole dataset; the others differ only in their test views, rendered
through the lens focused at --focus-distance, default the camera distance: the scene's
centre plane). The compact NeRF trains once, on the pinhole dataset's training views (the
same pixels as every lens dataset's), for --budget-seconds; then for every aperture:

- nerf: `nerfgauge render RUN --dataset DS --other-dataset --aperture-samples N` (the field integrates the lens);
- refocus: `nerfgauge baseline DS --method refocus` (shift and add over the camera grid);
- lightfield-quadrilinear: the two-plane light field, which has no lens (a pinhole view);
- nearest: the nearest training view, unchanged (sharp everywhere);

each evaluated with `nerfgauge evaluate DS` (each step calls the stage function that command
calls: nerf.render_views.render_split, methods.baselines.write_baseline, eval.evaluate).
Writes OUT/lens.json (every metrics document's means, the render costs), OUT/lens.md
(PSNR/SSIM against aperture), OUT/lens.png (an image row per method at each aperture) and
OUT/lens.html. The NeRF's defocus cost is its
milliseconds per lens frame against per pinhole frame (timing.json). Times are of this
machine at the time of the run.
"""

from __future__ import annotations

import json
from pathlib import Path

from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, write_bytes_atomic, write_json
from nerfgauge.methods.baselines import baseline_folder, write_baseline
from nerfgauge.eval.evaluate import evaluate
from nerfgauge.eval.report import _data_uri, aperture_table, focus_rows, page_html, sortable_table_html
from nerfgauge.generate.pipeline import GenerateConfig, generate
from nerfgauge.orchestrate.bench.common import claim_bench_folder

METHODS = ("nerf", "refocus", "lightfield-quadrilinear", "nearest")


def run_lens_bench(out, *, scene: str = "primitives", views: int = 64, test_views: int = 6, res: int = 96,
                   spp: int = 64, radius: float = 3.5, focus_distance=None, apertures=(0.1, 0.2),
                   budget_seconds: float = 120.0, aperture_samples: int = 16, threads: int = 2) -> dict:
    from nerfgauge.nerf.config import TrainConfig  # loads torch
    from nerfgauge.nerf.render_views import render_split  # torch
    from nerfgauge.nerf.train import train  # torch

    out = Path(out)
    focus = radius if focus_distance is None else focus_distance
    all_apertures = [0.0] + [float(a) for a in apertures]
    with claim_bench_folder(out, "lens"):
        datasets = {}
        for aperture in all_apertures:
            datasets[aperture] = out / "data" / f"aperture_{aperture:g}"
            lens = {"aperture": aperture, "focus_distance": focus} if aperture else {}
            generate(GenerateConfig(scene=scene, layout="lightfield", views=views, val_views=2, test_views=test_views,
                                    width=res, height=res, spp=spp, radius=radius, **lens), datasets[aperture],
                     progress=False)
        run = out / "run"
        if not (run / "model.pt").is_file():
            train(TrainConfig(dataset=str(datasets[0.0]), budget_seconds=budget_seconds, threads=threads), run,
                  overwrite=True, progress=False)
        preds, scores, costs = {m: {} for m in METHODS}, {m: {} for m in METHODS}, {}
        for aperture, root in datasets.items():
            for method in METHODS:
                pred = out / "pred" / f"aperture_{aperture:g}" / method
                if method == "nerf":
                    render_split(run, "test", pred, threads=threads, overwrite=True, progress=False,
                                 aperture_samples=aperture_samples, dataset=root, other_dataset=True)
                else:
                    with baseline_folder(root, method, pred, "test", overwrite=True):
                        write_baseline(root, method, pred, "test")
                evaluate(root, pred)
                preds[method][aperture] = pred
                scores[method][aperture] = read_json(pred / "metrics.json")
                costs.setdefault(method, {})[aperture] = read_json(pred / "timing.json")
        stem = f"test/r_{0:03d}"
        focus_rows(datasets, preds, stem, out / "lens.png")
        table = aperture_table(scores, all_apertures)
        nerf_pinhole = scores["nerf"][0.0]["mean"]["psnr"]
        summary = {
            "scene": scene, "views": views, "test_views": test_views, "resolution": res, "spp": spp,
            "camera_distance": radius, "focus_distance": focus, "apertures": all_apertures,
            "budget_seconds": budget_seconds, "aperture_samples": aperture_samples,
            "mean": {m: {f"{a:g}": scores[m][a]["mean"] for a in all_apertures} for m in METHODS},
            "nerf_psnr_minus_pinhole": {f"{a:g}": scores["nerf"][a]["mean"]["psnr"] - nerf_pinhole
                                        for a in all_apertures},
            "ms_per_frame": {m: {f"{a:g}": costs[m][a].get("ms_per_frame") for a in all_apertures} for m in METHODS},
            "nerf_ms_per_lens_frame": {f"{a:g}": costs["nerf"][a].get("ms_per_lens_frame") for a in all_apertures},
            "nerf_ms_per_pinhole_frame": costs["nerf"][0.0].get("ms_per_frame"),
        }
        write_json(out / "lens.json", summary)
        markdown = _markdown(table, summary)
        write_bytes_atomic(out / "lens.md", markdown.encode())
        notes = [f"{scene}, light-field grid of {views} cameras at distance {radius:g}, {res} px, {spp} spp; "
                 f"focus distance {focus:g}; NeRF trained {budget_seconds:g} s on the pinhole training views, "
                 f"{aperture_samples} lens samples per pixel"]
        body = (sortable_table_html(table) + f"<h2>frame {stem}: one row per method</h2>"
                f"<img src='{_data_uri(out / 'lens.png')}' alt='focus rows'>")
        write_bytes_atomic(out / "lens.html", page_html("defocus: methods against the thin-lens truth", body, notes))
        print(markdown)
        return summary


def _markdown(table: list, summary: dict) -> str:
    head, *rows = table
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    deltas = ", ".join(f"A={a}: {d:+.2f} dB" for a, d in summary["nerf_psnr_minus_pinhole"].items())
    lens_ms = ", ".join(f"A={a}: {v:.0f} ms" for a, v in summary["nerf_ms_per_lens_frame"].items() if v)
    lines += ["", f"NeRF PSNR minus its pinhole PSNR: {deltas}.",
              f"NeRF per frame: pinhole {summary['nerf_ms_per_pinhole_frame']:.0f} ms; through the lens "
              f"({summary['aperture_samples']} samples + the pinhole depth pass) {lens_ms}."]
    return "\n".join(lines) + "\n"
