"""`nerfgauge suite report DIR`: the leaderboard of a suite folder, as JSON, Markdown and
HTML, and a report.html per dataset (eval.report.write_report).

Numbers are copied from the metrics.json files `suite evaluate` wrote with eval.evaluate
(the function behind `nerfgauge evaluate`), never recomputed, so a method's leaderboard
entry for a dataset equals its single-run `nerfgauge evaluate` numbers exactly. Columns:
every metric of eval.metrics.METRIC_NAMES that has a value somewhere (metrics added there
show up here), then our NeRF's geometry where scored (eval.geometry.summary), then cost:
training wall seconds, steps per second, peak memory, model size, render milliseconds per
frame (every method's, as its job measured them: methods.interface.TrainResult). The mean
row of a method is the mean over the datasets where the value is defined; `scenes` says
over how many. A method that failed on a dataset has its row there with the reason
(result.json "failed"), and the mean table says on how many it failed.

Uncertainty (eval.uncertainty, docs/conventions.md "Uncertainty"): each dataset's table
gives the PSNR's 95% interval: for a method run once, copied from metrics.json's `ci95`
(bootstrap over the views, as `nerfgauge evaluate` wrote it); for a method run with seeds
(`suite run --seeds`), from the aggregate of its per-seed metrics.json files (two-level
bootstrap over seeds, then views; recomputed as evaluate_suite computed aggregate.json,
which is not read back), with the seeds, each seed's PSNR and their std (the run-to-run
spread). The mean row's interval is `suite_interval` (each dataset's two-level resample,
averaged over the datasets; a fresh np.random.default_rng(EVALUATE_SEED) per method and
metric). The paired table compares every pair of methods (A before B in name order) on
each dataset both scored, on the per-frame PSNR of their metrics.json files matched by
frame name and per seed (`pair_runs`: a method run once, the baselines, is repeated for
every seed): mean difference A - B over the (seed, view) cells, its 95% paired bootstrap
interval (seeds then views resampled once for both methods; a fresh
np.random.default_rng(EVALUATE_SEED) per comparison, 10000 resamples), the two-sided
Wilcoxon signed-rank p-value on the per-view differences averaged over seeds, and whether
it is significant at 0.05.

Every metrics.json is checked before use (eval.check.validate_scores: finite numbers, the
suite's protocol and split), method and dataset names are drawn as text in figures
(eval.report.plain_text) and escaped in Markdown and HTML, and a report is made anew or
not at all (`write_leaderboard` removes the previous one first).

One table is recomputed, on purpose: the protocol-sensitivity table scores the same
renders under each scoring protocol the field uses (eval.protocols: ours, NerfBaselines',
nerfstudio's ns-eval) and gives the spread, so a reader sees how much the protocol alone
moves a number before comparing ours with a published one.
"""

from __future__ import annotations

import html

import numpy as np
from pathlib import Path

from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, write_bytes_atomic, write_json
from nerfgauge.core.folders import MARKER, folder_lock, read_marker
from nerfgauge.orchestrate.suite import robustness as suite_robustness
from nerfgauge.orchestrate.suite.definition import Suite, dataset_dir, read_results, read_suite_folder, suite_from_folder
from nerfgauge.eval.check import ScoringProtocol, protocol_of_metrics, validate_scores
from nerfgauge.eval.metrics import METRIC_NAMES
from nerfgauge.eval.uncertainty import (EVALUATE_SEED, LEVEL, LEVEL_ALPHA, RESAMPLES, aggregate_runs, mean_of,
                                        paired_comparison, run_matrix, suite_interval)
from nerfgauge.eval.protocols import combine, sensitivity, sensitivity_rows
from nerfgauge.eval.report import (PROTOCOL_CAPTION, REPORT_FIGURES, page_html, remove_previous,
                                  sortable_table_html, write_report)

