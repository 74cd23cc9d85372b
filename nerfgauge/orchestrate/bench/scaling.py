"""`nerfgauge bench scaling`: how training, rendering and generation grow with the size of
the problem, measured in one run on this machine.

- NeRF against image resolution (square, at a fixed number of train views) and against the
  number of train views (at a fixed resolution); the shared case runs once. Each case
  generates its dataset, trains `compact` for a time budget and renders and scores the test
  views, every stage in its own process (`orchestrate.bench.run_child`) so peak memory is its own.
  Time to the target PSNR is the first training-clock second whose logged val PSNR reaches
  it (logged every `EVAL_EVERY_SECONDS` training seconds, so it is an upper bound within that).
- Generation against views (at a fixed spp) and against spp (at a fixed number of views),
  timed in process around `generate.pipeline.generate` (train views only), with a
  straight-line fit: seconds per view, seconds per spp per view, and the fixed cost. An
  untimed 1-view generation per spp value goes first: it imports Mitsuba, and Dr.Jit
  compiles a kernel per sample count the first time a process uses it (0.5-1 s here),
  which would otherwise land on whichever case came first.

Writes OUT/scaling.json after every case (atomically, so a killed run keeps what it
measured), then OUT/scaling.md (tables, growth ratios, fits) and OUT/scaling.png.
Figures are ratios within one run; absolute seconds depend on the machine.
"""

from __future__ import annotations

import math
import os
import platform
import shlex
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from nerfgauge.orchestrate.bench.common import claim_bench_folder, first_time_reaching, run_child

from nerfgauge.core import arguments
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_bytes_atomic, write_json
from nerfgauge.core.folders import remove_owned
from nerfgauge.core import dataset
from nerfgauge.eval.evaluate import BACKGROUNDS, composited_pair, evaluate
from nerfgauge.eval.metrics import area_average, psnr
from nerfgauge.eval.predictions import find_nerfgauge_predictions
from nerfgauge.eval.report import read_log, save_png
from nerfgauge.generate.pipeline import GenerateConfig, generate
from nerfgauge.scenes import make_scene

EVAL_EVERY_SECONDS = 2.0  # val PSNR log spacing (training seconds): the resolution of time-to-target
MODEL = "compact"

# (row key, label) of the quantities whose growth along an axis is reported
NERF_GROWTH = (("time_to_target_s", "time to {target:g} dB"), ("render_ms_per_frame", "render ms/frame"),
               ("steps_per_second", "steps/s"), ("model_mb", "model MB"), ("peak_memory_mb", "peak MB"),
               ("generation_seconds", "generation s"))
GEN_GROWTH = (("seconds", "generation s"),)


