"""`nerfgauge bench splat`: Gaussian splatting against the compact NeRF, side by side on the
same datasets, budgets, seeds and threads, measured in one run on this machine (issue 50).

For each scene: the dataset (`nerfgauge generate`, with its COLMAP model's surface points),
then for each budget and seed, each method in turn (so machine load falls on both alike):
`nerfgauge train --model M --budget-seconds B --seed S --threads T` in its own process (its
peak memory its own), `nerfgauge render` of the test views in another (render ms per frame
from its timing.json), `evaluate` (PSNR, SSIM, LPIPS, depth AbsRel) and the geometry of the
rendered test depth back-projected (eval.geometry with pred_depth: the same protocol for
both methods, F-score at 1% of the diagonal). Per (scene, method, budget) the runs over
seeds are aggregated with two-level bootstrap intervals (eval.uncertainty.aggregate_runs),
and splat is compared with the compact NeRF on the same views and seeds
(eval.uncertainty.paired_comparison: mean PSNR difference, its interval, Wilcoxon p).

Writes into OUT (a nerfgauge "bench" folder of kind splat): splat.json (the config, the
command that reproduces it, every row, the aggregates and comparisons; rewritten after
each run), splat.md (the tables and the command) and splat.png (eval.report.save_png).
Figures are ratios and orderings within one run; absolute seconds depend on the machine,
so run it on an idle one.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from nerfgauge.core import arguments
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, write_bytes_atomic, write_json
from nerfgauge.core.folders import remove_owned
from nerfgauge.eval.evaluate import evaluate
from nerfgauge.eval.geometry import score_geometry, summary as geometry_summary
from nerfgauge.eval.report import plain_text, read_log, save_png
from nerfgauge.generate.pipeline import GenerateConfig
from nerfgauge.eval.uncertainty import EVALUATE_SEED, aggregate_runs, mean_of, paired_comparison, run_matrix
from nerfgauge.orchestrate.bench.common import claim_bench_folder, run_child
from nerfgauge.scenes import make_scene

# method -> the file its run saves the model in (its size is the model size)
MODEL_FILES = {"splat": "gaussians.ply", "compact": "model.pt"}
METHODS = tuple(MODEL_FILES)
IMAGE_METRICS = ("psnr", "ssim", "lpips", "depth_absrel")
FSCORE = "geometry_fscore_1pct"
# issue 50's targets for splat on primitives, 128 px, 100 train views, 2 threads
PSNR_TARGETS = {120.0: 36.0, 600.0: 40.0}
RENDER_MS_TARGET = 20.0
TARGET_CASE = {"scene": "primitives", "width": 128, "height": 128, "views": 100, "threads": 2}
GEOMETRY_SAMPLES = arguments.bounded(int, 1, 10_000_000)  # each side's samples: 10^7 is minutes of distances


@dataclass(frozen=True)
class SplatBenchConfig:
    scenes: tuple = ("primitives",)
    width: int = 128
    height: int = 128
    views: int = 100
    test_views: int = GenerateConfig.test_views
    spp: int = GenerateConfig.spp
    budgets: tuple = (120.0, 600.0)
    seeds: tuple = (0,)
    threads: int = 2
    methods: tuple = METHODS
    geometry_samples: int = 200_000  # ground-truth and predicted samples of the geometry scores

    def validate(self) -> None:
        arguments.check_fields(self, {"width": arguments.IMAGE_SIDE, "height": arguments.IMAGE_SIDE,
                                      "views": arguments.VIEWS, "test_views": arguments.VIEWS, "spp": arguments.SPP,
                                      "threads": arguments.THREADS, "geometry_samples": GEOMETRY_SAMPLES},
                               flags={"width": "--res", "height": "--res"})
        for name, values, kind in (("--budgets", self.budgets, arguments.SECONDS), ("--seeds", self.seeds, arguments.SEED)):
            if not values or len(set(values)) != len(values):
                raise InputError(f"{name} must be distinct values, at least one, got {list(values)}")
            for value in values:
                kind.check(value, name)
        unknown = [method for method in self.methods if method not in METHODS]
        if not self.methods or unknown or len(set(self.methods)) != len(self.methods):
            raise InputError(f"--methods must be distinct names from {', '.join(METHODS)}, got {list(self.methods)}")
        if not self.scenes:
            raise InputError("--scenes is empty")
        for scene in self.scenes:
            make_scene(scene, 0)  # an unknown name raises InputError naming the known ones

    def command(self, out) -> str:
        """The command line that runs this configuration again into `out`."""
        return (f"nerfgauge bench splat --scenes {','.join(self.scenes)} --res {self.width}x{self.height} "
                f"--views {self.views} --test-views {self.test_views} --spp {self.spp} "
                f"--budgets {','.join(f'{b:g}' for b in self.budgets)} --seeds {','.join(map(str, self.seeds))} "
                f"--threads {self.threads} --methods {','.join(self.methods)} "
                f"--geometry-samples {self.geometry_samples} --out {out}")


def bench_splat(config: SplatBenchConfig, out, progress_print=print) -> dict:
    """Run every scene x budget x seed x method into the bench folder `out` (module
    docstring). Returns the document splat.json holds."""
    config.validate()
    out = Path(out)
    rows = []
    with claim_bench_folder(out, "splat"):
        for scene in config.scenes:
            data = out / "datasets" / f"{scene}-{config.width}x{config.height}-{config.views}"
            code, _, _ = run_child(["generate", scene, "--out", str(data), "--views", str(config.views), "--res",
                                    f"{config.width}x{config.height}", "--test-views", str(config.test_views),
                                    "--spp", str(config.spp), "--quiet"])
            if code != 0:
                raise InputError(f"bench splat: generating {scene} failed (exit {code})")
            for budget in config.budgets:
                for seed in config.seeds:
                    for method in config.methods:
                        progress_print(f"bench splat: {scene}, {method}, {budget:g} s, seed {seed}")
                        rows.append(_case(config, data, out / "runs" / f"{scene}-{method}-{budget:g}s-seed{seed}",
                                          scene, method, budget, seed))
                        write_json(out / "splat.json", _document(config, out, rows, final=False))
        document = _document(config, out, rows, final=True)
        write_json(out / "splat.json", document)
        write_bytes_atomic(out / "splat.md", (report_markdown(document) + "\n").encode())
        plot(document, out / "splat.png")
    return document


def _case(config: SplatBenchConfig, data: Path, run: Path, scene: str, method: str, budget: float, seed: int) -> dict:
    """Train, render, evaluate and score the geometry of one run; its row."""
    row = {"scene": scene, "method": method, "budget": budget, "seed": seed, "run": str(run)}
    remove_owned(run, "run")  # an earlier bench's run of this case: train afresh
    code, _, peak_mb = run_child(["train", str(data), "--out", str(run), "--model", method, "--budget-seconds",
                                  str(budget), "--seed", str(seed), "--threads", str(config.threads), "--quiet"])
    if code != 0:
        return row | {"error": f"train exit {code}"}
    code, _, _ = run_child(["render", str(run), "--threads", str(config.threads), "--quiet"])
    if code != 0:
        return row | {"error": f"render exit {code}"}
    log = read_log(run / "log.jsonl")
    metrics = evaluate(data, run / "renders", "test", run / "metrics.json")
    try:
        geometry, _ = score_geometry(data, pred_depth=run / "renders", split="test", samples=config.geometry_samples)
    except InputError as error:  # no surface to score (a depth that hits nothing): no F-score, and why
        geometry = {"error": str(error)}
    write_json(run / "geometry.json", geometry)
    return row | {"val_psnr": log[-1]["val_psnr"], **{name: metrics["mean"].get(name) for name in IMAGE_METRICS},
                  "lpips_note": (metrics.get("notes") or {}).get("lpips"), "geometry_note": geometry.get("error"),
                  FSCORE: None if "error" in geometry else geometry_summary(geometry).get(FSCORE),
                  "train_seconds": log[-1]["seconds"], "steps": log[-1]["step"],
                  "steps_per_second": log[-1]["steps_per_second"],
                  "render_ms_per_frame": metrics["timing"].get("ms_per_frame"),
                  "model_mb": (run / MODEL_FILES[method]).stat().st_size / 1e6, "peak_memory_mb": peak_mb,
                  "gaussians": log[-1].get("gaussians")}


def _document(config: SplatBenchConfig, out: Path, rows: list, final: bool) -> dict:
    document = {"config": asdict(config), "command": config.command(out), "rows": rows}
    if final:
        document |= {"aggregates": aggregates(config, rows), "comparisons": comparisons(config, rows)}
    return document


def _runs(rows: list, scene: str, method: str, budget: float) -> list:
    return [row for row in rows if (row["scene"], row["method"], row["budget"]) == (scene, method, budget)
            and "error" not in row]


def aggregates(config: SplatBenchConfig, rows: list) -> list:
    """Per (scene, method, budget): the image metrics over seeds and test views with their
    bootstrap intervals (aggregate_runs), the other figures' means over seeds."""
    table = []
    for scene in config.scenes:
        for budget in config.budgets:
            for method in config.methods:
                runs = _runs(rows, scene, method, budget)
                if not runs:
                    continue
                documents = [read_json(Path(row["run"]) / "metrics.json") for row in runs]
                aggregate = aggregate_runs(documents, [row["seed"] for row in runs], IMAGE_METRICS)
                means = {name: _mean([row[name] for row in runs], name) for name in
                         (FSCORE, "steps_per_second", "render_ms_per_frame", "model_mb", "peak_memory_mb", "steps")}
                table.append({"scene": scene, "method": method, "budget": budget, "seeds": len(runs),
                              "mean": aggregate["mean"], "ci95": aggregate["ci95"], **means})
    return table


