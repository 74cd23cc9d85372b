"""The report of a train-and-evaluate run: a metrics table against the baselines, the
speed-vs-error curve, an image grid, and one self-contained report.html that shows them.

Inputs are files only (metrics.json documents, a run's log.jsonl, render folders), so
any method's results can be reported the same way. Figures use matplotlib's object API
(Figure + Agg canvas): no global backend is switched.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import numpy as np
from nerfgauge.eval.error_maps import colour_error, colourize, depth_relative_error

from nerfgauge.core.dataset import open_dataset, read_depth, read_mask, read_rgba
from nerfgauge.core.files import atomic_path, write_bytes_atomic
from nerfgauge.core.images import read_exr_single, read_png

TABLE_METRICS = (("psnr", "PSNR dB", "{:.2f}"), ("ssim", "SSIM", "{:.4f}"), ("psnr_foreground", "foreground PSNR dB", "{:.2f}"),
                 ("depth_absrel", "depth AbsRel", "{:.4f}"),
                 ("depth_rmse", "depth RMSE", "{:.4f}"), ("depth_delta1", "depth δ<1.25", "{:.4f}"),
                 ("opacity_iou", "opacity IoU", "{:.4f}"))


def read_log(path) -> list[dict]:
    """A run's log.jsonl: one JSON object per line (val PSNR against training seconds)."""
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def ceiling_cell(psnr, ceiling) -> str:
    """The dataset's noise ceiling (evaluate's noise.psnr_ceiling), marked when the PSNR is
    within NOISE_FLOOR_DB of it."""
    from nerfgauge.eval.evaluate import NOISE_FLOOR_DB

    if ceiling is None:
        return "–"
    at_floor = psnr is not None and psnr >= ceiling - NOISE_FLOOR_DB
    return f"{ceiling:.2f}" + (" (at the noise floor: add spp)" if at_floor else "")


def metrics_table(rows: dict) -> list[list[str]]:
    """rows: {method: metrics.json document}. Returns a header row and one row per method."""
    table = [["method"] + [label for _, label, _ in TABLE_METRICS[:1]] + ["PSNR ceiling dB"]
             + [label for _, label, _ in TABLE_METRICS[1:]] + ["ms/frame"]]
    for method, document in rows.items():
        cells = [method]
        for key, _, fmt in TABLE_METRICS:
            mean, std = document["mean"].get(key), document["std"].get(key)
            cells.append("–" if mean is None else fmt.format(mean) + ("" if not std else f" ± {fmt.format(std)}"))
            if key == "psnr":
                cells.append(ceiling_cell(mean, (document.get("noise") or {}).get("psnr_ceiling")))
        ms = document.get("timing", {}).get("ms_per_frame")
        cells.append("–" if ms is None else f"{ms:.1f}")
        table.append(cells)
    return table