GEOMETRY_COLUMNS = ("geometry_chamfer_l1", "geometry_fscore_1pct", "normal_angle_mean")
COST_COLUMNS = ("train_seconds", "steps_per_second", "peak_memory_bytes", "model_bytes", "ms_per_frame")
LOWER_IS_BETTER_PREFIXES = ("depth_absrel", "depth_rmse", "depth_mae", "geometry_chamfer", "geometry_accuracy",
                            "geometry_completeness", "normal_angle", "lpips", "train_seconds", "model_bytes",
                            "ms_per_frame", "peak_memory_bytes", "outline_alpha_rmse")
LABELS = {"psnr": "PSNR dB", "ssim": "SSIM", "psnr_foreground": "fg PSNR dB", "depth_absrel": "depth AbsRel",
          "depth_rmse": "depth RMSE", "depth_mae": "depth MAE", "depth_delta1": "depth δ<1.25",
          "opacity_iou": "opacity IoU", "psnr_outline": "outline PSNR dB", "outline_alpha_bias": "outline α bias",
          "outline_alpha_rmse": "outline α RMSE", "geometry_chamfer_l1": "Chamfer-L1", "geometry_fscore_1pct": "F@1%",
          "normal_angle_mean": "normal err °", "train_seconds": "train s", "steps_per_second": "steps/s",
          "peak_memory_bytes": "peak MB", "model_bytes": "model MB", "ms_per_frame": "render ms/frame"}


def metric_names() -> tuple:
    return tuple(METRIC_NAMES)


def scores(suite: Suite, out: Path, rel: str) -> dict:
    """A metrics.json of the suite folder (rel: a path check_result accepted), checked as
    eval.check.validate_scores checks one, and scored under the suite's [scoring] (its
    protocol, background and depth kind) on its split: the leaderboard ranks like with like."""
    path = out / rel
    document = validate_scores(read_json(path, finite=True), str(path))
    scoring = suite.scoring
    wanted = ScoringProtocol(name=scoring["protocol"], background=scoring["background"],
                             depth_kind=scoring["depth_kind"])
    scored = protocol_of_metrics(document, str(path))
    if scored != wanted or document.get("split") != scoring["split"]:
        raise InputError(f"{path} was scored under protocol {scored} on split {document.get('split')!r}; the suite "
                         f"scores under {wanted} on {scoring['split']!r}: evaluate again")
    return document


def leaderboard(suite: Suite, out) -> dict:
    """The leaderboard document from the suite folder's results (checked by read_results).
    A seeded method's aggregate is recomputed from its per-seed metrics.json files
    (eval.uncertainty.aggregate_runs, as evaluate_suite computed aggregate.json), so
    aggregate.json is never read back."""
    out = Path(out)
    results = read_results(suite, out)
    methods, documents = {}, {}
    for method, result in results.items():
        scenes = {}
        for entry in suite.scenes:
            row = result["datasets"].get(entry.id)
            if row is None:
                continue
            document = scores(suite, out, row["metrics"])
            runs = row.get("runs")
            if runs:  # suite run --seeds: every seed's metrics.json, and their aggregate
                docs = [scores(suite, out, run["metrics"]) for run in runs]
                aggregate = aggregate_runs(docs, [run["seed"] for run in runs],
                                           [m for m in METRIC_NAMES if m in docs[0]["mean"]])
                documents.setdefault(method, {})[entry.id] = ([run["seed"] for run in runs], docs)
                values = {name: aggregate["mean"].get(name) for name in document["mean"]}
                spread = {"seeds": [run["seed"] for run in runs], "aggregate": row["aggregate"],
                          "psnr_per_seed": aggregate["per_seed"].get("psnr"),
                          "psnr_seed_std": aggregate["seed_std"].get("psnr"),
                          "psnr_variance": aggregate["variance"].get("psnr")}
                interval = aggregate["ci95"].get("psnr")
            else:
                documents.setdefault(method, {})[entry.id] = (None, [document])
                values, spread = dict(document["mean"]), {}
                interval = (document.get("ci95") or {}).get("psnr")
            geometry = row.get("geometry") or {}
            values.update({key: geometry.get(key) for key in GEOMETRY_COLUMNS})
            values.update({name: row.get(name) for name in COST_COLUMNS})
            scenes[entry.id] = {"values": values, "frames": len(document["frames"]),
                                "psnr_ci95": interval, **spread,
                                "geometry_na": geometry.get("n/a"), "metrics": row["metrics"]}
        methods[method] = {"scenes": scenes, **{name: dict(result[name]) for name in ("skipped", "failed")
                                                if result.get(name)}}
    columns = [name for name in (*metric_names(), *GEOMETRY_COLUMNS, *COST_COLUMNS)
               if any(isinstance(s["values"].get(name), (int, float)) for m in methods.values() for s in m["scenes"].values())]
    for name_of_method, method in methods.items():
        method["mean"], method["scenes_scored"], method["ci95"] = {}, {}, {}
        for name in columns:
            defined = [s["values"][name] for s in method["scenes"].values() if isinstance(s["values"].get(name), (int, float))]
            method["mean"][name] = mean_of(defined, f"{name_of_method}: mean {name} over datasets") if defined else None
            method["scenes_scored"][name] = len(defined)
            if name in METRIC_NAMES:  # the suite mean's interval (eval.uncertainty.suite_interval)
                tables = [run_matrix(docs, name)[0] for _, docs in documents.get(name_of_method, {}).values()]
                interval = suite_interval(tables, np.random.default_rng(EVALUATE_SEED)) if tables else None
                method["ci95"][name] = None if interval is None else interval.to_json()
    unavailable = unavailable_metrics(suite, out, results)
    paired = paired_comparisons(documents, [e.id for e in suite.scenes])
    return {**suite.identity(), "schema": 1, "columns": columns, "scenes": [e.id for e in suite.scenes],
            "methods": methods, **({"unavailable": unavailable} if unavailable else {}),
            **({"paired": paired} if paired["rows"] else {})}


