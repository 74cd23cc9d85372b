"""eval.uncertainty against independent implementations: a plain-loop bootstrap on the same
resample indices (same generator, same draw order), scipy's Wilcoxon, coverage of the
interval on normal data, and the variance split on data with known components."""

import math

import numpy as np
import pytest
from scipy.stats import wilcoxon

from nerfgauge.core.errors import InputError
from nerfgauge.eval.uncertainty import (RESAMPLES, bootstrap_ci, paired_comparison, variance_split, wilcoxon_p)


def percentile_linear(values, q):
    """numpy's default ('linear') percentile, written out: position q/100 * (n-1) in the
    sorted values, linear between the two order statistics around it."""
    s = sorted(values)
    position = q / 100.0 * (len(s) - 1)
    lo = math.floor(position)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (position - lo) * (s[hi] - s[lo])


def loop_bootstrap(rows, seed, resamples=RESAMPLES):
    """The two-level bootstrap by plain loops: rows is [n_seeds][n_views] with None for
    undefined cells (already without all-undefined seeds/views). Indices drawn as the module
    documents: seeds (resamples x n_seeds) first, then views (resamples x n_views)."""
    rng = np.random.default_rng(seed)
    n_seeds, n_views = len(rows), len(rows[0])
    seed_index = rng.integers(0, n_seeds, size=(resamples, n_seeds))
    view_index = rng.integers(0, n_views, size=(resamples, n_views))
    means = []
    for b in range(resamples):
        total, count = 0.0, 0
        for s in seed_index[b]:
            for v in view_index[b]:
                value = rows[s][v]
                if value is not None:
                    total += value
                    count += 1
        if count:
            means.append(total / count)
    return percentile_linear(means, 2.5), percentile_linear(means, 97.5)


def test_one_seed_matches_the_loop_bootstrap_to_1e_9():
    values = list(np.random.default_rng(5).normal(30.0, 2.0, size=12))
    interval = bootstrap_ci(values, np.random.default_rng(42), resamples=2000)
    low, high = loop_bootstrap([values], 42, resamples=2000)
    assert abs(interval.low - low) < 1e-9 and abs(interval.high - high) < 1e-9
    assert interval.mean == pytest.approx(np.mean(values), abs=1e-12)
    assert interval.n_seeds == 1 and interval.n_views == 12 and not interval.degenerate
    assert interval.low < interval.mean < interval.high


def test_seeds_and_views_with_undefined_cells_match_the_loop_bootstrap_to_1e_9():
    rng = np.random.default_rng(6)
    rows = (30.0 + rng.normal(0, 1.0, size=(3, 1)) + rng.normal(0, 2.0, size=(1, 9))
            + rng.normal(0, 0.3, size=(3, 9))).tolist()
    rows[1][4] = None  # undefined in one seed only: left out of the means that draw it
    rows[0][2] = float("nan")
    interval = bootstrap_ci(rows, np.random.default_rng(7), resamples=1500)
    loop_rows = [[None if (v is None or math.isnan(v)) else v for v in row] for row in rows]
    low, high = loop_bootstrap(loop_rows, 7, resamples=1500)
    assert abs(interval.low - low) < 1e-9 and abs(interval.high - high) < 1e-9
    defined = [v for row in loop_rows for v in row if v is not None]
    assert interval.mean == pytest.approx(sum(defined) / len(defined), abs=1e-12)
    assert interval.n_seeds == 3 and interval.n_views == 9


def test_undefined_views_are_left_out_as_summarize_does():
    values = [31.0, None, 29.5, float("nan"), 33.0, 30.0]
    with_gaps = bootstrap_ci(values, np.random.default_rng(1), resamples=500)
    without = bootstrap_ci([31.0, 29.5, 33.0, 30.0], np.random.default_rng(1), resamples=500)
    assert (with_gaps.mean, with_gaps.low, with_gaps.high) == (without.mean, without.low, without.high)
    assert with_gaps.n_views == 4


def test_one_view_is_degenerate_and_nothing_defined_is_none():
    one = bootstrap_ci([31.0, None], np.random.default_rng(0))
    assert one.degenerate and one.low == one.high == one.mean == 31.0 and one.to_json() == [31.0, 31.0]
    none = bootstrap_ci([None, None], np.random.default_rng(0))
    assert none.mean is None and none.to_json() is None


def test_bad_values_raise_input_error():
    with pytest.raises(InputError):
        bootstrap_ci([1.0, float("inf")], np.random.default_rng(0))
    with pytest.raises(InputError):
        bootstrap_ci([[1.0, 2.0], [1.0]], np.random.default_rng(0))
    with pytest.raises(InputError):
        bootstrap_ci(["a", 2.0], np.random.default_rng(0))


def test_coverage_on_normal_data_is_about_95_percent():
    """400 samples of 20 views from N(30, 2): the interval covers 30 in 0.95 +- 3 binomial
    standard errors of the repetitions (the percentile bootstrap is a little narrow at n=20:
    its coverage there is ~0.93, inside the band)."""
    rng = np.random.default_rng(123)
    repetitions, covered = 400, 0
    for _ in range(repetitions):
        sample = rng.normal(30.0, 2.0, size=20)
        interval = bootstrap_ci(sample, rng, resamples=1000)
        covered += interval.low <= 30.0 <= interval.high
    band = 3 * math.sqrt(0.95 * 0.05 / repetitions)
    assert abs(covered / repetitions - 0.95) <= band, covered


