"""The report of a train-and-evaluate run: a metrics table against the baselines, the
speed-vs-error curve, an image grid, and one self-contained report.html that shows them.

Inputs are files only (metrics.json documents, a run's log.jsonl, render folders), so
any method's results can be reported the same way. Figures use matplotlib's object API
(Figure + Agg canvas): no global backend is switched.

Every string a user chose that a figure draws (method names, scene and dataset ids, frame
names, paths) goes through `plain_text` first: matplotlib reads text between two `$` as
mathtext, so a method named `m$\\frac$x` raised a parse error while the figure was saved.
A report is made anew or not at all: `write_report` removes the previous report.html and
the figures it is about to draw before drawing anything, so a report that fails leaves no
earlier report that looks current.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import numpy as np
from nerfgauge.eval.covisibility import held_out_pixels, holds_out, reference_depths
from nerfgauge.eval.error_maps import colour_error, depth_relative_error
from nerfgauge.eval.check import finite_number
from nerfgauge.eval.evaluate import NOISE_FLOOR_DB
from nerfgauge.eval.geometry import summary
from nerfgauge.eval.metrics import METRIC_NAMES, composite
from nerfgauge.eval.predictions import find_prediction, read_colour
from nerfgauge.eval.protocols import sensitivity_rows

from nerfgauge.core.dataset import open_dataset
from nerfgauge.core import bounded, owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import atomic_path, write_bytes_atomic
from nerfgauge.core.images import read_exr_single

TABLE_METRICS = (("psnr", "PSNR dB", "{:.2f}"), ("ssim", "SSIM", "{:.4f}"), ("psnr_foreground", "foreground PSNR dB", "{:.2f}"),
                 ("psnr_edges", "edge PSNR dB", "{:.2f}"), ("psnr_interior", "interior PSNR dB", "{:.2f}"),
                 ("psnr_outline", "outline PSNR dB", "{:.2f}"), ("outline_alpha_bias", "outline α bias", "{:+.4f}"),
                 ("outline_alpha_rmse", "outline α RMSE", "{:.4f}"),
                 ("psnr_covisible", "co-visible PSNR dB", "{:.2f}"),
                 ("psnr_capture_bound", "capture bound PSNR dB", "{:.2f}"),
                 ("depth_absrel", "depth AbsRel", "{:.4f}"),
                 ("depth_absrel_resolved", "resolved depth AbsRel", "{:.4f}"),
                 ("depth_rmse", "depth RMSE", "{:.4f}"), ("depth_delta1", "depth δ<1.25", "{:.4f}"),
                 ("depth_bias", "depth bias (median rel.)", "{:+.4f}"),
                 ("opacity_iou", "opacity IoU", "{:.4f}"), ("lpips", "LPIPS (Alex)", "{:.4f}"))


def plain_text(text) -> str:
    """`text` as matplotlib draws it literally: every `$` escaped, so no part is read as
    mathtext (matplotlib shows an escaped dollar as `$`; a string with no unescaped `$`
    is never mathtext). The one way a user's string (a method, scene or frame name, a
    path) enters a figure's label, title, tick or legend."""
    return str(text).replace("$", r"\$")


LOG_NUMBERS = ("seconds", "val_psnr", "step")  # what a figure reads from a log line


def read_log(path, *, finite: bool = True) -> list[dict]:
    """A run's log.jsonl: one JSON object per line (val PSNR against training seconds);
    InputError (one line naming the line) when a line is not an object or a value the
    figures read is not a finite number or null. finite=False keeps NaN and infinities
    (the hard scenes' audit counts them)."""
    entries = []
    for number, line in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        try:
            entry = bounded.loads_json(line, path, parse_constant=_refuse_constant(path, number) if finite else None)
        except json.JSONDecodeError as error:
            raise InputError(f"{path} line {number} is not valid JSON: {error}") from None
        if not isinstance(entry, dict):
            raise InputError(f"{path} line {number}: expected a JSON object, got {type(entry).__name__}")
        for key in LOG_NUMBERS:
            value = entry.get(key)
            if value is not None and not (finite_number(value) or not finite and isinstance(value, float)):
                raise InputError(f"{path} line {number}: {key} must be a finite number or null, got {value!r:.40}")
        entries.append(entry)
    return entries


def _refuse_constant(path, number: int):
    def refuse(constant):
        raise InputError(f"{path} line {number} holds {constant}, which is not valid JSON")
    return refuse