PAIRED_METRIC = "psnr"
ROBUSTNESS_CAPTION = ("Robustness: each method's score against the level of one train-view degradation "
                      "(orchestrate.suite.robustness; docs/conventions.md, Degradations)")
PAIRED_CAPTION = ("Paired comparison on PSNR: every pair of methods, A minus B, per dataset (same views and "
                  "seeds; 95% paired bootstrap interval over seeds, then views; two-sided Wilcoxon signed-rank test "
                  f"on the per-view differences at {LEVEL_ALPHA:g})")


def paired_comparisons(documents: dict, scenes: list, metric: str = PAIRED_METRIC) -> dict:
    """{"metric", "difference", "level", "alpha", "test", "resamples", "seed", "rows": [...]}:
    one row per (dataset, pair of methods A before B in name order) that both scored:
    {"scene", "reference" (A), "method" (B), "views", "seeds", "mean_difference" (A - B),
    "ci95", "p_value", "significant", "degenerate"} from eval.uncertainty.paired_comparison
    on the per-frame values matched by frame name (A's order; frames either leaves undefined
    are left out), one row per training seed paired by `pair_runs` (by seed; a method run
    once, without a seed, repeated for every seed of the other), so the differences are
    per (seed, view) and the interval resamples seeds then views; a fresh
    default_rng(EVALUATE_SEED) per row. documents: {method: {scene id: (seeds or None,
    [metrics.json document per seed])}}."""
    rows = []
    names = sorted(documents)
    for scene in scenes:
        for i, reference in enumerate(names):
            ours = documents[reference].get(scene)
            for method in names[i + 1:]:
                theirs = documents[method].get(scene)
                pairs = None if ours is None or theirs is None else pair_runs(ours, theirs)
                if pairs is None:
                    continue
                seeds, our_docs, their_docs = pairs
                their_names = {frame["name"] for frame in their_docs[0]["frames"]}
                frames = [frame["name"] for frame in our_docs[0]["frames"] if frame["name"] in their_names]
                result = paired_comparison(run_matrix(our_docs, metric, frames)[0],
                                           run_matrix(their_docs, metric, frames)[0],
                                           np.random.default_rng(EVALUATE_SEED))
                rows.append({"scene": scene, "reference": reference, "method": method, "views": result["n_views"],
                             "seeds": seeds, **{key: result[key] for key in ("mean_difference", "ci95", "p_value",
                                                                             "significant", "degenerate")}})
    return {"metric": metric, "difference": "reference - method", "level": LEVEL,
            "alpha": LEVEL_ALPHA, "test": "Wilcoxon signed-rank, two-sided (scipy.stats.wilcoxon, exact for n <= 50)",
            "resamples": RESAMPLES, "seed": EVALUATE_SEED, "rows": rows}