@dataclass(frozen=True)
class ScalingConfig:
    """One scaling run's settings; saved in scaling.json and echoed as a command line."""

    scene: str = "primitives"
    resolutions: tuple = (64, 128, 256)  # square, each at `views` train views
    views: int = 100
    view_counts: tuple = (25, 50, 100)  # train views, each at `view_counts_res`
    view_counts_res: int = 128
    budget_seconds: float = 120.0
    target_psnr: float = 30.0
    gen_views: tuple = (25, 50, 100)  # generation: train views, each at `gen_views_spp`
    gen_views_spp: int = 64
    gen_spp: tuple = (16, 64, 256)  # generation: spp, each at `gen_spp_views` views
    gen_spp_views: int = 50
    gen_res: int = 128

    def validate(self) -> None:
        """One-line InputError for anything a run would trip on later; builds the scene (cheap)."""
        lists = {"resolutions": self.resolutions, "view-counts": self.view_counts, "gen-views": self.gen_views,
                 "gen-spp": self.gen_spp}
        for flag, values in lists.items():
            check_counts(values, flag)
        arguments.check_fields(self, {"views": arguments.VIEWS, "view_counts_res": arguments.IMAGE_SIDE,
                                      "gen_views_spp": arguments.SPP, "gen_spp_views": arguments.VIEWS,
                                      "gen_res": arguments.IMAGE_SIDE, "budget_seconds": arguments.SECONDS,
                                      "target_psnr": arguments.TARGET_PSNR})
        make_scene(self.scene, 0)  # unknown names and unreadable meshes raise InputError
        try:  # the generator's own limits (e.g. image size)
            for resolution, views, _ in self.nerf_cases():
                GenerateConfig(scene=self.scene, views=views, width=resolution, height=resolution).validate()
            GenerateConfig(scene=self.scene, views=max(self.gen_views + (self.gen_spp_views,)), width=self.gen_res,
                           height=self.gen_res, spp=max(self.gen_spp + (self.gen_views_spp,))).validate()
        except InputError as error:
            raise InputError(f"bench scaling case: {error}") from None

    def nerf_cases(self) -> list[tuple[int, int, tuple]]:
        """(resolution, views, axes) of every NeRF case, each (resolution, views) once."""
        cases = {(r, self.views): ["resolution"] for r in self.resolutions}
        for v in self.view_counts:
            cases.setdefault((self.view_counts_res, v), []).append("views")
        return [(r, v, tuple(axes)) for (r, v), axes in cases.items()]

    def command(self, out) -> str:
        """The `nerfgauge bench scaling` command line that reproduces this run."""
        def join(values):
            return ",".join(str(v) for v in values)

        return (f"nerfgauge bench scaling --scene {shlex.quote(self.scene)} --resolutions {join(self.resolutions)} "
                f"--views {self.views} --view-counts {join(self.view_counts)} --view-counts-res {self.view_counts_res} "
                f"--budget-seconds {self.budget_seconds:g} --target-psnr {self.target_psnr:g} "
                f"--gen-views {join(self.gen_views)} --gen-views-spp {self.gen_views_spp} "
                f"--gen-spp {join(self.gen_spp)} --gen-spp-views {self.gen_spp_views} --gen-res {self.gen_res} "
                f"--out {shlex.quote(str(out))}")


def check_counts(values, flag: str) -> tuple:
    """Positive, distinct integers (at least one), or a one-line InputError naming --flag."""
    values = tuple(values)
    if not values:
        raise InputError(f"--{flag} must list at least one positive integer")
    bad = [v for v in values if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0]
    if bad:
        raise InputError(f"--{flag} must be positive integers, got {bad[0]!r}")
    duplicates = sorted({v for v in values if values.count(v) > 1})
    if duplicates:
        raise InputError(f"--{flag} lists {duplicates[0]} more than once")
    return values


def _finite(value):
    """A float, or None for missing/NaN/inf (scaling.json is strict JSON)."""
    return None if value is None or not math.isfinite(float(value)) else float(value)


# --------------------------------------------------------------------------------------
# measuring