def plot_curves(curves: dict, out) -> None:
    """curves: {label: [log entries]} -> PNG of val PSNR against training seconds."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(6, 4), dpi=110)
    axes = figure.add_subplot()
    for label, entries in curves.items():
        points = [(e["seconds"], e["val_psnr"]) for e in entries if e.get("val_psnr") is not None]
        if points:
            axes.plot(*zip(*points), marker="o", markersize=3, label=label)
    axes.set_xlabel("training seconds")
    axes.set_ylabel("validation PSNR (dB)")
    axes.set_title("speed against error")
    axes.grid(alpha=0.3)
    axes.legend()
    figure.tight_layout()
    with atomic_path(out) as tmp:
        FigureCanvasAgg(figure).print_png(str(tmp))


def image_grid(dataset_root, pred_dir, out, split: str = "test", frames: int = 3, background=(1.0, 1.0, 1.0)) -> None:
    """Rows of (ground truth, prediction, colour error, predicted depth, depth error) PNG."""
    from nerfgauge.core.images import write_png

    ds = open_dataset(dataset_root)
    cameras = ds.cameras(split)
    bg = np.asarray(background, np.float32)
    rows = []
    for stem in cameras.stems[:frames]:
        gt = read_rgba(ds, stem, cameras.intrinsics)
        pred = read_png(Path(pred_dir) / (stem + ".png"))
        gt_rgb = gt[..., :3] * gt[..., 3:] + bg * (1 - gt[..., 3:])
        pred_rgb = pred[..., :3] * pred[..., 3:] + bg * (1 - pred[..., 3:]) if pred.shape[-1] == 4 else pred
        gt_depth = read_depth(ds, stem, cameras.intrinsics)
        mask = read_mask(ds, stem, cameras.intrinsics)
        depth_path = Path(pred_dir) / (stem + "_depth.exr")
        pred_depth = read_exr_single(depth_path) if depth_path.is_file() else np.zeros_like(gt_depth)
        far = float(gt_depth[mask].max()) if mask.any() else 1.0
        near = float(gt_depth[mask].min()) if mask.any() else 0.0
        depth_vis = colourize(np.where(pred_depth > 0, (far - pred_depth) / max(far - near, 1e-9), 0.0), 1.0, "viridis")
        tiles = [gt_rgb, pred_rgb, colourize(colour_error(pred_rgb, gt_rgb), 0.2, "magma") / 255.0,
                 depth_vis / 255.0, colourize(depth_relative_error(pred_depth, gt_depth, mask), 0.1, "viridis") / 255.0]
        rows.append(np.concatenate([np.clip(t[..., :3], 0, 1) for t in tiles], axis=1))
    write_png(out, np.round(np.concatenate(rows, axis=0) * 255).astype(np.uint8))


def _data_uri(path) -> str:
    return "data:image/png;base64," + base64.b64encode(Path(path).read_bytes()).decode()


def write_html(out, title: str, table: list, images: dict, notes: list[str]) -> None:
    """A self-contained page: the table and every image inlined as a data URI."""
    head, *body = table
    rows = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>" for row in body)
    figures = "".join(f"<h2>{html.escape(caption)}</h2><img src='{_data_uri(path)}' alt='{html.escape(caption)}'>"
                      for caption, path in images.items())
    notes_html = "".join(f"<li>{html.escape(n)}</li>" for n in notes)
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:4px 8px;text-align:right}}td:first-child{{text-align:left}}
img{{max-width:100%;image-rendering:pixelated}}</style></head><body>
<h1>{html.escape(title)}</h1><table><tr>{''.join(f'<th>{html.escape(h)}</th>' for h in head)}</tr>{rows}</table>
<ul>{notes_html}</ul>{figures}</body></html>"""
    write_bytes_atomic(out, page.encode())


def geometry_table(document: dict) -> str:
    """One line of the geometry scores (eval.geometry's document) for the report's notes."""
    from nerfgauge.eval.geometry import summary

    labels = {"geometry_chamfer_l1": "Chamfer-L1", "geometry_accuracy": "accuracy",
              "geometry_completeness": "completeness", "geometry_fscore_0p5pct": "F-score@0.5%",
              "geometry_fscore_1pct": "F-score@1%", "geometry_normal_consistency": "normal consistency",
              "normal_angle_mean": "normal error mean deg", "normal_angle_median": "normal error median deg",
              "normal_within_11_25": "normals within 11.25 deg", "normal_within_30": "normals within 30 deg"}
    flat = summary(document)
    cells = [f"{label} {flat[key]:.4g}" for key, label in labels.items() if flat.get(key) is not None]
    return "geometry against the exact meshes (mesh by marching cubes, distances in scene units, taus as " \
           "fractions of the ground-truth diagonal): " + "; ".join(cells)


def geometry_histogram(distances: dict, document: dict, out) -> None:
    """Histograms of predicted-to-ground-truth and ground-truth-to-predicted distances, with
    the F-score thresholds marked; PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    taus = [row["tau"] for row in document["at_tau"]]
    top = max(3 * max(taus), 1e-9)
    figure = Figure(figsize=(6, 3.5), dpi=110)
    axes = figure.add_subplot()
    bins = np.linspace(0, top, 60)
    for key, label in (("accuracy", "prediction to ground truth"), ("completeness", "ground truth to prediction")):
        values = np.minimum(distances[key], top)  # the last bin gathers everything beyond
        axes.hist(values, bins=bins, alpha=0.6, label=label, density=True)
    for tau in taus:
        axes.axvline(tau, color="k", linestyle=":", linewidth=1)
    axes.set_xlabel(f"distance (scene units; last bin: >= {top:.3g}; dotted: F-score taus)")
    axes.set_ylabel("density")
    axes.legend()
    figure.tight_layout()
    with atomic_path(out) as tmp:
        FigureCanvasAgg(figure).print_png(str(tmp))