def pair_runs(ours: tuple, theirs: tuple):
    """(seeds, our documents, their documents) paired run by run: by seed where both were run
    with seeds (the seeds both have, in our order); a method run once without a seed (the
    baselines: deterministic functions of the dataset) is paired with every seed of the
    other, its one document repeated. None when two seeded methods share no seed."""
    (our_seeds, our_docs), (their_seeds, their_docs) = ours, theirs
    if our_seeds is not None and their_seeds is not None:
        common = [seed for seed in our_seeds if seed in their_seeds]
        if not common:
            return None
        return (common, [our_docs[our_seeds.index(s)] for s in common],
                [their_docs[their_seeds.index(s)] for s in common])
    if our_seeds is None and their_seeds is None:
        return None, our_docs, their_docs
    if our_seeds is None:
        return their_seeds, our_docs * len(their_docs), their_docs
    return our_seeds, our_docs, their_docs * len(our_docs)


def paired_rows(paired: dict) -> list[list[str]]:
    """The paired table, a header row first."""
    rows = [["dataset", "A", "B", "seeds", "views", "Δ PSNR dB (A - B)", "95% CI", "Wilcoxon p",
             f"significant at {paired['alpha']:g}"]]
    for row in paired["rows"]:
        ci = row["ci95"]
        mark = "–" if row["significant"] is None else "yes" if row["significant"] else "no (not significant)"
        seeds = row.get("seeds")
        rows.append([row["scene"], row["reference"], row["method"], "1 (no seed)" if seeds is None else str(len(seeds)), str(row["views"]),
                     "–" if row["mean_difference"] is None else f"{row['mean_difference']:+.2f}",
                     "–" if ci is None else f"[{ci[0]:+.2f}, {ci[1]:+.2f}]" + (" (1 view)" if row["degenerate"] else ""),
                     "–" if row["p_value"] is None else f"{row['p_value']:.3g}", mark])
    return rows


def unavailable_metrics(suite: Suite, out: Path, results: dict) -> dict:
    """{id: {metric: reason}} of folder entries (ground truth nerfgauge did not write): the
    metrics their metrics.json says are unavailable (shown as not defined)."""
    unavailable = {}
    for entry in suite.scenes:
        if not entry.foreign:
            continue
        for result in results.values():
            row = result["datasets"].get(entry.id)
            if row is not None:
                notes = scores(suite, out, row["metrics"]).get("notes") or {}
                unavailable[entry.id] = {metric: note.removeprefix("unavailable: ") for metric, note in sorted(notes.items())
                                         if isinstance(note, str) and note.startswith("unavailable: ")}
                break
    return unavailable


def _cell(name: str, value) -> str:
    if not isinstance(value, (int, float)):
        return "–"
    if name in ("model_bytes", "peak_memory_bytes"):
        return f"{value / 1e6:.2f}"
    if name == "steps_per_second":
        return f"{value:.1f}"
    if name in ("psnr", "psnr_foreground", "train_seconds", "ms_per_frame", "normal_angle_mean") or name.startswith("psnr"):
        return f"{value:.2f}"
    return f"{value:.4f}"


def _label(name: str) -> str:
    return LABELS.get(name, name) + (" ↓" if name.startswith(LOWER_IS_BETTER_PREFIXES) else "")


