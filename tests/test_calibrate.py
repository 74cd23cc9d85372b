"""`nerfgauge check --calibrate` (eval/calibrate.py) and the under-trained verdict of
`check` (eval/check.py): the proposed floor's false-alarm rate on data drawn from a known
normal distribution, the written TOML against an independent computation, file ownership,
bad flag values, and exit 4 for a failed run that got under half the calibrated steps."""

from __future__ import annotations

import json
import math
import tomllib

import numpy as np
import pytest
from scipy.stats import norm, t

from nerfgauge.cli import main
from nerfgauge.eval.calibrate import proposed_bound


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def metrics_file(path, psnr, ssim=0.95, depth_absrel=0.01, steps=400, speed=10.0, seed=None, budget=None):
    path.parent.mkdir(parents=True, exist_ok=True)
    training = {"steps": steps, "seconds": steps / speed, "steps_per_second": speed, "budget_seconds": budget}
    if seed is not None:
        training["seed"] = seed
    path.write_text(json.dumps({"schema": 1, "scene": "primitives", "split": "test",
                                "mean": {"psnr": psnr, "ssim": ssim, "depth_absrel": depth_absrel,
                                         "covisible_fraction": 0.9},
                                "training": training}))
    return path


@pytest.mark.parametrize("false_alarm, higher", [(0.05, True), (0.01, True), (0.1, False)])
def test_the_bound_has_the_stated_false_alarm_rate_on_normal_data(false_alarm, higher):
    """K = 10 runs from N(mu, sigma): the chance that a new run from the same distribution
    falls beyond the proposed bound, P = Phi((floor - mu) / sigma) for a floor (1 - Phi for a
    ceiling), averaged over 4000 calibration sets, is the stated rate (the prediction bound
    is exact under normality). Tolerance: 5 standard errors of that average."""
    rng = np.random.default_rng(2026)
    mu, sigma, k, sets = 31.0, 0.4, 10, 4000
    rates = []
    for _ in range(sets):
        values = rng.normal(mu, sigma, size=k).tolist()
        bound = proposed_bound(values, false_alarm, higher)
        rates.append(norm.cdf((bound - mu) / sigma) if higher else norm.sf((bound - mu) / sigma))
    rates = np.asarray(rates)
    standard_error = rates.std(ddof=1) / math.sqrt(sets)
    assert abs(rates.mean() - false_alarm) < 5 * standard_error + 1e-4, (rates.mean(), standard_error)
    # and by counting: one new run per set, beyond the bound about false_alarm of the time
    draws = rng.normal(mu, sigma, size=(sets, k + 1))
    beyond = [(d[-1] < proposed_bound(d[:-1].tolist(), false_alarm, True)) for d in draws]
    expected_sd = math.sqrt(false_alarm * (1 - false_alarm) / sets)
    if higher:
        assert abs(np.mean(beyond) - false_alarm) < 4 * expected_sd


