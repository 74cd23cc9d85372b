"""`nerfgauge check --calibrate RESULTS... --false-alarm A --out FILE`: thresholds proposed
from measured runs, for a stated false-alarm rate.

RESULTS are metrics.json files (a folder: every metrics.json under it), one per training
run of the same pipeline with different seeds (e.g. `nerfgauge run --seeds 10`'s
eval/<model>/seed-<s>/metrics.json, or a suite's results/compact-nerf/<id>/seed-<s>/). The
runs are grouped by the scene their metrics.json names; each scene needs K >= 2 runs.

The bound, per metric (`proposed_bound`): the one-sided normal **prediction bound** for
one new run,

    floor   = mean - t_{1-A, K-1} * s * sqrt(1 + 1/K)      (metrics where higher is better)
    ceiling = mean + t_{1-A, K-1} * s * sqrt(1 + 1/K)      (lower is better)

with mean and s (ddof=1) over the K runs' means and t the Student t quantile. If the runs'
scores are independent draws from one normal distribution, a new run from the same
distribution falls below the floor with probability exactly A ((X_new - mean) / (s
sqrt(1 + 1/K)) is t-distributed with K - 1 degrees of freedom), averaged over calibration
sets. Why not an order statistic (the minimum of the runs): its false-alarm rate is 1/(K+1)
whatever the distribution, 0.09 for K = 10; reaching 0.05 would need K >= 19 runs, and
0.01 K >= 99. The normal bound gives any rate from few runs, at the price of the normality
assumption: run-to-run PSNR spreads of a fixed pipeline are close to normal in the field's
reports, but a heavy lower tail (a seed that sometimes fails) makes the real rate higher
than A; measure it on new seeds (the lead's job) before trusting a floor.

The quantile is Student's upper-tail quantile computed directly for A (`t_upper_quantile`),
never as t.ppf(1 - A): below A = 1.1e-16, 1 - A rounds to 1 and ppf(1) is inf, which made
-inf floors, and nan ones where s = 0 (inf * 0). The bound is exact under normality for
every A, so a tiny rate gets the finite, very loose bound it asks for (A = 1e-300 with
K = 10: t about 5e33, a floor that never fires), not a refusal at an arbitrary rate; such
a bound rests entirely on the normal tail. Every number written (mean, s, bound, the
training medians) is checked finite first: values so large that the arithmetic leaves
float range (1e308 in two runs), or a rate below the smallest normal float (2.2e-308),
are one line naming the scene, the metric and why, exit 2.

All runs must be scored under one protocol (eval.check.ScoringProtocol: the protocol,
its background, the depth kind); mixed runs are refused naming two of them. The file
written records it in its [protocol] table, which `check` compares with every metrics
file it gates.

A is per bound. With m bounds in a gate the chance that at least one fires on a good run
is at most m * A (Bonferroni): pass A / m for a family-wise rate A.

Metrics with no direction (dataset properties such as covisible_fraction) are not
proposed. A metric that is null in some run is left out with a comment. When the runs
record training (`nerfgauge run` writes metrics.json's `training`: steps, seconds,
steps_per_second), the table gets `training = { steps = ..., steps_per_second = ... }`
(the medians), which `check` compares a run's training with (eval.check: under-trained).

The output is a thresholds file in thresholds.toml's format whose first line is
`# nerfgauge-kind: thresholds` (core.outputs: `--out` replaces only such a file), with the
method, the rate, and every run's values (source file, seed where known) as comments.
"""

from __future__ import annotations

import datetime
import math
import re
import statistics
import sys
from pathlib import Path

from nerfgauge.core.errors import InputError
from nerfgauge.eval.check import finite_number, load_metrics, protocol_of_metrics
from nerfgauge.eval.geometry import SUMMARY_NAMES
from nerfgauge.eval.metrics import METRIC_NAMES as IMAGE_METRIC_NAMES

THRESHOLDS_KIND = "thresholds"
HIGHER_IS_BETTER = ("psnr", "ssim", "psnr_foreground", "psnr_covisible", "ssim_covisible", "depth_delta1",
                    "opacity_iou", "geometry_normal_consistency", "geometry_fscore_0p5pct", "geometry_fscore_1pct",
                    "normal_within_11_25", "normal_within_22_5", "normal_within_30")