def tables(board: dict) -> list[tuple[str, list[list[str]]]]:
    """(title, rows with a header row first): the means, then one table per dataset."""
    columns = board["columns"]
    n = len(board["scenes"])
    failures = any(data.get("failed") for data in board["methods"].values())
    head = ["method", "scenes"] + [_label(c) for c in columns] + ["PSNR 95% CI"] + (["failed"] if failures else [])
    mean_rows = [head]
    for method, data in board["methods"].items():
        failed = data.get("failed") or {}
        mean_rows.append([method, f"{len(data['scenes'])}/{n}" if len(data["scenes"]) != n else str(n)]
                         + [_cell(c, data["mean"].get(c)) for c in columns]
                         + [_interval((data.get("ci95") or {}).get("psnr"))]
                         + ([f"{len(failed)}/{n}: {next(iter(failed.values()))}" if failed else "–"]
                            if failures else []))
    result = [(f"mean over datasets ({n})", mean_rows)]
    for scene in board["scenes"]:
        rows = [["method", "frames"] + [_label(c) for c in columns]
                + ["PSNR 95% CI", "seeds", "PSNR per seed (std)", "PSNR variance: seed / view / residual"]]
        for method, data in board["methods"].items():
            entry = data["scenes"].get(scene)
            if entry is None:
                failed, reason = data.get("failed", {}).get(scene), data.get("skipped", {}).get(scene)
                cell = f"failed: {failed}" if failed else f"n/a: {reason}" if reason else "n/a"
                rows.append([method, cell] + ["–"] * (len(columns) + 4))
            else:
                rows.append([method, str(entry["frames"])] + [_cell(c, entry["values"].get(c)) for c in columns]
                            + [_interval(entry.get("psnr_ci95")), _seeds(entry), _per_seed(entry),
                               _variance(entry.get("psnr_variance"))])
        result.append((scene, rows))
    return result


def _interval(ci) -> str:
    return "–" if ci is None else f"[{ci[0]:.2f}, {ci[1]:.2f}]"


def _seeds(entry: dict) -> str:
    seeds = entry.get("seeds")
    return "1 (no seed)" if seeds is None else ",".join(map(str, seeds))


def _variance(split) -> str:
    """eval.uncertainty.variance_split's components (dB²) and the seeds' share."""
    if not split or split.get("var_seed") is None or split.get("var_residual") is None:
        return "–"
    share = split.get("seed_share")
    return (f"{split['var_seed']:.3g} / {split['var_view']:.3g} / {split['var_residual']:.3g}"
            + ("" if share is None else f" (seeds {100 * share:.0f}%)"))


def _per_seed(entry: dict) -> str:
    """Each seed's PSNR and the sample std of those (the run-to-run spread)."""
    values = entry.get("psnr_per_seed")
    if not values:
        return "–"
    std = entry.get("psnr_seed_std")
    return " ".join("–" if v is None else f"{v:.2f}" for v in values) + ("" if std is None else f" (±{std:.2f})")


# The sensitivity table rescores one run per method; the tables above average every seed.
FIRST_SEED = " (a seeded method: its first seed's renders)"


def protocol_sensitivity(suite: Suite, out) -> dict:
    """{method: eval.protocols sensitivity document over the suite's datasets}: every
    method's renders (each result.json row's renders, in its format; from before rows
    recorded them, pred_root/<dataset id> read as found) under each protocol. A seeded
    method's first seed stands for it. Render folders that are gone are left out (the
    leaderboard's numbers do not need them)."""
    out = Path(out)
    documents = {}
    for method, result in read_results(suite, out).items():
        found = []
        for entry in suite.scenes:
            renders, pred_format = rendered(out, result, entry.id)
            if renders is not None and renders.is_dir():
                found.append(sensitivity(dataset_dir(out, entry), renders, suite.scoring["split"],
                                         pred_format=pred_format, background=suite.scoring["background"]))
        if found:
            documents[method] = combine(found)
    return documents


def rendered(out: Path, result: dict, entry_id: str) -> tuple:
    """(renders folder, pred format) of a method's (first) run on a dataset as result.json
    records it (check_result checked where it lies); (None, None) where it has none."""
    row = result.get("datasets", {}).get(entry_id)
    if row is None:
        return None, None
    run = row["runs"][0] if row.get("runs") else row
    if run.get("renders") is not None:
        return out / run["renders"], run["pred_format"]  # a relative path joins out; an absolute one stays
    root = result.get("pred_root")
    if not root:
        return None, None
    seeds = result.get("seeds")
    return Path(root) / (f"seed-{seeds[0]}" if seeds else "") / entry_id, "auto"


