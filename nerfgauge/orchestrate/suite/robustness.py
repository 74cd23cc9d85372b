"""Robustness curves of a suite: each method's score against the level of one train-view
degradation (generate.degrade), from the leaderboard's numbers (copied from each dataset's
metrics.json, never recomputed).

Which entries make a curve: an entry's degradations are its GenerateConfig's degradation
fields (generate.degrade.FIELDS; degrade_seed is no level). Entries whose other settings
(scene, seed, resolution, views, ...) agree form a group; in a group, the entries with
exactly one degradation field set are points of that field's curve at its value, and the
entry with none is level 0 of every curve of the group. An entry with two or more set
(a combined degradation) is on no curve (listed under "combined"). A curve needs at least
two levels. Any suite whose entries vary one degradation at a time has curves: the
built-in `robustness` suite crosses pose noise and exposure with levels this way.

The leaderboard gets "robustness": {"curves": [{"group", "field", "levels": [...],
"entries": [...], "scores": {method: {metric: [value per level or None]}}}], "combined": [...]},
a table (one row per curve, method and level) and robustness.png (PSNR against level, one
panel per curve, one line per method; method names drawn as text, eval.report.plain_text).
"""

from __future__ import annotations

import dataclasses

from nerfgauge.eval.report import plain_text, save_png
from nerfgauge.generate.degrade import FIELDS
from nerfgauge.generate.pipeline import GenerateConfig

LEVEL_FIELDS = tuple(name for name in FIELDS if name != "degrade_seed")
METRICS = ("psnr", "ssim", "lpips")
UNITS = {"pose_noise_rotation": "RMS deg", "pose_noise_translation": "RMS / spread", "exposure_ev": "EV sd",
         "white_balance": "log2 gain sd", "vignetting": "k"}
PLOT = "robustness.png"


def _split(entry) -> tuple:
    """(the entry's settings without its degradation levels as a hashable key, {field: level} set)."""
    config = GenerateConfig(scene=entry.scene, seed=entry.seed, **entry.dataset)
    default = GenerateConfig()
    levels = {name: getattr(config, name) for name in LEVEL_FIELDS if getattr(config, name) != getattr(default, name)}
    base = dataclasses.replace(config, **{name: getattr(default, name) for name in LEVEL_FIELDS})
    return repr(sorted(base.to_json().items())), levels


def robustness(suite, board: dict) -> dict | None:
    """The curves (module docstring) of `suite` from `board` (suite_report.leaderboard);
    None when the suite has no entry on a curve of at least two levels."""
    groups, combined = {}, []
    for entry in suite.scenes:
        if entry.foreign:
            continue
        key, levels = _split(entry)
        group = groups.setdefault(key, {"clean": None, "points": {}, "label": f"{entry.scene} seed {entry.seed}"})
        if not levels:
            group["clean"] = group["clean"] or entry.id
        elif len(levels) == 1:
            (name, level), = levels.items()
            group["points"].setdefault(name, []).append((float(level), entry.id))
        else:
            combined.append({"entry": entry.id, "levels": levels})
    curves = []
    for group in groups.values():
        for name, points in group["points"].items():
            points = sorted(([(0.0, group["clean"])] if group["clean"] else []) + points)
            if len(points) < 2:
                continue
            ids = [entry_id for _, entry_id in points]
            scores = {}
            for method, data in board["methods"].items():
                rows = [data["scenes"].get(entry_id) for entry_id in ids]
                scores[method] = {metric: [None if row is None else row["values"].get(metric) for row in rows]
                                  for metric in METRICS}
            curves.append({"group": group["label"], "field": name, "unit": UNITS[name],
                           "levels": [level for level, _ in points], "entries": ids, "scores": scores})
    if not curves:
        return None
    return {"curves": curves, "combined": combined,
            "note": "scores copied from each dataset's metrics.json; level 0 is the group's clean entry"}


def rows(document: dict) -> list[list[str]]:
    """The table: one row per curve, method and level."""
    table = [["curve", "method", "level", "dataset", "PSNR dB", "SSIM", "LPIPS"]]
    for curve in document["curves"]:
        for method, scores in curve["scores"].items():
            for k, level in enumerate(curve["levels"]):
                cells = ["–" if scores[m][k] is None else f"{scores[m][k]:.4g}" for m in METRICS]
                table.append([f"{curve['field']} ({curve['group']})", method, f"{level:g} {curve['unit']}",
                              curve["entries"][k], *cells])
    return table


def plot(document: dict, out) -> None:
    """robustness.png: PSNR against level, one panel per curve, one line per method."""
    from matplotlib.figure import Figure  # matplotlib

    curves = document["curves"]
    figure = Figure(figsize=(4.2 * len(curves), 3.6), dpi=110)
    for k, curve in enumerate(curves, 1):
        axes = figure.add_subplot(1, len(curves), k)
        for method, scores in curve["scores"].items():
            points = [(level, value) for level, value in zip(curve["levels"], scores["psnr"]) if value is not None]
            if points:
                axes.plot(*zip(*points), marker="o", label=plain_text(method))
        axes.set_xlabel(plain_text(f"{curve['field']} ({curve['unit']})"))
        axes.set_ylabel("test PSNR (dB)")
        axes.set_title(plain_text(curve["group"]), fontsize=9)
        axes.grid(alpha=0.3)
        if k == 1:
            axes.legend(fontsize=7)
    figure.tight_layout()
    save_png(figure, out)