def test_calibrate_writes_thresholds_check_reads(tmp_path, capsys):
    rng = np.random.default_rng(7)
    psnr = rng.normal(31.0, 0.3, size=10)
    ssim = rng.normal(0.97, 0.002, size=10)
    absrel = rng.normal(0.012, 0.001, size=10)
    files = [metrics_file(tmp_path / "runs" / f"seed-{s}" / "metrics.json", float(psnr[s]), float(ssim[s]),
                          float(absrel[s]), steps=400, speed=10.0 + s) for s in range(10)]
    out = tmp_path / "proposed.toml"
    code, stdout, err = run(capsys, "check", "--calibrate", tmp_path / "runs", "--false-alarm", "0.05", "--out", out)
    assert code == 0, err
    text = out.read_text()
    assert text.startswith("# nerfgauge-kind: thresholds\n")
    table = tomllib.loads(text)["primitives"]
    quantile = t.ppf(0.95, 9) * math.sqrt(1 + 1 / 10)
    assert table["psnr"]["min"] == pytest.approx(psnr.mean() - quantile * psnr.std(ddof=1), rel=1e-9)
    assert table["ssim"]["min"] == pytest.approx(ssim.mean() - quantile * ssim.std(ddof=1), rel=1e-9)
    assert table["depth_absrel"]["max"] == pytest.approx(absrel.mean() + quantile * absrel.std(ddof=1), rel=1e-9)
    assert "covisible_fraction" not in table  # no direction: a property of the dataset
    assert table["training"] == {"steps": 400, "steps_per_second": pytest.approx(14.5)}
    for s in range(10):  # the data it came from, as comments: seed (from seed-<s>/) and value
        assert any(line.startswith("#") and f"  {s}  " in line and f"{psnr[s]:.6g}" in line
                   for line in text.splitlines())
    # the proposal is a thresholds file: a run at the calibration mean passes it
    at_mean = metrics_file(tmp_path / "new" / "metrics.json", float(psnr.mean()), float(ssim.mean()),
                           float(absrel.mean()))
    code, stdout, err = run(capsys, "check", at_mean, "--thresholds", out)
    assert code == 0, err
    assert "training: 400 steps in 40.0 s, 10 steps/s on this machine (step-counted)" in stdout
    # a rerun replaces its own output; a file nerfgauge did not write is refused
    code, _, err = run(capsys, "check", "--calibrate", *files, "--out", out)
    assert code == 0, err
    mine = tmp_path / "mine.toml"
    mine.write_text("[primitives]\npsnr = { min = 1.0 }\n")
    code, _, err = run(capsys, "check", "--calibrate", *files, "--out", mine)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "did not write" in err, err
    assert mine.read_text() == "[primitives]\npsnr = { min = 1.0 }\n"


@pytest.mark.parametrize("value", ["0", "1", "-0.1", "1.5", "nan", "x"])
def test_bad_false_alarm_is_one_line_exit_2(value, tmp_path, capsys):
    files = [metrics_file(tmp_path / f"{s}" / "metrics.json", 30.0 + s) for s in range(3)]
    code, _, err = run(capsys, "check", "--calibrate", *files, f"--false-alarm={value}", "--out", tmp_path / "p.toml")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--false-alarm" in err, err
    assert not (tmp_path / "p.toml").exists()


def test_one_run_or_missing_out_is_one_line_exit_2(tmp_path, capsys):
    one = metrics_file(tmp_path / "a" / "metrics.json", 30.0)
    code, _, err = run(capsys, "check", "--calibrate", one, "--out", tmp_path / "p.toml")
    assert code == 2 and "at least 2" in err and len(err.strip().splitlines()) == 1, err
    code, _, err = run(capsys, "check", "--calibrate", one)
    assert code == 2 and "--out" in err, err
    code, _, err = run(capsys, "check", one)
    assert code == 2 and "--thresholds" in err, err


def test_an_under_trained_failure_says_so_and_exits_4(tmp_path, capsys):
    thresholds = tmp_path / "t.toml"
    thresholds.write_text("[primitives]\npsnr = { min = 30.0 }\ntraining = { steps = 400, steps_per_second = 8.0 }\n")
    slow = metrics_file(tmp_path / "slow" / "metrics.json", 27.0, steps=150, speed=1.67, budget=90.0)
    code, stdout, _ = run(capsys, "check", slow, "--thresholds", thresholds)
    assert code == 4
    assert "under-trained: got 150 steps, calibration had 400 (1.67 steps/s here, 8 in calibration)" in stdout
    assert "time budget 90 s" in stdout
    # enough steps (>= half): a failure is a failure (exit 1), no under-trained line
    short = metrics_file(tmp_path / "short" / "metrics.json", 27.0, steps=200, speed=2.2, budget=90.0)
    code, stdout, _ = run(capsys, "check", short, "--thresholds", thresholds)
    assert code == 1 and "under-trained" not in stdout
    # under-trained but passing: exit 0, the line still printed
    lucky = metrics_file(tmp_path / "lucky" / "metrics.json", 31.0, steps=100, speed=1.1, budget=90.0)
    code, stdout, _ = run(capsys, "check", lucky, "--thresholds", thresholds)
    assert code == 0 and "under-trained: got 100 steps" in stdout
    bad = tmp_path / "bad.toml"
    bad.write_text("[primitives]\npsnr = { min = 30.0 }\ntraining = { steps = 0, steps_per_second = 8.0 }\n")
    code, _, err = run(capsys, "check", slow, "--thresholds", bad)
    assert code == 2 and "training.steps" in err, err