def nerf_case(config: ScalingConfig, out: Path, resolution: int, views: int, axes: tuple) -> dict:
    """Generate, train, render and score one (resolution, views) case; a row (with "error" on failure)."""
    name = f"{config.scene.replace('/', '_').replace(':', '_')}-{resolution}x{resolution}-{views}v"
    data, run = out / "datasets" / name, out / "runs" / f"{name}-{config.budget_seconds:g}s"
    # this case's own folders from an earlier run: start fresh, or times would lie (only through their markers)
    remove_owned(data, "dataset")
    remove_owned(run, "run")
    row = {"resolution": resolution, "views": views, "axes": list(axes), "train_pixels": views * resolution ** 2,
           "budget": config.budget_seconds, "target_psnr": config.target_psnr}
    code, generation_seconds, _ = run_child(["generate", config.scene, "--out", str(data), "--views", str(views),
                                             "--res", str(resolution), "--quiet"])
    if code != 0:
        return row | {"error": f"generate exit {code}"}
    row["generation_seconds"] = generation_seconds
    code, _, peak_mb = run_child(["train", str(data), "--out", str(run), "--model", MODEL, "--budget-seconds",
                                  f"{config.budget_seconds:g}", "--eval-every", f"{EVAL_EVERY_SECONDS:g}", "--quiet"])
    if code != 0:
        return row | {"error": f"train exit {code}"}
    log = read_log(run / "log.jsonl")
    code, _, _ = run_child(["render", str(run), "--quiet"])
    if code != 0:
        return row | {"error": f"render exit {code}"}
    metrics = evaluate(data, run / "renders", "test", run / "metrics.json")
    common = min(config.resolutions)
    if resolution % common == 0:  # the ladder's coarsest pixels (see psnr_at_common_resolution)
        row |= {"common_resolution": common,
                "psnr_at_common": psnr_at_common_resolution(data, run / "renders", resolution // common)}
    return row | {"time_to_target_s": first_time_reaching(log, config.target_psnr),
                  "val_psnr": _finite(log[-1]["val_psnr"]), "psnr": _finite(metrics["mean"]["psnr"]),
                  "ssim": _finite(metrics["mean"]["ssim"]), "depth_absrel": _finite(metrics["mean"]["depth_absrel"]),
                  "train_seconds": log[-1]["seconds"],
                  "steps": log[-1]["step"], "steps_per_second": log[-1]["steps_per_second"],
                  "render_ms_per_frame": _finite(metrics["timing"].get("ms_per_frame")),
                  "model_mb": (run / "model.pt").stat().st_size / 1e6, "peak_memory_mb": peak_mb,
                  "log": str(run / "log.jsonl")}


def psnr_at_common_resolution(data: Path, pred_dir: Path, factor: int, split: str = "test") -> float:
    """Mean PSNR of a nerfgauge renders folder against its dataset with both area-averaged
    by `factor` (composited on white first): every case of a resolution ladder scored on the
    same coarse pixels, so a finer capture is compared on what both resolve, not penalised
    for the detail only its own ground truth holds."""
    ds = dataset.Dataset(data)
    cameras = ds.cameras(split)
    scores = []
    for stem, files in find_nerfgauge_predictions(pred_dir, split, cameras.stems, "distance").items():
        if files is None:
            raise InputError(f"no prediction for frame {stem} in {pred_dir}")
        pred, gt, _, _ = composited_pair(ds, stem, cameras.intrinsics, files, BACKGROUNDS["white"])
        scores.append(psnr(area_average(pred, factor), area_average(gt, factor)))
    return float(np.mean(scores))


def generation_case(scene: str, views: int, spp: int, resolution: int, axes: tuple, scratch: Path) -> dict:
    """Time `generate.pipeline.generate` of `views` train views (no val/test) into a fresh folder."""
    config = GenerateConfig(scene=scene, views=views, val_views=0, test_views=0, width=resolution, height=resolution,
                            spp=spp)
    with tempfile.TemporaryDirectory(dir=scratch) as folder:
        start = time.perf_counter()
        result = generate(config, Path(folder) / "dataset", progress=False)
        seconds = time.perf_counter() - start
    return {"views": views, "spp": spp, "resolution": resolution, "axes": list(axes),
            "samples": views * spp * resolution ** 2, "seconds": seconds, "seconds_per_view": seconds / views,
            "render_seconds": result["render_seconds"], "variant": result["variant"]}


def bench_scaling(config: ScalingConfig, out: Path) -> dict:
    """Every generation case, then every NeRF case, in the bench folder `out`; OUT/scaling.json
    is rewritten after each, then OUT/scaling.md and OUT/scaling.png. Returns the document."""
    config.validate()
    out = Path(out)
    with claim_bench_folder(out, "scaling"):
        document = {"command": config.command(out), "config": asdict(config), "eval_every_seconds": EVAL_EVERY_SECONDS,
                    "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                                "python": platform.python_version(),
                                "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS")},
                    "generation": [], "nerf": []}
        gen_cases = {(v, config.gen_views_spp): ["views"] for v in config.gen_views}
        for spp in config.gen_spp:
            gen_cases.setdefault((config.gen_spp_views, spp), []).append("spp")
        with tempfile.TemporaryDirectory(dir=out, prefix=".gen-") as scratch:
            for spp in sorted({spp for _, spp in gen_cases}):  # warm-up: imports, variant, a kernel per spp
                generation_case(config.scene, 1, spp, config.gen_res, (), Path(scratch))
            for (views, spp), axes in gen_cases.items():
                document["generation"].append(generation_case(config.scene, views, spp, config.gen_res, tuple(axes),
                                                              Path(scratch)))
                document["fits"] = generation_fits(document["generation"])
                write_json(out / "scaling.json", document)
        for resolution, views, axes in config.nerf_cases():
            document["nerf"].append(nerf_case(config, out, resolution, views, axes))
            write_json(out / "scaling.json", document)
        write_bytes_atomic(out / "scaling.md", report_markdown(document).encode())
        scaling_plots(document, out / "scaling.png")
    return document