def _mean(values: list, what: str):
    defined = [value for value in values if value is not None]
    return mean_of(defined, what) if defined else None


def comparisons(config: SplatBenchConfig, rows: list) -> list:
    """splat minus the compact NeRF in test PSNR, per (scene, budget), on the seeds both
    finished: paired over the same test views (eval.uncertainty.paired_comparison)."""
    found = []
    if not {"splat", "compact"} <= set(config.methods):
        return found
    for scene in config.scenes:
        for budget in config.budgets:
            splat = {row["seed"]: row for row in _runs(rows, scene, "splat", budget)}
            compact = {row["seed"]: row for row in _runs(rows, scene, "compact", budget)}
            seeds = sorted(set(splat) & set(compact))
            if not seeds:
                continue
            matrices = []
            for runs in (splat, compact):
                documents = [read_json(Path(runs[seed]["run"]) / "metrics.json") for seed in seeds]
                matrices.append(run_matrix(documents, "psnr")[0])
            result = paired_comparison(*matrices, np.random.default_rng(EVALUATE_SEED))
            found.append({"scene": scene, "budget": budget, "metric": "psnr", "seeds": seeds, **result})
    return found


def _cell(value, digits: int) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _interval(row: dict, metric: str, digits: int) -> str:
    mean, interval = row["mean"].get(metric), row["ci95"].get(metric)
    text = _cell(mean, digits)
    return text if interval is None else f"{text} [{_cell(interval[0], digits)}, {_cell(interval[1], digits)}]"


