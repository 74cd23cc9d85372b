"""`nerfgauge bench train`: speed against error, scenes x variants x budgets, measured in
one run on this machine. Each training of a variant of ours runs in its own process (so its
peak memory is its own), then renders the test views and is evaluated. Writes
OUT/train.json, OUT/train.md (the table) and Pareto plots (PSNR against training seconds,
PSNR against model MB), and prints the table. Figures are ratios and orderings within one run.

`--methods A,B,...` adds any method the harness runs (nerfgauge.methods.registry: a shipped
spec such as nerfacto, a spec file, module:Class, a built-in name) on the same datasets, in
the same run, through the method interface (`method_rows`): a method that accepts a time
budget trains once per budget, one that takes steps once per `--steps` count, one that
does not train once; each renders the test split and is scored by the same `evaluate`, its
test PSNR drawn against its wall time beside ours. Another tool's method measures its own
commands (wall, CPU, peak memory: methods.measure.run_process); a method of ours named here
trains in this process, so its peak memory is this process's so far (an upper bound). A
method that fails gets its row with the reason; the others go on.
"""

from __future__ import annotations

import time
from pathlib import Path

from nerfgauge.core import arguments
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_bytes_atomic, write_json
from nerfgauge.core.folders import remove_owned
from nerfgauge.eval.evaluate import evaluate
from nerfgauge.eval.report import ceiling_cell, plain_text, read_log, save_png
from nerfgauge.generate.pipeline import GenerateConfig, generate
from nerfgauge.methods.interface import TrainRequest
from nerfgauge.methods.registry import resolve
from nerfgauge.orchestrate.bench.common import claim_bench_folder, first_time_reaching, run_child
from nerfgauge.scenes import make_scene

# variant name -> (model, extra `nerfgauge train` arguments). The vanilla NeRF logs its
# curve every 30 s and is not rendered on the test views: at ~0.5 s per ray batch on two
# cores, 20 test frames of 128x128 would take longer than the whole benchmark.
VARIANTS = {
    "compact": ("compact", []),
    "vanilla": ("vanilla", ["--eval-every", "30"]),
    "compact-view-on": ("compact", ["--view-dependent", "on"]),  # view dependence forced on
    "compact-view-off": ("compact", ["--view-dependent", "off"]),  # ... forced off
    "compact-no-prune": ("compact", ["--no-prune"]),  # save the whole grid
    "compact-no-skip": ("compact", ["--no-occupancy"]),  # no empty-space skipping
    "compact-res256": ("compact", ["--resolution", "256"]),  # resolution fixed high
}