# --------------------------------------------------------------------------------------
# arithmetic


def axis_rows(rows: list, axis: str) -> list:
    """The rows measured along `axis` without an error, sorted by that axis's value."""
    return sorted((r for r in rows if axis in r.get("axes", ()) and "error" not in r), key=lambda r: r[axis])


def growth(rows: list, axis: str, size_key: str, metric: str):
    """From the smallest to the largest value of `axis`: (metric growth, size growth, their ratio).

    size_key names the problem size (train_pixels for NeRF rows, samples for generation
    rows), so along resolution the size ratio is the pixel-count ratio, along views the
    view-count ratio. None when fewer than two rows, or the metric is missing at either end.
    """
    along = axis_rows(rows, axis)
    if len(along) < 2:
        return None
    lo, hi = along[0], along[-1]
    if lo.get(metric) is None or hi.get(metric) is None or lo[metric] == 0:
        return None
    ratio, size = hi[metric] / lo[metric], hi[size_key] / lo[size_key]
    return ratio, size, ratio / size


def fit_line(xs, ys):
    """Least-squares seconds = slope * x + intercept (numpy.polyfit); None for fewer than two x values."""
    if len(set(xs)) < 2:
        return None
    slope, intercept = np.polyfit(np.asarray(xs, float), np.asarray(ys, float), 1)
    return {"slope": float(slope), "intercept": float(intercept)}


def generation_fits(rows: list) -> dict:
    """Seconds against views (slope: s per view) and against spp (slope / views: s per spp per view)."""
    by_views, by_spp = axis_rows(rows, "views"), axis_rows(rows, "spp")
    fits = {"views": fit_line([r["views"] for r in by_views], [r["seconds"] for r in by_views]),
            "spp": fit_line([r["spp"] for r in by_spp], [r["seconds"] for r in by_spp])}
    if fits["views"]:
        fits["views"] |= {"spp": by_views[0]["spp"], "seconds_per_view": fits["views"]["slope"]}
    if fits["spp"]:
        views = by_spp[0]["views"]
        fits["spp"] |= {"views": views, "seconds_per_spp_per_view": fits["spp"]["slope"] / views,
                        "fixed_seconds_per_view": fits["spp"]["intercept"] / views}
    return fits


# --------------------------------------------------------------------------------------
# report


def growth_line(rows: list, axis: str, metrics: tuple, size_key: str, target: float = 0.0) -> str:
    """One markdown bullet: each metric's growth from the smallest to the largest axis value."""
    along = axis_rows(rows, axis)
    if len(along) < 2:
        return f"- {axis}: fewer than two measured values, no ratio"
    lo, hi = along[0], along[-1]
    size_name = {"resolution": "pixel", "views": "view-count", "spp": "spp"}[axis]
    size = hi[size_key] / lo[size_key]
    parts = []
    for metric, label in metrics:
        label = label.format(target=target)
        result = growth(rows, axis, size_key, metric)
        if result is None:
            missing = [str(r[axis]) for r in (lo, hi) if r.get(metric) is None]
            parts.append(f"{label} n/a ({'not reached at ' + ', '.join(missing) if missing else 'zero at the start'})")
        else:
            parts.append(f"{label} ×{result[0]:.2f} ({result[2]:.2f} of the {size_name} ratio)")
    return f"- {axis} {lo[axis]} → {hi[axis]} ({size_name} ratio ×{size:.2f}): " + "; ".join(parts)