def ceiling_cell(psnr, ceiling) -> str:
    """The dataset's noise ceiling (evaluate's noise.psnr_ceiling), marked when the PSNR is
    within NOISE_FLOOR_DB of it."""
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
            absent = document.get("notes", {}).get(key, "–")  # e.g. lpips: "n/a (install: nerfgauge lpips install)"
            cells.append(absent if mean is None else fmt.format(mean) + ("" if not std else f" ± {fmt.format(std)}"))
            if key == "psnr":
                cells.append(ceiling_cell(mean, (document.get("noise") or {}).get("psnr_ceiling")))
        ms = document.get("timing", {}).get("ms_per_frame")
        cells.append("–" if ms is None else f"{ms:.1f}")
        table.append(cells)
    return table


def _figure(width: float, height: float):
    from matplotlib.figure import Figure  # matplotlib: only when a figure is drawn

    return Figure(figsize=(width, height), dpi=110)


def save_png(figure, out) -> None:
    """A matplotlib Figure as PNG at `out`, through the atomic writer (every figure we draw)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # matplotlib

    with atomic_path(out) as tmp:
        FigureCanvasAgg(figure).print_png(str(tmp))


def plot_curves(curves: dict, out, baselines: dict | None = None, finals: dict | None = None) -> None:
    """Speed against error, PNG. curves: {label: [log entries]}: validation PSNR against
    training seconds. baselines: {label: test PSNR}: methods that do not train, drawn at 0 s
    with a dashed line across. finals: {label: (training seconds, test PSNR)}: a trained
    method's final test score, a star."""
    figure = _figure(6.4, 4.2)
    axes = figure.add_subplot()
    for label, entries in curves.items():
        points = [(e["seconds"], e["val_psnr"]) for e in entries if e.get("val_psnr") is not None]
        if points:
            axes.plot(*zip(*points), marker="o", markersize=3, label=plain_text(f"{label} (validation)"))
    for label, (seconds, value) in (finals or {}).items():
        if value is not None and seconds is not None:
            axes.plot([seconds], [value], marker="*", markersize=12, linestyle="none",
                      label=plain_text(f"{label} (test)"))
    for k, (label, value) in enumerate((baselines or {}).items()):
        if value is None:
            continue
        colour = f"C{(k + 3) % 10}"
        axes.axhline(value, color=colour, linestyle="--", linewidth=1)
        axes.plot([0.0], [value], marker="s", color=colour, linestyle="none",
                  label=plain_text(f"{label} (test, no training)"))
    axes.set_xlabel("training seconds")
    axes.set_ylabel("PSNR (dB)")
    axes.set_title("speed against error")
    axes.grid(alpha=0.3)
    if axes.get_legend_handles_labels()[0]:
        axes.legend(fontsize=8)
    figure.tight_layout()
    save_png(figure, out)


GRID_COLUMNS = (("ground truth", None, None), ("prediction", None, None),
                ("colour error |Δ| (mean over RGB)", "magma", 0.2), ("predicted depth (ray distance)", "viridis", None),
                ("depth relative error |Δ|/d", "viridis", 0.1),
                ("train views saw it: magenta none,\norange not its depth", None, None))
UNSEEN_RGB = (1.0, 0.0, 1.0)  # held-out pixels no train view saw
UNRESOLVED_RGB = (1.0, 0.6, 0.0)  # seen, but no two train views resolve their depth


def held_out_overlay(gt: np.ndarray, held_out, hit: np.ndarray) -> np.ndarray:
    """What the train views saw of a held-out frame, over its ground truth in gray:
    pixels no train view saw in UNSEEN_RGB, hit pixels whose depth they do not resolve
    tinted UNRESOLVED_RGB (eval.covisibility). gt [H, W, 3], hit [H, W] bool,
    held_out: HeldOutPixels. Returns [H, W, 3] in [0, 1]."""
    gray = np.repeat(0.35 + 0.65 * gt.mean(axis=-1, keepdims=True), 3, axis=-1)  # [H, W, 3], light: the marks show
    out = gray.copy()
    unresolved = hit & held_out.covisible & ~held_out.resolved
    out[unresolved] = 0.4 * gray[unresolved] + 0.6 * np.asarray(UNRESOLVED_RGB)
    out[~held_out.covisible] = UNSEEN_RGB
    return out