def bench_train(out: Path, scenes: list, variants: list, budgets: list, width: int, height: int, views: int,
                methods=(), steps=()) -> list:
    """Run every scene x variant x budget, and every scene x method x budget or step count
    (`method_rows`), into the bench folder `out`; writes train.json (after each case),
    train.md and pareto.png. Returns the rows."""
    unknown = [v for v in variants if v not in VARIANTS]
    if (not variants and not methods) or unknown:
        raise InputError(f"unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
    chosen = [resolve(name) for name in methods]  # unknown names: InputError before anything is written
    for method in chosen:
        if method.learned and not method.accepts_budget and not steps:
            raise InputError(f"method {method.name} takes a step count, not a time budget: give --steps N[,N...]")
    for count in steps:
        arguments.STEPS.check(count, "--steps")
    if not budgets or not all(isinstance(b, (int, float)) and 0 < b < float("inf") for b in budgets):
        raise InputError(f"budgets must be positive finite seconds, got {budgets!r}")
    if not scenes:
        raise InputError("no scenes to benchmark")
    for scene in scenes:
        make_scene(scene, 0)  # unknown names: InputError before anything is written
    out = Path(out)
    rows = []
    with claim_bench_folder(out, "train"):
        for scene in scenes:
            data = out / "datasets" / f"{scene}-{width}x{height}-{views}"
            code, _, _ = run_child(["generate", scene, "--out", str(data), "--views", str(views), "--res",
                                    f"{width}x{height}", "--quiet"])
            if code != 0:
                raise InputError(f"generating {scene} failed (exit {code})")
            for variant in variants:
                model, extra = VARIANTS[variant]
                for budget in budgets:
                    run = out / "runs" / f"{scene}-{variant}-{budget:g}s"
                    remove_owned(run, "run")  # an earlier bench's run of this case: train afresh
                    code, _, peak_mb = run_child(["train", str(data), "--out", str(run), "--model", model,
                                                  "--budget-seconds", str(budget), "--quiet", *extra])
                    if code != 0:
                        rows.append({"scene": scene, "variant": variant, "budget": budget, "error": f"exit {code}"})
                        continue
                    log = read_log(run / "log.jsonl")
                    if model == "vanilla":
                        metrics = {"mean": {"psnr": None, "ssim": None, "depth_absrel": None}, "timing": {}, "noise": {}}
                    else:
                        run_child(["render", str(run), "--quiet"])
                        metrics = evaluate(data, run / "renders", "test", run / "metrics.json")
                    rows.append({"scene": scene, "variant": variant, "budget": budget,
                                 "val_psnr": log[-1]["val_psnr"], "psnr": metrics["mean"]["psnr"],
                                 **{key: metrics["mean"].get(key) for key in
                                    ("psnr_foreground", "psnr_edges", "psnr_interior")},
                                 "psnr_ceiling": (metrics.get("noise") or {}).get("psnr_ceiling"),
                                 "ssim": metrics["mean"]["ssim"], "depth_absrel": metrics["mean"]["depth_absrel"],
                                 "lpips": metrics["mean"].get("lpips"), "lpips_note": metrics.get("notes", {}).get("lpips"),
                                 "train_seconds": log[-1]["seconds"], "steps": log[-1]["step"],
                                 "steps_per_second": log[-1]["steps_per_second"],
                                 "render_ms_per_frame": metrics["timing"].get("ms_per_frame"),
                                 "model_mb": (run / "model.pt").stat().st_size / 1e6, "peak_memory_mb": peak_mb,
                                 "log": str(run / "log.jsonl")})
                    write_json(out / "train.json", {"rows": rows})
            for method in chosen:
                rows += method_rows(method, scene, data, out, budgets, steps)
                write_json(out / "train.json", {"rows": rows})
        write_bytes_atomic(out / "train.md", (table_markdown(rows) + "\n\n" + "\n".join(speedups(rows)) + "\n").encode())
        pareto_plots(rows, out)
    return rows


def method_rows(method, scene: str, data: Path, out: Path, budgets: list, steps: list) -> list:
    """One row per length of `method` (methods.interface.Method) on the dataset `data`:
    each budget where it accepts one, else each step count, or once where it does not
    train. Its run in OUT/runs/<scene>-<method>-<length>/, its renders of the test split in
    that run's renders/, scored by eval.evaluate as our variants are."""
    lengths = ([(None, None)] if not method.learned else [(None, b) for b in budgets] if method.accepts_budget
               else [(n, None) for n in steps])
    rows = []
    for count, budget in lengths:
        label = "once" if count is None and budget is None else f"{count}steps" if budget is None else f"{budget:g}s"
        run = out / "runs" / f"{scene}-{method.name}-{label}"
        row = {"scene": scene, "variant": method.name, "budget": budget, "method_steps": count}
        try:
            trained = method.train(TrainRequest(dataset=data, run=run, steps=count, budget_seconds=budget,
                                                overwrite=True))
            rendered = method.render(run, data, "test", run / "renders", overwrite=True)
        except Exception as error:  # noqa: BLE001 - a method's failure is its row's, not the bench's
            reason = getattr(error, "reason", None) or (str(error).splitlines() or [type(error).__name__])[0]
            rows.append({**row, "error": reason})
            continue
        metrics = evaluate(data, rendered.out, "test", run / "metrics.json", pred_format=rendered.pred_format)
        log = run / "log.jsonl"  # a NeRF of ours logs its val curve, drawn beside the variants'
        log = str(log) if log.is_file() else None
        rows.append({**row, "val_psnr": read_log(log)[-1]["val_psnr"] if log else None, "psnr": metrics["mean"]["psnr"],
                     **{key: metrics["mean"].get(key) for key in ("psnr_foreground", "psnr_edges", "psnr_interior")},
                     "psnr_ceiling": (metrics.get("noise") or {}).get("psnr_ceiling"),
                     "ssim": metrics["mean"]["ssim"], "depth_absrel": metrics["mean"].get("depth_absrel"),
                     "lpips": metrics["mean"].get("lpips"), "lpips_note": metrics.get("notes", {}).get("lpips"),
                     "train_seconds": trained.seconds, "steps": trained.steps,
                     "steps_per_second": trained.steps_per_second,
                     "render_ms_per_frame": metrics["timing"].get("ms_per_frame") or rendered.ms_per_frame,
                     "model_mb": None if trained.model_bytes is None else trained.model_bytes / 1e6,
                     "peak_memory_mb": None if trained.peak_memory_bytes is None else trained.peak_memory_bytes / 2**20,
                     "log": log})
    return rows


def _length_cell(row: dict) -> str:
    """The budget column: seconds, a step count (a method taking steps), or – (no training)."""
    if row.get("budget") is not None:
        return f"{row['budget']:g}"
    return f"{row['method_steps']} steps" if row.get("method_steps") is not None else "–"


def _number(value, spec: str) -> str:
    return "–" if value is None else format(value, spec)


def speedups(rows: list) -> list[str]:
    """For each scene and budget: how much sooner compact reaches vanilla's final val PSNR."""
    lines = []
    for row in rows:
        if row.get("variant") != "vanilla" or "error" in row:
            continue
        compact = next((r for r in rows if r["scene"] == row["scene"] and r["variant"] == "compact"
                        and r["budget"] == row["budget"] and "error" not in r), None)
        if compact is None:
            continue
        target = read_log(row["log"])[-1]["val_psnr"]
        reached = first_time_reaching(read_log(compact["log"]), target)
        ratio = None if not reached else row["train_seconds"] / max(reached, 1e-9)
        lines.append(f"{row['scene']}, {row['budget']:g} s: vanilla ends at {target:.2f} dB val PSNR; compact reaches "
                     f"it at {reached if reached is None else f'{reached:.1f}'} s "
                     f"({'n/a' if ratio is None else f'{ratio:.0f}x sooner'})")
    return lines


def table_markdown(rows: list) -> str:
    head = ("scene", "variant", "budget s", "val PSNR", "test PSNR", "PSNR ceiling", "SSIM", "LPIPS", "depth AbsRel", "train s",
            "steps/s", "render ms",
            "model MB", "peak MB")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['scene']} | {r['variant']} | {_length_cell(r)} | {r['error']} |" + " |" * (len(head) - 4))
            continue
        cells = [r["scene"], r["variant"], _length_cell(r), _number(r.get("val_psnr"), ".2f"),
                 "–" if r["psnr"] is None else f"{r['psnr']:.2f}", ceiling_cell(r.get("psnr"), r.get("psnr_ceiling")),
                 "–" if r["ssim"] is None else f"{r['ssim']:.4f}",
                 (r.get("lpips_note") or "–") if r.get("lpips") is None else f"{r['lpips']:.4f}",
                 "–" if r["depth_absrel"] is None else f"{r['depth_absrel']:.4f}", f"{r['train_seconds']:.0f}",
                 _number(r.get("steps_per_second"), ".1f"), _number(r.get("render_ms_per_frame"), ".0f"),
                 _number(r.get("model_mb"), ".2f"), _number(r.get("peak_memory_mb"), ".0f")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# The val curve is logged while training, one ray through each pixel's centre; the test score
# renders with the filter the run chose on its val views (more rays on edge pixels, averaged
# as the ground truth's pixel box is), which scores higher on the same model.
VAL_AGAINST_TEST = ("Val PSNR (top): logged during training, one ray through each pixel's centre. Test PSNR "
                    "(bottom): the final render of the test views with the run's render filter (config.json's "
                    "render_filter: 2 x 2 or 3 x 3 rays on edge pixels, averaged like the ground truth's pixel), "
                    "which scores higher than centre rays on the same views (auto_reasons.render_filter gives both "
                    "on the val views): the two curves measure different renders.")


def pareto_plots(rows: list, out: Path) -> None:
    """OUT/pareto.png: every run's val PSNR against training seconds; each budget's final
    test PSNR against training seconds and against steps (one line a scene and variant,
    so machine load, which moves the seconds, cannot hide whether more steps still help);
    final val PSNR against model MB. A footnote says why the val curves end below the test
    points: they measure different renders (centre rays against the run's render filter)."""
    from matplotlib.figure import Figure  # matplotlib: only when a figure is drawn

    figure = Figure(figsize=(11, 8), dpi=110)
    by_time, by_size = figure.add_subplot(2, 2, 1), figure.add_subplot(2, 2, 2)
    test_by_time, test_by_steps = figure.add_subplot(2, 2, 3), figure.add_subplot(2, 2, 4)
    done = [r for r in rows if "error" not in r]
    # one colour a scene and variant in every panel (a run's budget: its line style on top),
    # so a colour never names one method in one panel and another method in the next
    cycle = [f"C{k % 10}" for k in range(len(done))]
    colour = dict(zip(dict.fromkeys((r["scene"], r["variant"]) for r in done), cycle))
    styles = ("-", "--", ":", "-.")
    for r in done:
        if r.get("log") is None:  # another tool's run: no val curve
            continue
        label = plain_text(f"{r['scene']}: {r['variant']} ({_length_cell(r)}{' s' if r['budget'] else ''})")  # $ as text
        log = read_log(r["log"])
        same = [q for q in done if (q["scene"], q["variant"]) == (r["scene"], r["variant"]) and q.get("log")]
        style = styles[same.index(r) % len(styles)]
        by_time.plot([e["seconds"] for e in log], [e["val_psnr"] for e in log], marker=".", linestyle=style,
                     color=colour[r["scene"], r["variant"]], label=label)
        by_size.scatter([r["model_mb"]], [r["val_psnr"]], color=colour[r["scene"], r["variant"]],
                        marker="os^D"[same.index(r) % 4], label=label)
    for r in done:  # a method that does not train: its PSNR at every time, as a line
        if r["psnr"] is not None and r["budget"] is None and r.get("method_steps") is None:
            test_by_time.axhline(r["psnr"], linestyle="--", linewidth=1, color=colour[r["scene"], r["variant"]],
                                 label=plain_text(f"{r['scene']}: {r['variant']} (no training)"))
    for scene, variant in dict.fromkeys((r["scene"], r["variant"]) for r in done if r["psnr"] is not None
                                        and (r["budget"] is not None or r.get("method_steps") is not None)):
        line = sorted((r for r in done if (r["scene"], r["variant"]) == (scene, variant) and r["psnr"] is not None),
                      key=lambda r: (r["budget"] or 0, r.get("method_steps") or 0, r["train_seconds"]))
        test_by_time.plot([r["train_seconds"] for r in line], [r["psnr"] for r in line], marker="o",
                          color=colour[scene, variant], label=plain_text(f"{scene}: {variant}"))
        counted = [r for r in line if r.get("steps") is not None]  # a method that does not say its steps: not here
        test_by_steps.plot([r["steps"] for r in counted], [r["psnr"] for r in counted], marker="o",
                           color=colour[scene, variant], label=plain_text(f"{scene}: {variant}"))
    by_time.set(xlabel="training seconds", ylabel="val PSNR, centre rays (dB)", title="PSNR against training time (each run)")
    by_size.set(xlabel="saved model (MB)", ylabel="final val PSNR (dB)", title="PSNR against model size", xscale="log")
    test_by_time.set(xlabel="training seconds (wall; ours: the budget)", ylabel="test PSNR (dB)",
                     title="test PSNR at the end of each budget", xscale="log")
    test_by_steps.set(xlabel="training steps", ylabel="test PSNR (dB)", title="the same against steps", xscale="log")
    for axes in (by_time, by_size, test_by_time, test_by_steps):
        axes.grid(alpha=0.3)
    if any(r.get("log") for r in done):
        by_size.legend(fontsize=6, loc="lower right")
        by_time.legend(fontsize=6, loc="lower right")
    if done:
        test_by_steps.legend(fontsize=7, loc="lower right")
        test_by_time.legend(fontsize=7, loc="lower right")
    figure.text(0.01, 0.01, VAL_AGAINST_TEST, fontsize=8, va="bottom", wrap=True)
    figure.tight_layout(rect=(0, 0.05, 1, 1))
    save_png(figure, out / "pareto.png")