def nerf_table(rows: list, target: float, budget: float) -> str:
    common = next((r["common_resolution"] for r in rows if r.get("common_resolution")), None)
    head = ("res", "views", f"time to {target:g} dB (s)", "val PSNR", "test PSNR",
            f"test PSNR at {common} px" if common else "test PSNR at the coarsest res", "SSIM", "depth AbsRel",
            "steps/s", "render ms/frame", "model MB", "peak MB", "generation s (child wall)")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        size = f"{r['resolution']}x{r['resolution']}"
        if "error" in r:
            lines.append(f"| {size} | {r['views']} | {r['error']} |" + " |" * (len(head) - 3))
            continue

        def cell(key, fmt):
            return "–" if r.get(key) is None else fmt.format(r[key])

        reached = f"not reached in {budget:g} s" if r["time_to_target_s"] is None else f"{r['time_to_target_s']:.1f}"
        cells = [size, str(r["views"]), reached, cell("val_psnr", "{:.2f}"), cell("psnr", "{:.2f}"),
                 cell("psnr_at_common", "{:.2f}"), cell("ssim", "{:.4f}"), cell("depth_absrel", "{:.4f}"), cell("steps_per_second", "{:.1f}"), cell("render_ms_per_frame", "{:.1f}"),
                 cell("model_mb", "{:.2f}"), cell("peak_memory_mb", "{:.0f}"), cell("generation_seconds", "{:.1f}")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def finer_never_worse_line(rows: list) -> str:
    """Whether each finer capture scores at least as well as the coarser ones on their
    common pixels (test PSNR at the coarsest resolution, area-averaged)."""
    scored = sorted((r for r in rows if r.get("psnr_at_common") is not None and "error" not in r),
                    key=lambda r: r["resolution"])
    if len(scored) < 2:
        return "Finer captures against coarser ones: fewer than two resolutions scored at a common resolution."
    worse = [f"{b['resolution']} px ({b['psnr_at_common']:.2f} dB) < {a['resolution']} px ({a['psnr_at_common']:.2f})"
             for a, b in zip(scored, scored[1:]) if b["psnr_at_common"] < a["psnr_at_common"]]
    common = scored[0]["common_resolution"]
    figures = ", ".join(f"{r['resolution']} px {r['psnr_at_common']:.2f}" for r in scored)
    verdict = "a finer capture never scored worse" if not worse else "a finer capture scored worse: " + "; ".join(worse)
    return f"Scored on common {common} px pixels (renders and ground truth area-averaged): {figures} dB; {verdict}."


def generation_table(rows: list) -> str:
    head = ("views", "spp", "res", "generation s (in-process generate.pipeline.generate, warm)", "s/view",
            "of which Mitsuba render s")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        lines.append(f"| {r['views']} | {r['spp']} | {r['resolution']}x{r['resolution']} | {r['seconds']:.2f} | "
                     f"{r['seconds_per_view']:.4f} | {r['render_seconds']:.2f} |")
    return "\n".join(lines)


def fit_lines(fits: dict) -> list[str]:
    lines = []
    views, spp = fits.get("views"), fits.get("spp")
    lines.append("- fit against views: n/a (fewer than two view counts)" if views is None else
                 f"- fit against views (at {views['spp']} spp): seconds = {views['slope']:.4f} s/view × views "
                 f"+ {views['intercept']:.2f} s fixed")
    lines.append("- fit against spp: n/a (fewer than two spp values)" if spp is None else
                 f"- fit against spp (at {spp['views']} views): seconds = {spp['slope']:.5f} s/spp × spp "
                 f"+ {spp['intercept']:.2f} s, i.e. {spp['seconds_per_spp_per_view'] * 1e3:.4f} ms per spp per view "
                 f"and {spp['fixed_seconds_per_view']:.4f} s per view that does not depend on spp")
    return lines


def report_markdown(document: dict) -> str:
    config = document["config"]
    target, budget = config["target_psnr"], config["budget_seconds"]
    nerf, generation = document["nerf"], document["generation"]
    by_res = [r for r in nerf if "resolution" in r["axes"]]
    by_views = [r for r in nerf if "views" in r["axes"]]
    parts = ["```bash", document["command"], "```", "",
             f"## NeRF scaling ({MODEL}, scene {config['scene']}, {budget:g} s of training each)", "",
             f"Time to {target:g} dB: the first training-clock second whose val PSNR (logged every "
             f"{document['eval_every_seconds']:g} s) reaches it. Generation s: the `nerfgauge generate` child's wall "
             "time (process start, train + 10 val + 20 test views). Render ms/frame on the test views.", "",
             f"### Against resolution ({config['views']} train views)", "", nerf_table(by_res, target, budget), "",
             finer_never_worse_line(by_res), "",
             f"### Against train views ({config['view_counts_res']}x{config['view_counts_res']})", "",
             nerf_table(by_views, target, budget), "",
             "Growth from the smallest to the largest value (and that growth over the growth of the problem size):", "",
             growth_line(nerf, "resolution", NERF_GROWTH, "train_pixels", target),
             growth_line(nerf, "views", NERF_GROWTH, "train_pixels", target), "",
             "## Generation scaling", "",
             "Train views only (no val/test), each into a fresh folder, after an untimed 1-view generation per spp "
             "value (imports, and Dr.Jit's kernel compile per sample count).", "",
             generation_table(generation), "",
             growth_line(generation, "views", GEN_GROWTH, "samples"),
             growth_line(generation, "spp", GEN_GROWTH, "samples"),
             *fit_lines(document.get("fits", {})), ""]
    return "\n".join(parts)


def scaling_plots(document: dict, path: Path) -> None:
    """Six panels: time to target and render ms/frame against resolution and views; generation
    seconds against views and spp (with the fitted lines)."""
    from matplotlib.figure import Figure  # matplotlib: only when a figure is drawn

    config = document["config"]
    target, budget = config["target_psnr"], config["budget_seconds"]
    nerf, generation, fits = document["nerf"], document["generation"], document.get("fits", {})
    figure = Figure(figsize=(14, 8), dpi=100)
    panels = figure.subplots(2, 3)
    for column, (axis, label) in enumerate((("resolution", f"resolution (px, square; {config['views']} views)"),
                                            ("views", f"train views ({config['view_counts_res']}px)"))):
        rows = axis_rows(nerf, axis)
        xs = [r[axis] for r in rows]
        time_axes, render_axes = panels[0][column], panels[1][column]
        reached = [(r[axis], r["time_to_target_s"]) for r in rows if r.get("time_to_target_s") is not None]
        missed = [r[axis] for r in rows if r.get("time_to_target_s") is None]
        if reached:
            time_axes.plot(*zip(*reached), marker="o", label="reached")
        if missed:
            time_axes.scatter(missed, [budget] * len(missed), marker="^", facecolors="none", edgecolors="red",
                              label=f"not reached in {budget:g} s")
            time_axes.legend(fontsize=8)
        time_axes.set(xlabel=label, ylabel="training seconds", title=f"time to {target:g} dB vs {axis}")
        ms = [(r[axis], r["render_ms_per_frame"]) for r in rows if r.get("render_ms_per_frame") is not None]
        if ms:
            render_axes.plot(*zip(*ms), marker="o")
        render_axes.set(xlabel=label, ylabel="ms per frame", title=f"render ms/frame vs {axis}")
        for axes in (time_axes, render_axes):
            if xs:
                axes.set_xticks(xs)
            axes.set_ylim(bottom=0)
            axes.grid(alpha=0.3)
    for row, (axis, label) in enumerate((("views", f"train views (at {config['gen_views_spp']} spp)"),
                                         ("spp", f"spp (at {config['gen_spp_views']} views)"))):
        axes = panels[row][2]
        rows = axis_rows(generation, axis)
        xs = [r[axis] for r in rows]
        axes.plot(xs, [r["seconds"] for r in rows], marker="o", linestyle="none", label="measured")
        fit = fits.get(axis)
        if fit and xs:
            line = np.linspace(0, max(xs), 50)
            axes.plot(line, fit["slope"] * line + fit["intercept"], linestyle="--",
                      label=f"{fit['slope']:.3g} s/{'view' if axis == 'views' else 'spp'} + {fit['intercept']:.2f} s")
            axes.legend(fontsize=8)
        axes.set(xlabel=label, ylabel="seconds", title=f"generation s vs {axis} ({config['gen_res']}px)")
        axes.set_ylim(bottom=min(0.0, axes.get_ylim()[0]))
        axes.grid(alpha=0.3)
    figure.tight_layout()
    save_png(figure, path)