def unavailable_line(notes: dict) -> str:
    """One line: which metrics a folder entry cannot give and why (grouped by reason)."""
    by_reason = {}
    for metric, reason in notes.items():
        by_reason.setdefault(reason, []).append(metric)
    return "Unavailable on this ground truth (not defined, –): " + "; ".join(
        f"{', '.join(metrics)}: {reason}" for reason, metrics in by_reason.items()) + "."


def _md_row(cells) -> str:
    """One Markdown table row; a `|` or `\\` in a cell (a method named a|b) is escaped so it
    stays one cell."""
    return "| " + " | ".join(str(cell).replace("\\", "\\\\").replace("|", "\\|") for cell in cells) + " |"


def markdown(board: dict) -> str:
    lines = [f"# Leaderboard: suite {board['suite']} v{board['version']}", "",
             f"suite sha256 `{board['suite_sha256']}`; ↓ lower is better; – not defined or not applicable; "
             "means are over the datasets where a value is defined (leaderboard.json: scenes_scored).", ""]
    for title, rows in tables(board):
        lines += [f"## {title}", "", _md_row(rows[0]), "|" + "---|" * len(rows[0])]
        lines += [_md_row(row) for row in rows[1:]]
        lines.append("")
        if title in board.get("unavailable", {}):
            lines += [unavailable_line(board["unavailable"][title]), ""]
    if board.get("paired"):
        rows = paired_rows(board["paired"])
        lines += [f"## {PAIRED_CAPTION}", "", _md_row(rows[0]), "|" + "---|" * len(rows[0])]
        lines += [_md_row(row) for row in rows[1:]]
        lines.append("")
    if board.get("robustness"):
        rows = suite_robustness.rows(board["robustness"])
        lines += [f"## {ROBUSTNESS_CAPTION}", "", f"![robustness curves]({suite_robustness.PLOT})", "",
                  _md_row(rows[0]), "|" + "---|" * len(rows[0])]
        lines += [_md_row(row) for row in rows[1:]]
        lines.append("")
    sensitivity = board.get("protocol_sensitivity")
    if sensitivity:
        rows = sensitivity_rows(sensitivity)
        lines += [f"## {PROTOCOL_CAPTION}{FIRST_SEED}", "", _md_row(rows[0]), "|" + "---|" * len(rows[0])]
        lines += [_md_row(row) for row in rows[1:]]
        lines.append("")
    return "\n".join(lines)


LEADERBOARD_FILES = ("leaderboard.json", "leaderboard.md", "leaderboard.html", suite_robustness.PLOT)


def write_leaderboard(suite: Suite | None, out, *, log=print, reports: bool = True) -> dict:
    """leaderboard.json, .md and .html in `out`, and report/<id>/report.html per dataset.
    suite: None reads it from out/suite.json (orchestrate.suite.suite_from_folder).

    Made anew or not at all: in a folder whose marker says it is a nerfgauge suite, under
    its write lock, the previous leaderboard files, robustness.png and every
    report/<id>/'s report.html and figures are removed before anything is read or computed,
    so a report that fails (a malformed state file, a figure that cannot be drawn) leaves
    nothing that looks current. A folder without that marker is refused untouched."""
    out = Path(out)
    marker = read_marker(out) if out.is_dir() else None
    if marker is None or marker["kind"] != "suite":
        raise InputError(f"{out} is not a suite folder (no suite marker {MARKER}); make it with nerfgauge suite generate")
    with folder_lock(out):
        reports_root = out / "report"
        ids = (sorted(p.name for p in reports_root.iterdir() if p.is_dir() and not p.is_symlink())
               if reports_root.is_dir() and not reports_root.is_symlink() else [])
        remove_previous([out / name for name in LEADERBOARD_FILES]
                        + [reports_root / entry_id / name for entry_id in ids
                           for name in ("report.html", *REPORT_FIGURES)])
        if suite is None:
            suite = suite_from_folder(out)
        read_suite_folder(suite, out)
        return _write_leaderboard(suite, out, log, reports)