def _note(row: dict) -> str:
    """A run's failure, or what it could not be scored on, as one table cell."""
    notes = [row.get(key) for key in ("error", "geometry_note", "lpips_note") if row.get(key)]
    return "; ".join(note.replace("|", "/") for note in notes)


def report_markdown(document: dict) -> str:
    """The aggregate table, each run's row, the paired comparisons, the issue's targets
    where this run measures them, and the command that reproduces it."""
    head = ("scene", "method", "budget s", "seeds", "test PSNR [95% CI]", "SSIM", "LPIPS", "depth AbsRel",
            "F-score 1%", "steps/s", "render ms", "model MB", "peak MB")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in document.get("aggregates", []):
        cells = [row["scene"], row["method"], f"{row['budget']:g}", str(row["seeds"]), _interval(row, "psnr", 2),
                 _interval(row, "ssim", 4), _interval(row, "lpips", 4), _interval(row, "depth_absrel", 4),
                 _cell(row[FSCORE], 4), _cell(row["steps_per_second"], 1), _cell(row["render_ms_per_frame"], 1),
                 _cell(row["model_mb"], 2), _cell(row["peak_memory_mb"], 0)]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Each run:", "", "| scene | method | budget s | seed | val PSNR | test PSNR | steps | Gaussians | note |",
              "|---|---|---|---|---|---|---|---|---|"]
    for row in document["rows"]:
        lines.append(f"| {row['scene']} | {row['method']} | {row['budget']:g} | {row['seed']} | "
                     f"{_cell(row.get('val_psnr'), 2)} | {_cell(row.get('psnr'), 2)} | {row.get('steps', '–')} | "
                     f"{row.get('gaussians') or '–'} | {_note(row)} |")
    if document.get("comparisons"):
        lines += ["", "splat minus compact, test PSNR, paired over the same views and seeds:", ""]
        for item in document["comparisons"]:
            interval = item["ci95"]
            p = "n/a" if item["p_value"] is None else f"{item['p_value']:.3g}"
            lines.append(f"- {item['scene']}, {item['budget']:g} s: {item['mean_difference']:+.2f} dB "
                         f"[{interval[0]:+.2f}, {interval[1]:+.2f}], Wilcoxon p = {p} "
                         f"({item['n_views']} views, seeds {', '.join(map(str, item['seeds']))})")
    lines += targets_lines(document)
    lines += ["", f"Reproduce: `{document['command']}`"]
    return "\n".join(lines)