LOWER_IS_BETTER = ("depth_absrel", "depth_rmse", "depth_mae", "depth_absrel_resolved", "lpips", "geometry_accuracy",
                   "geometry_completeness", "geometry_chamfer_l1", "normal_angle_mean", "normal_angle_median")
SEED_IN_PATH = re.compile(r"(?:^|/)seed-(\d+)(?:/|$)")
SMALLEST_RATE = sys.float_info.min  # 2.2e-308: below, 2A is subnormal and the quantile loses its digits


def check_rate(false_alarm) -> float:
    """A false-alarm rate in [SMALLEST_RATE, 1), as a float; InputError naming the range otherwise."""
    if not (isinstance(false_alarm, float) and SMALLEST_RATE <= false_alarm < 1):
        raise InputError(f"--false-alarm must be a number from {SMALLEST_RATE:.3g} (the smallest normal float) "
                         f"to below 1, got {false_alarm!r}")
    return false_alarm


def t_upper_quantile(false_alarm: float, df: int) -> float:
    """q with P(T > q) = A for Student's t with df degrees of freedom, to float precision for
    every A in [SMALLEST_RATE, 1): never through 1 - A (module docstring). df 1 (Cauchy:
    P(T > q) = atan(1/q) / pi) and df 2 (P(T > q) = (1 - q / sqrt(2 + q^2)) / 2) in closed
    form; df >= 3 from P(|T| > q) = I_x(df/2, 1/2) at x = df / (df + q^2), inverted by
    scipy.special.betaincinv (x >= 1e-216 there, so it never underflows, unlike df 1 and
    2 whose x reaches 1e-599). A > 1/2 by symmetry: q(A) = -q(1 - A)."""
    from scipy.special import betaincinv  # scipy: a dependency of scikit-image, which metrics needs

    if false_alarm > 0.5:
        return -t_upper_quantile(1.0 - false_alarm, df)
    if df == 1:
        return 1.0 / math.tan(math.pi * false_alarm)
    if df == 2:
        return (1.0 - 2.0 * false_alarm) / math.sqrt(2.0 * false_alarm * (1.0 - false_alarm))
    x = float(betaincinv(df / 2.0, 0.5, 2.0 * false_alarm))
    return math.sqrt(df * (1.0 - x) / x)


def proposed_bound(values, false_alarm: float, higher_is_better: bool = True, what: str = "the bound") -> float:
    """The one-sided normal prediction bound of the module docstring for K = len(values) >= 2;
    InputError (naming `what`) when a value or the result is not a finite float."""
    return _prediction_bound(values, false_alarm, higher_is_better, what)["bound"]


def _prediction_bound(values, false_alarm: float, higher_is_better: bool, what: str) -> dict:
    """{"kind", "bound", "mean", "std", "k"}, every number checked finite."""
    k = len(values)
    if k < 2:
        raise InputError(f"a prediction bound needs at least 2 runs, got {k}")
    check_rate(false_alarm)
    if not all(finite_number(v) for v in values):
        raise InputError(f"{what}: the runs' values must be finite numbers, got {[v for v in values][:4]!r}")
    try:
        mean = math.fsum(values) / k
        s = statistics.stdev(values)
        quantile = t_upper_quantile(false_alarm, k - 1)
        margin = quantile * s * math.sqrt(1.0 + 1.0 / k)
        bound = mean - margin if higher_is_better else mean + margin
    except OverflowError:
        mean = s = quantile = bound = math.inf
    for name, value in (("mean", mean), ("s", s), ("t quantile", quantile), ("bound", bound)):
        if not math.isfinite(value):
            raise InputError(f"{what}: the {name} is beyond float range at --false-alarm {false_alarm:g} with K = {k} "
                             f"runs (values up to {max(map(abs, values)):.3g}); use a larger rate, or check the runs' "
                             "values")
    return {"kind": "min" if higher_is_better else "max", "bound": bound, "mean": mean, "std": s, "k": k}