def test_variance_split_recovers_known_seed_and_view_variances():
    rng = np.random.default_rng(9)
    seeds, views = 60, 80
    var_seed, var_view, var_res = 4.0, 1.0, 0.25
    y = (30.0 + rng.normal(0, math.sqrt(var_seed), size=(seeds, 1)) + rng.normal(0, math.sqrt(var_view), size=(1, views))
         + rng.normal(0, math.sqrt(var_res), size=(seeds, views)))
    split = variance_split(y.tolist())
    # standard errors of the estimates ~ var * sqrt(2/(n-1)): 0.74 for seeds (60), 0.16 for views (80)
    assert split["var_seed"] == pytest.approx(var_seed, abs=3 * 0.74)
    assert split["var_view"] == pytest.approx(var_view, abs=3 * 0.16)
    assert split["var_residual"] == pytest.approx(var_res, rel=0.05)
    assert split["n_seeds"] == seeds and split["n_views"] == views
    assert split["seed_share"] == pytest.approx(split["var_seed"] / (split["var_seed"] + split["var_view"]
                                                                     + split["var_residual"]))


def test_variance_split_by_hand_and_small_cases():
    y = [[1.0, 2.0, 6.0], [3.0, 4.0, 5.0]]
    # grand 3.5; seed means 3, 4; view means 2, 3, 5.5
    ms_seed = 3 * ((3 - 3.5) ** 2 + (4 - 3.5) ** 2) / 1
    ms_view = 2 * ((2 - 3.5) ** 2 + (3 - 3.5) ** 2 + (5.5 - 3.5) ** 2) / 2
    res = [[1 - 3 - 2 + 3.5, 2 - 3 - 3 + 3.5, 6 - 3 - 5.5 + 3.5], [3 - 4 - 2 + 3.5, 4 - 4 - 3 + 3.5, 5 - 4 - 5.5 + 3.5]]
    ms_res = sum(r * r for row in res for r in row) / 2
    split = variance_split(y)
    assert split["var_residual"] == pytest.approx(ms_res)
    assert split["var_seed"] == pytest.approx(max(0.0, (ms_seed - ms_res) / 3))
    assert split["var_view"] == pytest.approx(max(0.0, (ms_view - ms_res) / 2))
    one_seed = variance_split([1.0, 2.0, None, 4.0])
    assert one_seed["var_seed"] is None and one_seed["var_view"] == pytest.approx(np.var([1, 2, 4], ddof=1))
    assert variance_split([5.0])["var_view"] is None


def test_wilcoxon_matches_scipy_exact_and_normal_approximation():
    rng = np.random.default_rng(3)
    small = rng.standard_t(2, size=12) + 0.5  # heavy-tailed, exact for n <= 50
    large = rng.standard_t(2, size=80) + 0.3  # normal approximation
    for d in (small, large):
        assert wilcoxon_p(d.tolist()) == pytest.approx(wilcoxon(d).pvalue, rel=1e-12)
    assert wilcoxon_p([0.0, 0.0]) == 1.0 and wilcoxon_p([None]) is None


def test_paired_comparison_resamples_views_once_for_both_methods():
    rng = np.random.default_rng(11)
    base = rng.normal(30.0, 3.0, size=16)  # views differ a lot; the gain is steady
    a, b = (base + 0.4 + rng.normal(0, 0.1, size=16)).tolist(), base.tolist()
    result = paired_comparison(a, b, np.random.default_rng(2), resamples=2000)
    d = [x - y for x, y in zip(a, b)]
    low, high = loop_bootstrap([d], 2, resamples=2000)
    assert abs(result["ci95"][0] - low) < 1e-9 and abs(result["ci95"][1] - high) < 1e-9
    assert result["mean_difference"] == pytest.approx(np.mean(d))
    assert result["p_value"] == pytest.approx(wilcoxon(d).pvalue) and result["significant"] is True
    # unpaired intervals would overlap (view spread 3 dB); the paired one excludes 0
    assert 0 < result["ci95"][0]
    same = paired_comparison(b, b, np.random.default_rng(2), resamples=200)
    assert same["mean_difference"] == 0.0 and same["p_value"] == 1.0 and same["significant"] is False


def test_paired_comparison_with_seeds_tests_per_view_means():
    rng = np.random.default_rng(4)
    a = rng.normal(30, 1, size=(3, 10))
    b = a - 0.2 + rng.normal(0, 0.5, size=(3, 10))
    result = paired_comparison(a.tolist(), b.tolist(), np.random.default_rng(0), resamples=300)
    assert result["p_value"] == pytest.approx(wilcoxon((a - b).mean(axis=0)).pvalue)
    assert result["n_seeds"] == 3 and result["n_views"] == 10
    with pytest.raises(InputError):
        paired_comparison(a.tolist(), b[:, :9].tolist(), np.random.default_rng(0))
