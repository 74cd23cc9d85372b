"""Uncertainty of a mean score: bootstrap confidence intervals over views and seeds, the
split of variance between seeds and views, and paired comparisons of two methods. Pure
numpy (and scipy.stats.wilcoxon for the paired test).

Conventions (docs/conventions.md, "Uncertainty"), stated once here:

- Values are a matrix [n_seeds, n_views]: one row per training seed, one column per test
  view, the same views for every seed (a dataset's test split). One seed is [1, n_views];
  a 1-D list [n_views] is read as one seed. Undefined values (None or NaN, e.g. depth of a
  view that hits nothing) are left out, as `eval.metrics.summarize` does: the mean is over
  the defined cells. inf raises InputError.
- The statistic is the mean of the defined cells (for one seed: exactly summarize's mean).
- Two-level bootstrap, `RESAMPLES` = 10000 resamples from a numpy Generator the caller
  passes in (no global seeding). Draw order, exactly (the tests redraw the same indices):
      seed_index = rng.integers(0, n_seeds, size=(resamples, n_seeds))   # first call
      view_index = rng.integers(0, n_views, size=(resamples, n_views))   # second call
  Resample b takes the rows seed_index[b] (seeds with replacement) and, within them, the
  columns view_index[b] (views with replacement), the SAME view resample for every seed:
  the views are shared by the seeds (every seed is scored on the same test views), so a
  view that is hard for one seed is hard for all; resampling views independently per seed
  would break that correlation and make the interval too narrow. The seed draw is made
  (all zeros) even for one seed, so the stream does not depend on n_seeds being 1.
  Views undefined in every seed and seeds undefined in every view are dropped first (for
  one seed: the undefined views, as summarize does); n_views and n_seeds count what is left.
- The interval is the percentile interval: the 2.5th and 97.5th percentiles of the
  resampled means, numpy's default (linear) interpolation between order statistics.
  With one defined view and one seed every resample equals the mean: the interval is
  degenerate, [mean, mean], and says nothing about the spread (`degenerate` is True).
  A resample that holds no defined cell (possible only when cells are undefined in some
  seeds but not others) has no mean and is left out of the percentiles.
- Paired comparisons (method A minus method B on the same views and seeds): the
  differences d = A - B per (seed, view) cell, defined where both are; the same bootstrap
  on d (resampling the views once and taking both methods' values at them). The test is
  the Wilcoxon signed-rank test, two-sided, at `LEVEL_ALPHA` = 0.05, on the per-view
  differences averaged over seeds (the view is the independent unit: a seed's runs share
  the views). Why Wilcoxon, not the paired t-test: per-view PSNR differences are not
  normal and are heavy-tailed (a few views with a floater or a missed thin part differ by
  several dB), and the t-test's p-value rests on normality at the small view counts
  (8-50) of a test split; the signed-rank test needs only a distribution symmetric about
  its median under the null.
- Finite in, finite out: every mean, interval end, spread and variance returned is checked
  finite (`finite_result`); values so large that a sum leaves float range (two views at
  1e308) raise InputError naming what overflowed, never an inf that a JSON writer then
  refuses with a traceback. `mean_of` is the mean of a list of numbers under the same rule.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from nerfgauge.core.errors import InputError

RESAMPLES = 10_000
LEVEL = 0.95  # the confidence level of every interval
LEVEL_ALPHA = 0.05  # the significance level of the paired test
# `nerfgauge evaluate`'s ci95: np.random.default_rng(EVALUATE_SEED), a fresh Generator per
# metric, so a metric's interval does not depend on which other metrics were scored.
EVALUATE_SEED = 0


def finite_result(values: dict, what: str) -> dict:
    """`values` ({name: number, None or a list of them}) when every number is finite;
    InputError naming `what` and the first that is not (finite inputs whose sums overflow)."""
    for name, value in values.items():
        for item in value if isinstance(value, (list, tuple)) else [value]:
            if item is not None and not math.isfinite(item):
                raise InputError(f"{what}: the {name} is beyond float range ({item}); the values it comes from are "
                                 "too large to average")
    return values


def mean_of(values, what: str) -> float:
    """The mean of finite numbers (math.fsum / n), InputError when it leaves float range."""
    try:
        return finite_result({"mean": math.fsum(values) / len(values)}, what)["mean"]
    except OverflowError:  # fsum raises on an intermediate overflow
        raise InputError(f"{what}: the mean is beyond float range; the values are too large to average") from None


def as_matrix(values) -> np.ndarray:
    """[n_seeds, n_views] float64 with NaN for undefined cells (None or NaN), from a list of
    numbers/None ([n_views], one seed) or a list of such lists ([n_seeds, n_views]).
    Raises InputError for ragged rows, non-numbers or inf."""
    rows = values if len(values) and isinstance(values[0], (list, tuple, np.ndarray)) else [values]
    if len({len(row) for row in rows}) > 1:
        raise InputError(f"uncertainty needs every seed scored on the same views, got rows of lengths "
                         f"{sorted({len(row) for row in rows})}")
    try:
        matrix = np.array([[np.nan if v is None else v for v in row] for row in rows], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"uncertainty needs numbers or None, got {list(rows[0])[:3]!r}...") from None
    if np.isinf(matrix).any():
        raise InputError(f"uncertainty: {int(np.isinf(matrix).sum())} infinite values")
    return matrix.reshape(len(rows), -1)


def defined_matrix(values) -> np.ndarray:
    """as_matrix without the views undefined in every seed and the seeds undefined in every
    view: [n_seeds', n_views'] (possibly empty)."""
    matrix = as_matrix(values)
    defined = ~np.isnan(matrix)
    return matrix[defined.any(axis=1)][:, defined.any(axis=0)]


@dataclass(frozen=True)
class Interval:
    """A bootstrap interval of a mean. low/high None when no value is defined."""

    mean: Optional[float]
    low: Optional[float]
    high: Optional[float]
    n_seeds: int
    n_views: int
    resamples: int
    degenerate: bool  # one seed and one view: [mean, mean], no information on the spread

    def to_json(self) -> Optional[list]:
        return None if self.low is None else [self.low, self.high]


def draw_indices(rng: np.random.Generator, n_seeds: int, n_views: int, resamples: int = RESAMPLES):
    """(seed_index [resamples, n_seeds], view_index [resamples, n_views]) in the documented
    order: the seed draw first, then the view draw."""
    seed_index = rng.integers(0, n_seeds, size=(resamples, n_seeds))
    view_index = rng.integers(0, n_views, size=(resamples, n_views))
    return seed_index, view_index


def _counts(index: np.ndarray, n: int) -> np.ndarray:
    """[resamples, n] how often each row/column is drawn in each resample."""
    resamples = index.shape[0]
    offsets = index + (np.arange(resamples)[:, None] * n)
    return np.bincount(offsets.ravel(), minlength=resamples * n).reshape(resamples, n).astype(np.float64)


def resampled_means(matrix: np.ndarray, seed_index: np.ndarray, view_index: np.ndarray) -> np.ndarray:
    """[resamples] the mean of the defined cells of each resample (NaN when none is):
    sum_ij cs_i cv_j M_ij / sum_ij cs_i cv_j D_ij, with cs, cv the draw counts of seed i and
    view j and D the defined mask, which is the mean over the resampled cells."""
    n_seeds, n_views = matrix.shape
    defined = ~np.isnan(matrix)
    filled = np.where(defined, matrix, 0.0)
    cs, cv = _counts(seed_index, n_seeds), _counts(view_index, n_views)
    with np.errstate(over="ignore", invalid="ignore"):  # overflowed sums give inf: callers refuse it (finite_result)
        numerator = ((cs @ filled) * cv).sum(axis=1)  # [resamples]
    denominator = ((cs @ defined.astype(np.float64)) * cv).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        return np.where(denominator > 0, numerator / np.where(denominator > 0, denominator, 1.0), np.nan)


def bootstrap_ci(values, rng: np.random.Generator, resamples: int = RESAMPLES, level: float = LEVEL) -> Interval:
    """The percentile bootstrap interval of the mean of `values` ([n_seeds, n_views] or
    [n_views], None/NaN undefined), resampling seeds then views as the module docstring
    states, with indices from `draw_indices(rng, n_seeds, n_views, resamples)` on the
    matrix left after dropping all-undefined seeds and views. No draw is made when nothing
    is defined (all None: mean, low, high None)."""
    if not 0 < level < 1 or resamples < 1:
        raise InputError(f"bootstrap_ci needs 0 < level < 1 and resamples >= 1, got {level}, {resamples}")
    matrix = defined_matrix(values)
    n_seeds, n_views = matrix.shape if matrix.size else (0, 0)
    if matrix.size == 0:
        return Interval(None, None, None, 0, 0, resamples, True)
    with np.errstate(over="ignore", invalid="ignore"):
        mean = float(np.nanmean(matrix))
    seed_index, view_index = draw_indices(rng, n_seeds, n_views, resamples)
    means = resampled_means(matrix, seed_index, view_index)
    tail = 100.0 * (1.0 - level) / 2.0
    with np.errstate(over="ignore", invalid="ignore"):  # an overflow is refused just below, by name
        low, high = np.nanpercentile(means, [tail, 100.0 - tail])
    finite_result({"mean": mean, "interval": [float(low), float(high)]}, "bootstrap interval")
    degenerate = n_seeds == 1 and n_views == 1
    return Interval(mean, float(low), float(high), n_seeds, n_views, resamples, degenerate)


def variance_split(values) -> dict:
    """The split of the variance of a score between seeds and views: a two-way crossed
    random-effects ANOVA (seed x view, one value per cell), y_sv = mu + a_s + b_v + e_sv,
    with S seeds and V views (the views are shared, so the design is crossed, not nested):

        MS_seed = V * sum_s (m_s. - m..)^2 / (S - 1)
        MS_view = S * sum_v (m_.v - m..)^2 / (V - 1)
        MS_res  = sum_sv (y_sv - m_s. - m_.v + m..)^2 / ((S - 1)(V - 1))
        var_seed = max(0, (MS_seed - MS_res) / V)      (run-to-run spread of a view's score)
        var_view = max(0, (MS_view - MS_res) / S)      (how much views differ in difficulty)
        var_residual = MS_res                          (seed x view interaction plus noise)

    (the method-of-moments estimators, E[MS_seed] = var_res + V var_seed etc.; negative
    estimates are set to 0). Only the views defined in every seed are used. With one seed,
    var_seed and var_residual are None (not estimable) and var_view is the sample variance
    over views (ddof=1); with one view, var_view and var_residual are None and var_seed is
    the sample variance over seeds; with fewer cells, all are None.
    Returns {"var_seed", "var_view", "var_residual", "seed_share", "n_seeds", "n_views"};
    seed_share = var_seed / (var_seed + var_view + var_residual) where all are defined and
    the sum is positive, else None.
    """
    matrix = defined_matrix(values)
    if matrix.size:
        matrix = matrix[:, ~np.isnan(matrix).any(axis=0)]
    n_seeds, n_views = matrix.shape if matrix.size else (0, 0)
    out = {"var_seed": None, "var_view": None, "var_residual": None, "seed_share": None,
           "n_seeds": n_seeds, "n_views": n_views}
    with np.errstate(over="ignore", invalid="ignore"):  # an overflow is refused by name below
        if n_seeds >= 2 and n_views >= 2:
            grand = matrix.mean()
            seed_means, view_means = matrix.mean(axis=1), matrix.mean(axis=0)
            ms_seed = n_views * float(((seed_means - grand) ** 2).sum()) / (n_seeds - 1)
            ms_view = n_seeds * float(((view_means - grand) ** 2).sum()) / (n_views - 1)
            residual = matrix - seed_means[:, None] - view_means[None, :] + grand
            ms_res = float((residual ** 2).sum()) / ((n_seeds - 1) * (n_views - 1))
            out.update(var_seed=max(0.0, (ms_seed - ms_res) / n_views), var_view=max(0.0, (ms_view - ms_res) / n_seeds),
                       var_residual=ms_res)
            total = out["var_seed"] + out["var_view"] + ms_res
            out["seed_share"] = out["var_seed"] / total if total > 0 else None
        elif n_seeds == 1 and n_views >= 2:
            out["var_view"] = float(matrix[0].var(ddof=1))
        elif n_views == 1 and n_seeds >= 2:
            out["var_seed"] = float(matrix[:, 0].var(ddof=1))
    return finite_result(out, "variance split")


def wilcoxon_p(differences) -> Optional[float]:
    """Two-sided p-value of the Wilcoxon signed-rank test that the differences are
    symmetric about 0, by scipy.stats.wilcoxon(zero_method="wilcox", method="auto"): zero
    differences are dropped; with the n non-zero differences ranked by |d| (ties get their
    mean rank), W+ = sum of the ranks of the positive ones; exact null distribution of W+
    (all 2^n sign flips) for n <= 50 without ties, else the normal approximation
    z = (W+ - n(n+1)/4) / sqrt(n(n+1)(2n+1)/24 - tie correction). All differences zero
    (identical scores): p = 1.0. No difference: None."""
    d = np.asarray([v for v in differences if v is not None and not math.isnan(v)], dtype=np.float64)
    if d.size == 0:
        return None
    if not np.any(d != 0):
        return 1.0
    from scipy.stats import wilcoxon  # scipy is a dependency of scikit-image, which metrics needs

    return float(wilcoxon(d, zero_method="wilcox", alternative="two-sided", method="auto").pvalue)


def paired_comparison(a, b, rng: np.random.Generator, resamples: int = RESAMPLES, level: float = LEVEL,
                      alpha: float = LEVEL_ALPHA) -> dict:
    """Method A against method B on the same views (and seeds): a and b are [n_seeds,
    n_views] (or [n_views]) in the same order. d = a - b per cell, defined where both are.

    Returns {"mean_difference": mean of the defined d, "ci95": [low, high] from
    bootstrap_ci(d, rng) (so the resample is paired: the same seeds and views for both
    methods), "p_value": wilcoxon_p of the per-view differences averaged over seeds
    (views defined in some seed), "significant": p_value < alpha (None when p is None),
    "alpha", "n_seeds", "n_views", "degenerate"}."""
    ma, mb = as_matrix(a), as_matrix(b)
    if ma.shape != mb.shape:
        raise InputError(f"paired comparison needs the same seeds and views, got shapes {ma.shape} and {mb.shape}")
    with np.errstate(over="ignore", invalid="ignore"):  # an overflow to inf is refused by as_matrix below
        d = ma - mb  # NaN where either is undefined
    interval = bootstrap_ci(d, rng, resamples, level)
    matrix = defined_matrix(d)
    per_view = np.nanmean(matrix, axis=0) if matrix.size else np.zeros(0)
    p = wilcoxon_p(per_view.tolist())
    return {"mean_difference": interval.mean, "ci95": interval.to_json(), "p_value": p,
            "significant": None if p is None else bool(p < alpha), "alpha": alpha,
            "n_seeds": interval.n_seeds, "n_views": interval.n_views, "degenerate": interval.degenerate}


# --- several training runs of one method on one dataset ----------------------------------

AGGREGATE_SCHEMA = 1


def run_matrix(documents: list, metric: str, names=None):
    """([n_runs, n_views] per-frame values of `metric`, None where undefined; frame names)
    from metrics.json documents (one per training seed, same dataset and split), frames
    matched by name in the order of the first document (or `names`). A frame that a run
    lacks is undefined in that run."""
    if names is None:
        names = [frame["name"] for frame in documents[0]["frames"]]
    rows = []
    for document in documents:
        by_name = {frame["name"]: frame.get(metric) for frame in document["frames"]}
        rows.append([by_name.get(name) for name in names])
    return rows, names


def aggregate_runs(documents: list, seeds: list, metrics, bootstrap_seed: int = EVALUATE_SEED) -> dict:
    """One method's runs on one dataset, one metrics.json document per training seed (same
    order as `seeds`): every run's means, and per metric the mean over all (seed, view)
    cells, the two-level bootstrap interval (`bootstrap_ci`, a fresh
    np.random.default_rng(bootstrap_seed) per metric, so the interval of one metric does not
    depend on the others), each seed's mean, their spread, and the variance split.

    Returns {"schema", "seeds", "runs": [{"seed", "mean"}], "mean": {metric: value},
    "ci95": {metric: [low, high] | None}, "per_seed": {metric: [mean of each seed]},
    "seed_std": {metric: sample std (ddof=1) of the per-seed means, None for one seed},
    "seed_range": {metric: [min, max] of the per-seed means}, "variance": {metric:
    variance_split}, "n_views", "resamples", "bootstrap_seed"}."""
    if len(documents) != len(seeds) or not documents:
        raise InputError(f"aggregate_runs needs one metrics document per seed, got {len(documents)} for {len(seeds)}")
    if len(set(seeds)) != len(seeds):
        raise InputError(f"aggregate_runs: seeds repeat: {list(seeds)}")
    out = {"schema": AGGREGATE_SCHEMA, "seeds": list(seeds),
           "runs": [{"seed": seed, "mean": document.get("mean", {})} for seed, document in zip(seeds, documents)],
           "mean": {}, "ci95": {}, "per_seed": {}, "seed_std": {}, "seed_range": {}, "variance": {},
           "n_views": len(documents[0]["frames"]), "resamples": RESAMPLES, "level": LEVEL,
           "bootstrap_seed": bootstrap_seed,
           "resampling": "two-level bootstrap: seeds with replacement, then views with replacement (the same view "
                         "resample for every seed); percentile interval (docs/conventions.md, Uncertainty)"}
    for metric in metrics:
        rows, _ = run_matrix(documents, metric)
        if all(value is None for row in rows for value in row):
            continue
        interval = bootstrap_ci(rows, np.random.default_rng(bootstrap_seed))
        matrix = as_matrix(rows)
        with np.errstate(over="ignore", invalid="ignore"):  # refused by name below
            per_seed = [None if np.isnan(row).all() else float(np.nanmean(row)) for row in matrix]
            defined = [value for value in per_seed if value is not None]
            seed_std = float(np.std(defined, ddof=1)) if len(defined) >= 2 else None
        out["mean"][metric] = interval.mean
        out["ci95"][metric] = interval.to_json()
        out["per_seed"][metric] = per_seed
        out["seed_std"][metric] = seed_std
        out["seed_range"][metric] = [min(defined), max(defined)] if defined else None
        out["variance"][metric] = variance_split(rows)
        finite_result({"per-seed mean": per_seed, "seed std": out["seed_std"][metric]}, f"aggregate of {metric}")
    return out



def suite_interval(tables: list, rng: np.random.Generator, resamples: int = RESAMPLES, level: float = LEVEL) -> Interval:
    """The interval of a suite's mean score, the mean over datasets of each dataset's mean.
    tables: one [n_seeds, n_views] matrix (or [n_views] list) per dataset. The datasets are
    the suite's fixed set (not resampled); within each, in the given order, seeds then views
    are resampled by `draw_indices(rng, ...)` on its defined matrix, independently of the
    other datasets (another dataset's seed k is another training run). Resample b's suite
    mean is the mean over the datasets of their resample-b means; the interval is the
    percentile interval of those. Datasets with nothing defined are left out (as the
    leaderboard's mean leaves them out); n_seeds and n_views are the largest counts."""
    matrices = [m for m in (defined_matrix(t) for t in tables) if m.size]
    if not matrices:
        return Interval(None, None, None, 0, 0, resamples, True)
    means = np.zeros(resamples)
    for matrix in matrices:
        seed_index, view_index = draw_indices(rng, matrix.shape[0], matrix.shape[1], resamples)
        with np.errstate(over="ignore", invalid="ignore"):
            means += resampled_means(matrix, seed_index, view_index)
    with np.errstate(over="ignore", invalid="ignore"):
        means /= len(matrices)
        tail = 100.0 * (1.0 - level) / 2.0
        low, high = np.nanpercentile(means, [tail, 100.0 - tail])
        mean = float(np.mean([np.nanmean(m) for m in matrices]))
    finite_result({"mean": mean, "interval": [float(low), float(high)]}, "suite interval")
    degenerate = all(m.shape == (1, 1) for m in matrices)
    return Interval(mean, float(low), float(high), max(m.shape[0] for m in matrices),
                    max(m.shape[1] for m in matrices), resamples, degenerate)