def _pred_rgb(pred_dir: Path, stem: str, intrinsics, background) -> np.ndarray:
    """The prediction of `stem` composited onto the background, [H, W, 3], whatever its
    format (eval.predictions finds it)."""
    files = find_prediction(pred_dir, stem, "distance")
    if files is None:
        raise InputError(f"no prediction for frame {stem} in {pred_dir}")
    rgb, alpha = read_colour(files.colour, intrinsics)
    return composite(np.concatenate([rgb, alpha[..., None]], -1), background) if alpha is not None else rgb


def image_grid(dataset_root, pred_dir, out, split: str = "test", frames: int = 3, background=(1.0, 1.0, 1.0)) -> None:
    """PNG: one row per frame; labelled columns ground truth, prediction, colour error,
    predicted depth, depth error, each map with its colour bar (scale in the label), and
    what the train views saw of the frame (held_out_overlay)."""
    ds = open_dataset(dataset_root)
    cameras = ds.cameras(split)
    stems = cameras.stems[:frames]
    bg = np.asarray(background, np.float64)
    figure = _figure(2.1 * len(GRID_COLUMNS), 2.0 * max(len(stems), 1) + 1.0)
    grid = figure.subplots(max(len(stems), 1), len(GRID_COLUMNS), squeeze=False)
    images = {}
    depths = reference_depths(ds) if holds_out(ds, split) else None
    for row, stem in enumerate(stems):
        gt = composite(ds.rgba_of(stem, cameras.intrinsics).astype(np.float64), bg)
        pred = _pred_rgb(Path(pred_dir), stem, cameras.intrinsics, bg)
        gt_depth = ds.depth_of(stem, cameras.intrinsics)
        mask = ds.mask_of(stem, cameras.intrinsics)
        depth_path = Path(pred_dir) / (stem + "_depth.exr")
        pred_depth = read_exr_single(depth_path) if depth_path.is_file() else None
        far = float(gt_depth[mask].max()) if mask.any() else 1.0
        tiles = [gt, pred, colour_error(pred, gt),
                 np.where(pred_depth > 0, pred_depth, np.nan) if pred_depth is not None else None,
                 depth_relative_error(pred_depth, gt_depth, mask) if pred_depth is not None else None,
                 None if depths is None else
                 held_out_overlay(gt, held_out_pixels(ds, split, row, depths, mask, gt_depth), mask)]
        for col, ((label, cmap, vmax), tile) in enumerate(zip(GRID_COLUMNS, tiles)):
            axes = grid[row, col]
            axes.set_xticks([])
            axes.set_yticks([])
            if row == 0:
                axes.set_title(label, fontsize=7)
            if col == 0:
                axes.set_ylabel(plain_text(stem), fontsize=7)
            if tile is None:
                axes.text(0.5, 0.5, "no depth" if col < len(GRID_COLUMNS) - 1 else plain_text(f"{split}: not held out"),
                          ha="center", va="center", fontsize=7, transform=axes.transAxes)
                continue
            if cmap is None:
                axes.imshow(np.clip(tile, 0, 1), interpolation="nearest")
            else:
                images[col] = axes.imshow(tile, cmap=cmap, vmin=0.0, vmax=vmax if vmax is not None else far,
                                          interpolation="nearest")
    for col, image in images.items():
        bar = figure.colorbar(image, ax=list(grid[:, col]), orientation="horizontal", fraction=0.08, pad=0.04)
        bar.ax.tick_params(labelsize=6)
    save_png(figure, out)