def _write_leaderboard(suite: Suite, out: Path, log, reports: bool) -> dict:
    board = leaderboard(suite, out)
    board["protocol_sensitivity"] = protocol_sensitivity(suite, out)
    curves = suite_robustness.robustness(suite, board)  # score against degradation level, when the suite has levels
    if curves is not None:
        board["robustness"] = curves
        suite_robustness.plot(curves, out / suite_robustness.PLOT)
    links = {}
    if reports:
        for entry in suite.scenes:
            page = scene_report(suite, out, entry, board)
            if page is not None:
                links[entry.id] = page.relative_to(out).as_posix()
    write_json(out / "leaderboard.json", board)
    write_bytes_atomic(out / "leaderboard.md", markdown(board).encode())
    sections = []
    for title, rows in tables(board):
        link = f" (<a href='{html.escape(links[title])}'>report</a>)" if title in links else ""
        sections.append(f"<h2>{html.escape(title)}{link}</h2>" + sortable_table_html(rows))
        if title in board.get("unavailable", {}):
            sections.append(f"<p>{html.escape(unavailable_line(board['unavailable'][title]))}</p>")
    if board.get("paired"):
        sections.append(f"<h2>{html.escape(PAIRED_CAPTION)}</h2>" + sortable_table_html(paired_rows(board["paired"])))
    if board.get("robustness"):
        sections.append(f"<h2>{html.escape(ROBUSTNESS_CAPTION)}</h2><img src='{suite_robustness.PLOT}' "
                        f"alt='robustness curves'>" + sortable_table_html(suite_robustness.rows(board["robustness"])))
    if board["protocol_sensitivity"]:
        sections.append(f"<h2>{html.escape(PROTOCOL_CAPTION + FIRST_SEED)}</h2>"
                        + sortable_table_html(sensitivity_rows(board["protocol_sensitivity"])))
    notes = [f"suite sha256 {board['suite_sha256']}", "↓ lower is better; – not defined or not applicable; "
             "means are over the datasets where a value is defined (leaderboard.json: scenes_scored); "
             "click a column header to sort."]
    write_bytes_atomic(out / "leaderboard.html",
                       page_html(f"nerfgauge leaderboard: {board['suite']} v{board['version']}", "".join(sections), notes))
    log(markdown(board).split("\n## ", 2)[1].split("\n", 1)[1] if len(board["scenes"]) else "")
    log(f"leaderboard: {out / 'leaderboard.md'}, {out / 'leaderboard.html'}, {out / 'leaderboard.json'}")
    return board


def scene_report(suite: Suite, out: Path, entry, board: dict):
    """report/<id>/report.html: a NeRF of ours against the other methods on one dataset:
    the first method (in name order) whose run on it has a training log
    (runs/<method>/[seed-<s>/]<id>/log.jsonl) and renders in our layout. Returns its path,
    or None where no such run is in the suite folder."""
    results = read_results(suite, out)
    for ours, data in board["methods"].items():
        scene = data["scenes"].get(entry.id)
        renders, pred_format = rendered(out, results[ours], entry.id) if scene is not None else (None, None)
        seeds = (scene or {}).get("seeds")
        where = Path(ours) / (f"seed-{seeds[0]}" if seeds else "") / entry.id  # seeded: the first seed is shown
        log_path = out / "runs" / where / "log.jsonl"
        if renders is not None and pred_format == "nerfgauge" and renders.is_dir() and log_path.is_file():
            break
    else:
        return None
    documents = {method: scores(suite, out, data["scenes"][entry.id]["metrics"])
                 for method, data in board["methods"].items() if entry.id in data["scenes"]}
    target = out / "report" / entry.id / "report.html"
    write_report(target, f"{suite.name} v{suite.version}: {entry.id}", dataset_dir(out, entry), renders,
                 documents, log_path=log_path, ours=ours,
                 train_seconds=board["methods"][ours]["scenes"][entry.id]["values"].get("train_seconds"),
                 notes=[f"{ours}; scene {entry.scene}, seed {entry.seed}, {entry.dataset.get('width')}x"
                        f"{entry.dataset.get('height')}, split {suite.scoring['split']}"
                        + (f"; training seed {seeds[0]} of {len(seeds)} shown (leaderboard: all)" if seeds else "")])
    return target