def targets_lines(document: dict) -> list:
    """Issue 50's targets for splat, where this run is their case (primitives, 128 px, 100
    train views, 2 threads): mean test PSNR at 120 and 600 s, render ms per frame."""
    config = document["config"]
    if any(config.get(key) != value for key, value in TARGET_CASE.items() if key != "scene") or \
            TARGET_CASE["scene"] not in config["scenes"]:
        return []
    lines = ["", "Targets (issue 50, splat on primitives, 128 px, 100 views, 2 threads):", ""]
    for row in document.get("aggregates", []):
        if row["method"] != "splat" or row["scene"] != TARGET_CASE["scene"]:
            continue
        psnr, target = row["mean"].get("psnr"), PSNR_TARGETS.get(row["budget"])
        if target is not None:
            met = psnr is not None and psnr >= target
            lines.append(f"- {row['budget']:g} s: {_cell(psnr, 2)} dB against >= {target:g} dB: "
                         f"{'met' if met else 'not met'}")
        ms = row["render_ms_per_frame"]
        met = ms is not None and ms <= RENDER_MS_TARGET
        lines.append(f"- render at {row['budget']:g} s: {_cell(ms, 1)} ms a frame against <= {RENDER_MS_TARGET:g}: "
                     f"{'met' if met else 'not met'}")
    return lines


def plot(document: dict, out: Path) -> None:
    """OUT/splat.png: every run's val PSNR against training seconds; the mean test PSNR
    (with its interval) against the budget; test PSNR against render ms per frame and
    against model MB, one marker per method and budget."""
    from matplotlib.figure import Figure  # matplotlib: only when a figure is drawn

    figure = Figure(figsize=(11, 8), dpi=110)
    curves, budgets = figure.add_subplot(2, 2, 1), figure.add_subplot(2, 2, 2)
    speed, size = figure.add_subplot(2, 2, 3), figure.add_subplot(2, 2, 4)
    for row in document["rows"]:
        if "error" in row:
            continue
        log = read_log(Path(row["run"]) / "log.jsonl")
        curves.plot([e["seconds"] for e in log], [e["val_psnr"] for e in log], marker=".",
                    label=plain_text(f"{row['scene']}: {row['method']} ({row['budget']:g} s, seed {row['seed']})"))
    aggregates = document.get("aggregates", [])
    for scene, method in dict.fromkeys((row["scene"], row["method"]) for row in aggregates):
        line = sorted((row for row in aggregates if (row["scene"], row["method"]) == (scene, method)
                       and row["mean"].get("psnr") is not None), key=lambda row: row["budget"])
        if not line:
            continue
        label = plain_text(f"{scene}: {method}")
        means = [row["mean"]["psnr"] for row in line]
        low = [mean - (row["ci95"]["psnr"] or [mean, mean])[0] for mean, row in zip(means, line)]
        high = [(row["ci95"]["psnr"] or [mean, mean])[1] - mean for mean, row in zip(means, line)]
        budgets.errorbar([row["budget"] for row in line], means, yerr=[low, high], marker="o", capsize=3, label=label)
        speed.scatter([row["render_ms_per_frame"] or 0 for row in line], means, label=label)
        size.scatter([row["model_mb"] for row in line], means, label=label)
    curves.set(xlabel="training seconds", ylabel="val PSNR (dB)", title="val PSNR against training time (each run)")
    budgets.set(xlabel="budget (s)", ylabel="test PSNR (dB)", title="test PSNR at each budget (95% CI over seeds, views)",
                xscale="log")
    speed.set(xlabel="render ms per frame", ylabel="test PSNR (dB)", title="PSNR against render time")
    size.set(xlabel="saved model (MB)", ylabel="test PSNR (dB)", title="PSNR against model size", xscale="log")
    for axes in (curves, budgets, speed, size):
        axes.grid(alpha=0.3)
    if document["rows"]:
        curves.legend(fontsize=6, loc="lower right")
    if aggregates:
        budgets.legend(fontsize=7, loc="lower right")
    figure.tight_layout()
    save_png(figure, out)