def frusta_plot(dataset_root, out, splits=("train", "test"), bounds=None) -> None:
    """PNG: the cameras of `splits` as frusta (apex at the centre, the image plane at a
    tenth of the scene's size) around the scene's bounding box, in 3D."""
    ds = open_dataset(dataset_root)
    bounds = ds.bounds if bounds is None else np.asarray(bounds)
    figure = _figure(5.5, 5.0)
    axes = figure.add_subplot(projection="3d")
    points = []
    if bounds is not None:
        lo, hi = np.asarray(bounds[0], float), np.asarray(bounds[1], float)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        for i in range(8):
            for j in range(i + 1, 8):
                if np.sum(corners[i] != corners[j]) == 1:  # the 12 edges
                    axes.plot(*zip(corners[i], corners[j]), color="k", linewidth=0.8)
        points.append(corners)
    centres = np.concatenate([ds.cameras(split).c2w[:, :3, 3] for split in splits if ds.cameras(split).stems] or
                             [np.zeros((0, 3))])
    extent = [p for p in points] + [centres]
    span = np.ptp(np.concatenate(extent), axis=0).max() if sum(len(e) for e in extent) > 1 else 1.0
    size = 0.08 * max(span, 1e-6)
    for split, colour in zip(splits, ("tab:blue", "tab:red", "tab:green")):
        cameras = ds.cameras(split)
        if not cameras.stems:
            continue
        k = cameras.intrinsics
        half_w, half_h = 0.5 * k.width / k.fx, 0.5 * k.height / k.fy
        local = np.array([[-half_w, -half_h, -1], [half_w, -half_h, -1], [half_w, half_h, -1], [-half_w, half_h, -1]])
        for c2w in cameras.c2w:
            apex = c2w[:3, 3]
            quad = apex + (local * size) @ c2w[:3, :3].T  # [4, 3]: OpenGL cameras look along -Z
            for corner in quad:
                axes.plot(*zip(apex, corner), color=colour, linewidth=0.5)
            loop = np.vstack([quad, quad[:1]])
            axes.plot(loop[:, 0], loop[:, 1], loop[:, 2], color=colour, linewidth=0.7)
        axes.plot([], [], color=colour, label=plain_text(f"{split} ({len(cameras.stems)})"))
        points.append(cameras.c2w[:, :3, 3])
    allpoints = np.concatenate(points) if points else np.zeros((1, 3))
    middle, radius = (allpoints.max(0) + allpoints.min(0)) / 2, max(np.ptp(allpoints, axis=0).max() / 2, 1e-6) * 1.1
    axes.set_xlim(middle[0] - radius, middle[0] + radius)
    axes.set_ylim(middle[1] - radius, middle[1] + radius)
    axes.set_zlim(middle[2] - radius, middle[2] + radius)
    axes.set_xlabel("x")
    axes.set_ylabel("y")
    axes.set_zlabel("z")
    axes.set_title("cameras and scene bounds", fontsize=9)
    axes.legend(fontsize=8, loc="upper left")
    save_png(figure, out)


def _data_uri(path) -> str:
    return "data:image/png;base64," + base64.b64encode(Path(path).read_bytes()).decode()


# A table sorts by the column whose header is clicked (again: the other way round); numbers
# compare as numbers, "–" sorts last. The page's URL hash "#sort=<table index>:<column
# index>[:desc]" sorts at load, so a sorted view can be linked to.
SORT_SCRIPT = """<script>
function cellValue(row, col) {
  var text = row.cells[col].textContent.trim();
  var number = parseFloat(text);
  return isNaN(number) ? text : number;
}
function sortTable(table, col, descending) {
  var body = table.tBodies[0];
  var rows = Array.prototype.slice.call(body.rows);
  rows.sort(function (a, b) {
    var x = cellValue(a, col), y = cellValue(b, col);
    if (typeof x !== typeof y) { return typeof x === "number" ? -1 : 1; }
    var order = x < y ? -1 : x > y ? 1 : 0;
    return descending ? -order : order;
  });
  rows.forEach(function (row) { body.appendChild(row); });
  table.setAttribute("data-sorted", col + (descending ? ":desc" : ":asc"));
}
document.querySelectorAll("table.sortable").forEach(function (table) {
  Array.prototype.forEach.call(table.tHead.rows[0].cells, function (header, col) {
    header.addEventListener("click", function () {
      sortTable(table, col, table.getAttribute("data-sorted") === col + ":asc");
    });
  });
});
(function () {
  var match = /^#sort=(\\d+):(\\d+)(:desc)?$/.exec(window.location.hash);
  var tables = document.querySelectorAll("table.sortable");
  if (match && tables[+match[1]]) { sortTable(tables[+match[1]], +match[2], !!match[3]); }
})();
</script>"""

# The page never scrolls sideways (issue 51): the body keeps a readable width with a margin,
# a table wider than it scrolls inside its own box (div.table), headers wrap, numbers do not,
# and figures shrink to the width.
STYLE = """<meta name='viewport' content='width=device-width, initial-scale=1'>
<style>body{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em}
div.table{overflow-x:auto;margin-bottom:1em}table{border-collapse:collapse;font-size:90%}
td,th{border:1px solid #ccc;padding:4px 8px;text-align:right}td{white-space:nowrap}
th{vertical-align:bottom;min-width:4em}td:first-child,th:first-child{text-align:left}
table.sortable th{cursor:pointer;background:#f4f4f4}img{max-width:100%;height:auto}</style>"""