def metric_files(paths) -> list[Path]:
    """The metrics.json files: files as given, folders searched (sorted) for metrics.json."""
    files = []
    for path in map(Path, paths):
        if path.is_dir():
            found = sorted(path.rglob("metrics.json"))
            if not found:
                raise InputError(f"--calibrate: no metrics.json under {path}")
            files += found
        elif path.is_file():
            files.append(path)
        else:
            raise InputError(f"--calibrate: {path} not found")
    if len(set(files)) != len(files):
        raise InputError("--calibrate: a metrics file is given twice")
    return files


def seed_of(path: Path, document: dict):
    """The training seed of a run: metrics.json's training.seed, else a seed-<s> folder in its path."""
    training = document.get("training")
    if isinstance(training, dict) and isinstance(training.get("seed"), int):
        return training["seed"]
    found = SEED_IN_PATH.search(Path(path).as_posix())
    return int(found.group(1)) if found else None


def calibrate(paths, false_alarm: float, metrics=None) -> dict:
    """{scene: {"runs": [{"source", "seed", "values": {metric: value}, "training"}],
    "bounds": {metric: {"kind": "min"|"max", "bound", "mean", "std", "k"}}, "left_out":
    {metric: why}, "training": {"steps", "steps_per_second"} or None}}."""
    check_rate(false_alarm)
    wanted = tuple(metrics) if metrics else HIGHER_IS_BETTER + LOWER_IS_BETTER
    unknown = [m for m in wanted if m not in HIGHER_IS_BETTER + LOWER_IS_BETTER]
    if unknown:
        raise InputError(f"--metrics: {unknown[0]!r} has no direction to calibrate; known: "
                         f"{', '.join(HIGHER_IS_BETTER + LOWER_IS_BETTER)}")
    scenes: dict = {}
    protocols = {}  # {ScoringProtocol: the first file scored under it}
    for path in metric_files(paths):
        document = load_metrics(path)
        protocols.setdefault(protocol_of_metrics(document, str(path)), path)
        values = {**(document.get("geometry") or {}), **document["mean"]}
        training = document.get("training") if isinstance(document.get("training"), dict) else None
        scenes.setdefault(document["scene"], {"runs": []})["runs"].append(
            {"source": str(path), "seed": seed_of(path, document), "training": training,
             "values": {m: values.get(m) for m in wanted if m in values}})
    if len(protocols) > 1:
        (first, one), (second, other) = list(protocols.items())[:2]
        raise InputError(f"--calibrate: the runs were scored under {len(protocols)} protocols ({one}: {first}; "
                         f"{other}: {second}): scores of different protocols are not comparable; calibrate the "
                         "runs of one protocol")
    for scene, data in scenes.items():
        data["protocol"] = next(iter(protocols))
        runs = data["runs"]
        if len(runs) < 2:
            raise InputError(f"--calibrate: scene {scene!r} has {len(runs)} run; a bound needs at least 2 "
                             "(runs with different seeds)")
        data["bounds"], data["left_out"] = {}, {}
        for metric in wanted:
            series = [run["values"].get(metric) for run in runs]
            if all(v is None for v in series) and all(metric not in run["values"] for run in runs):
                continue
            if any(not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) for v in series):
                data["left_out"][metric] = f"null or missing in {sum(v is None for v in series)} of {len(runs)} runs"
                continue
            data["bounds"][metric] = _prediction_bound(series, false_alarm, metric in HIGHER_IS_BETTER,
                                                       f"--calibrate: scene {scene!r} {metric}")
        data["training"] = _training_medians(runs, scene)
    return scenes


MAX_STEPS = 2**63 - 1  # a TOML integer