def sortable_table_html(table: list) -> str:
    """A header row and body rows of strings as a sortable <table>."""
    head, *body = table
    header = "".join(f"<th>{html.escape(str(h))}</th>" for h in head)
    rows = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in body)
    return f"<div class='table'><table class='sortable'><thead><tr>{header}</tr></thead><tbody>{rows}</tbody></table></div>"


def page_html(title: str, body: str, notes: list[str] = ()) -> bytes:
    """A self-contained page around `body`, with the notes and the sorting script."""
    notes_html = "".join(f"<li>{html.escape(n)}</li>" for n in notes)
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<link rel='icon' href='data:,'>{STYLE}</head><body><h1>{html.escape(title)}</h1><ul>{notes_html}</ul>"
            f"{body}{SORT_SCRIPT}</body></html>").encode()


def write_html(out, title: str, table: list, images: dict, notes: list[str], extra_tables: dict | None = None) -> None:
    """A self-contained page: the (sortable) table, then every image inlined as a data URI,
    then extra_tables ({caption: table}) as sortable tables."""
    figures = "".join(f"<h2>{html.escape(caption)}</h2><img src='{_data_uri(path)}' alt='{html.escape(caption)}'>"
                      for caption, path in images.items())
    extra = "".join(f"<h2>{html.escape(caption)}</h2>{sortable_table_html(rows)}"
                    for caption, rows in (extra_tables or {}).items())
    write_bytes_atomic(out, page_html(title, sortable_table_html(table) + figures + extra, notes))


def per_view_table(documents: dict) -> list[list[str]]:
    """One row per (frame, method) of the metrics documents ({method: document}): the
    frame, the method and every metric of eval.metrics.METRIC_NAMES defined anywhere."""
    names = [m for m in METRIC_NAMES if any(f.get(m) is not None for d in documents.values() for f in d["frames"])]
    table = [["frame", "method"] + [dict((k, label) for k, label, _ in TABLE_METRICS).get(m, m) for m in names]]
    formats = {k: fmt for k, _, fmt in TABLE_METRICS}
    for method, document in documents.items():
        for frame in document["frames"]:
            table.append([frame["name"], method] + ["–" if frame.get(m) is None else formats.get(m, "{:.4f}").format(frame[m])
                                                    for m in names])
    return table


REPORT_FIGURES = ("grid.png", "curve.png", "cameras.png")  # what write_report draws beside report.html


def remove_previous(paths) -> None:
    """Delete the files a report is about to write, before it draws anything, so a report
    that fails leaves none of the previous one looking current. All are checked first:
    a path that is a folder is the user's (InputError, nothing deleted); the deletion
    itself is core.owned's (a link on the way below a folder of ours is refused, a file
    that is a link is removed as a link)."""
    paths = [Path(path) for path in paths]
    for path in paths:
        if path.is_dir() and not path.is_symlink():
            raise InputError(f"refusing to replace {path}: it is a folder")
        owned.check_no_link(path, "delete", last=False)
    for path in paths:
        owned.remove_file(path)


def write_report(out, title: str, dataset_root, renders, documents: dict, *, log_path=None, ours: str,
                 train_seconds=None, notes=(), split: str = "test", frames: int = 3, figures=None,
                 extra_images=None, protocol_tables: dict | None = None) -> Path:
    """report.html with its figures (in `figures`, default out's folder): the metrics table
    of every method, the labelled image grid of `renders` (our method's), the
    speed-against-error curve with the baselines on it, the camera frusta with the scene
    bounds, the sortable per-view table, the protocol-sensitivity table (protocol_tables:
    {method: eval.protocols.sensitivity document}), then `extra_images` ({caption: PNG path}).
    documents: {method: metrics document}, `ours` among them."""
    out = Path(out)
    folder = out.parent if figures is None else Path(figures)
    owned.make_folder(folder)
    remove_previous([out, *(folder / name for name in REPORT_FIGURES)])  # a failure below leaves no old report
    background = (1.0, 1.0, 1.0) if documents[ours].get("background", "white") == "white" else (0.0, 0.0, 0.0)
    image_grid(dataset_root, renders, folder / "grid.png", split=split, frames=frames, background=background)
    curves = {ours: read_log(log_path)} if log_path is not None and Path(log_path).is_file() else {}
    plot_curves(curves, folder / "curve.png",
                baselines={m: d["mean"].get("psnr") for m, d in documents.items() if m != ours},
                finals={ours: (train_seconds, documents[ours]["mean"].get("psnr"))})
    frusta_plot(dataset_root, folder / "cameras.png", splits=("train", split) if split != "train" else ("train",))
    images = {"test views (columns labelled; colour bars give the scales)": folder / "grid.png",
              "speed against error (baselines: no training, at 0 s)": folder / "curve.png",
              "train and test cameras with the scene bounds": folder / "cameras.png", **(extra_images or {})}
    extra = {"per view (click a header to sort)": per_view_table(documents)}
    if protocol_tables:
        extra = {PROTOCOL_CAPTION: protocol_table(protocol_tables), **extra}
    write_html(out, title, metrics_table(documents), images, list(notes), extra_tables=extra)
    return out


PROTOCOL_CAPTION = ("protocol sensitivity: the same renders scored under each protocol "
                    "(nerfgauge, NerfBaselines' nerf, nerfstudio's ns-eval; eval/protocols.py), and the spread")


def protocol_table(documents: dict) -> list[list[str]]:
    """The protocol-sensitivity table of eval.protocols.sensitivity documents ({method: doc})."""
    return sensitivity_rows(documents)


def geometry_table(document: dict) -> str:
    """One line of the geometry scores (eval.geometry's document) for the report's notes."""
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
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # matplotlib: only when a figure is drawn
    from matplotlib.figure import Figure  # matplotlib

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
    save_png(figure, out)


# --- defocus: methods against the thin-lens truth at several apertures ---------------------


def aperture_table(scores: dict, apertures: list) -> list[list[str]]:
    """Rows: methods; columns: PSNR and SSIM at each aperture radius.
    scores: {method: {aperture: metrics.json document}} (a missing aperture shows "–")."""
    head = ["method"] + [f"{name} A={a:g}" for a in apertures for name in ("PSNR dB", "SSIM")]
    rows = [head]
    for method, by_aperture in scores.items():
        row = [method]
        for a in apertures:
            mean = by_aperture[a]["mean"] if a in by_aperture else {}
            row += [f"{mean['psnr']:.2f}" if mean.get("psnr") is not None else "–",
                    f"{mean['ssim']:.4f}" if mean.get("ssim") is not None else "–"]
        rows.append(row)
    return rows


def focus_rows(datasets: dict, preds: dict, stem: str, out, background=(1.0, 1.0, 1.0), crop=None) -> None:
    """PNG: one row per method (ground truth first), one column per aperture, all of frame
    `stem` composited on the background: how each method's focus plane stays sharp and the
    rest blurs as the aperture grows. datasets: {aperture: dataset root}; preds: {method:
    {aperture: prediction folder}}; crop: (row0, row1, col0, col1) of the image or None."""
    bg = np.asarray(background, np.float64)
    apertures = list(datasets)
    rows = ["ground truth"] + list(preds)
    figure = _figure(1.9 * len(apertures) + 0.6, 1.9 * len(rows) + 0.3)
    grid = figure.subplots(len(rows), len(apertures), squeeze=False)
    for col, aperture in enumerate(apertures):
        ds = open_dataset(datasets[aperture])
        intrinsics = ds.cameras(stem.split("/")[0]).intrinsics
        for row, name in enumerate(rows):
            axes = grid[row, col]
            axes.set_xticks([])
            axes.set_yticks([])
            if row == 0:
                axes.set_title(f"aperture {aperture:g}", fontsize=8)
            if col == 0:
                axes.set_ylabel(plain_text(name), fontsize=8)
            if name == "ground truth":
                tile = composite(ds.rgba_of(stem, intrinsics).astype(np.float64), bg)
            elif aperture in preds[name]:
                tile = _pred_rgb(Path(preds[name][aperture]), stem, intrinsics, bg)
            else:
                axes.text(0.5, 0.5, "–", ha="center", va="center", transform=axes.transAxes)
                continue
            if crop is not None:
                tile = tile[crop[0]:crop[1], crop[2]:crop[3]]
            axes.imshow(np.clip(tile, 0, 1), interpolation="nearest")
    save_png(figure, out)