def _training_medians(runs: list, scene: str):
    """{"steps", "steps_per_second"}: the medians over the runs (None unless every run records
    both), checked finite and in range before they are written."""
    trained = [run["training"] for run in runs if run["training"]]
    steps = [t["steps"] for t in trained if isinstance(t.get("steps"), int) and not isinstance(t["steps"], bool)
             and 0 < t["steps"] <= MAX_STEPS]
    speeds = [t["steps_per_second"] for t in trained if finite_number(t.get("steps_per_second"))
              and t["steps_per_second"] > 0]
    if len(steps) != len(runs) or len(speeds) != len(runs):
        return None
    ordered = sorted(steps)  # the median in integers: exact however large (a float mean of two would round)
    middle = len(ordered) // 2
    medians = {"steps": ordered[middle] if len(ordered) % 2 else (ordered[middle - 1] + ordered[middle]) // 2,
               "steps_per_second": statistics.median(speeds)}
    if not math.isfinite(medians["steps_per_second"]):  # two speeds near float max: their mean overflows
        raise InputError(f"--calibrate: scene {scene!r}: the runs' median training speed is beyond float range "
                         f"(steps_per_second up to {max(speeds):.3g}); check the runs' training records")
    return medians


def toml_float(value: float) -> str:
    """A finite float as TOML that reads back finite: 10 significant digits, or every digit
    when those would round past float max (1.7976931348623157e308 -> 1.797693135e+308 = inf)."""
    if not math.isfinite(value):
        raise InputError(f"refusing to write {value!r} as a bound")
    text = f"{value:.10g}"
    return text if math.isfinite(float(text)) else repr(value)


def _toml_key(scene: str) -> str:
    return scene if re.fullmatch(r"[A-Za-z0-9_-]+", scene) else '"' + scene.replace("\\", "\\\\").replace('"', '\\"') + '"'


def proposal_toml(scenes: dict, false_alarm: float) -> str:
    """The thresholds file (format: eval.check), the data as comments."""
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    lines = [f"# nerfgauge-kind: {THRESHOLDS_KIND}",
             f"# Proposed by `nerfgauge check --calibrate` at {now}, false-alarm rate {false_alarm:g} per bound.",
             "# Each bound is the one-sided normal prediction bound for one new run (eval/calibrate.py):",
             "#   min = mean - t_{1-A,K-1} * s * sqrt(1 + 1/K)   (higher is better; max: mean + ..., lower is better)",
             "# over the K runs below (s: sample std, ddof 1). Exact if the runs are normal and independent;",
             "# a heavier lower tail makes the real rate higher. With m bounds, at most m * A per gate.", ""]
    protocols = {data["protocol"] for data in scenes.values()}
    if protocols:  # one (calibrate refused mixed runs): what check compares every metrics file with
        lines += ["# The protocol every run was scored under: check refuses metrics scored under another.",
                  next(iter(protocols)).to_toml()]
    for scene, data in scenes.items():
        runs, bounds = data["runs"], data["bounds"]
        metrics = list(bounds)
        lines.append(f"# data: {len(runs)} runs of scene {scene}")
        header = ["run", "seed", *metrics, "steps", "steps/s", "source"]
        table = [header]
        for index, run in enumerate(runs, 1):
            training = run["training"] or {}
            table.append([str(index), "?" if run["seed"] is None else str(run["seed"]),
                          *[f"{run['values'][m]:.6g}" for m in metrics],
                          str(training.get("steps", "?")),
                          f"{training['steps_per_second']:.4g}" if isinstance(training.get("steps_per_second"),
                                                                             (int, float)) else "?",
                          run["source"]])
        widths = [max(len(row[i]) for row in table) for i in range(len(header))]
        lines += ["#   " + "  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in table]
        for metric, why in data["left_out"].items():
            lines.append(f"# {metric}: not proposed, {why}")
        lines.append(f"[{_toml_key(scene)}]")
        for metric, bound in bounds.items():
            lines.append(f"{metric} = {{ {bound['kind']} = {toml_float(bound['bound'])} }}  "
                         f"# mean {bound['mean']:.6g}, s {bound['std']:.3g}, K {bound['k']}")
        if data["training"]:
            lines.append(f"training = {{ steps = {data['training']['steps']}, "
                         f"steps_per_second = {data['training']['steps_per_second']:.6g} }}  "
                         "# medians of the runs: check says 'under-trained' below half the steps")
        lines.append("")
    return "\n".join(lines)
