"""Issue 36: a suite run over training seeds (`suite run --seeds`), its intervals against an
independent bootstrap (plain loops on the same generator draws), the paired comparison by
(seed, view), resuming job by job, and a dask cluster giving the same per-run metrics."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil

import numpy as np
import pytest
from scipy.stats import wilcoxon
from suite_toml import suite_toml
from test_uncertainty import loop_bootstrap, percentile_linear

from nerfgauge.cli import main
from nerfgauge.eval.uncertainty import EVALUATE_SEED, RESAMPLES

TINY = suite_toml("tiny-seeds", {"width": 16, "height": 16, "views": 4, "val_views": 0, "test_views": 4, "spp": 2},
                  {"steps": 60, "threads": 1}, description="two 16x16 datasets, 4 test views")
SEEDS = (0, 1, 2)
IDS = ("primitives", "random-3")


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def read(path):
    return json.loads(path.read_text())


def frame_values(document, metric="psnr"):
    return [frame.get(metric) for frame in document["frames"]]


@pytest.fixture(scope="module")
def seeded(tmp_path_factory):
    """`suite run tiny.toml --seeds 3` (local jobs), and the suite file."""
    root = tmp_path_factory.mktemp("seeds")
    toml = root / "tiny.toml"
    toml.write_text(TINY)
    out = root / "out"
    assert main(["suite", "run", str(toml), "--out", str(out), "--seeds", "3"]) == 0
    return toml, out


def per_seed_documents(out, method, entry_id):
    return [read(out / "results" / method / entry_id / f"seed-{seed}" / "metrics.json") for seed in SEEDS]


@pytest.mark.slow
def test_every_seed_is_kept_and_scored_as_evaluate_scores_it(seeded, tmp_path, capsys):
    toml, out = seeded
    result = read(out / "results" / "compact-nerf" / "result.json")
    assert result["seeds"] == list(SEEDS)
    for entry_id in IDS:
        row = result["datasets"][entry_id]
        assert [run["seed"] for run in row["runs"]] == list(SEEDS)
        for seed, run_row in zip(SEEDS, row["runs"]):
            assert (out / "runs" / "compact-nerf" / f"seed-{seed}" / entry_id / "model.pt").is_file()
            assert run_row["steps"] == 60 and run_row["steps_per_second"] > 0
            single = tmp_path / f"{entry_id}-{seed}.json"
            assert main(["evaluate", str(out / "datasets" / entry_id), "--pred",
                         str(out / "predictions" / "compact-nerf" / f"seed-{seed}" / entry_id),
                         "--out", str(single)]) == 0
            scored = read(out / run_row["metrics"])
            assert read(single)["mean"] == scored["mean"]
            assert scored["training"]["seed"] == seed and scored["training"]["steps"] == 60
        # different seeds train different models: the per-seed scores differ
        psnr = [read(out / run_row["metrics"])["mean"]["psnr"] for run_row in row["runs"]]
        assert len(set(psnr)) == len(SEEDS), psnr


@pytest.mark.slow
def test_calibrate_on_the_seeded_runs(seeded, tmp_path, capsys):
    """check --calibrate on a suite's per-seed metrics: the floor from the three runs' PSNR."""
    from scipy.stats import t

    _, out = seeded
    proposed = tmp_path / "proposed.toml"
    code, _, err = run(capsys, "check", "--calibrate", out / "results" / "compact-nerf" / "primitives",
                       "--metrics", "psnr", "--out", proposed)
    assert code == 0, err
    import tomllib

    table = tomllib.loads(proposed.read_text())["primitives"]
    psnr = np.array([d["mean"]["psnr"] for d in per_seed_documents(out, "compact-nerf", "primitives")])
    floor = psnr.mean() - t.ppf(0.95, 2) * psnr.std(ddof=1) * math.sqrt(1 + 1 / 3)
    assert table["psnr"]["min"] == pytest.approx(floor, rel=1e-9)
    assert table["training"]["steps"] == 60


def test_aggregate_interval_and_split_match_an_independent_computation(seeded):
    _, out = seeded
    for entry_id in IDS:
        aggregate = read(out / "results" / "compact-nerf" / entry_id / "aggregate.json")
        documents = per_seed_documents(out, "compact-nerf", entry_id)
        assert aggregate["seeds"] == list(SEEDS) and aggregate["resamples"] == RESAMPLES
        for metric in ("psnr", "ssim", "depth_absrel"):
            rows = [frame_values(d, metric) for d in documents]
            low, high = loop_bootstrap(rows, EVALUATE_SEED)  # fresh default_rng(0) per metric, seeds then views
            assert abs(aggregate["ci95"][metric][0] - low) < 1e-9 and abs(aggregate["ci95"][metric][1] - high) < 1e-9
            matrix = np.array(rows, dtype=float)
            assert aggregate["mean"][metric] == pytest.approx(matrix.mean(), abs=1e-12)
            per_seed = matrix.mean(axis=1)
            assert aggregate["per_seed"][metric] == pytest.approx(per_seed.tolist(), abs=1e-12)
            assert aggregate["seed_std"][metric] == pytest.approx(float(np.std(per_seed, ddof=1)), abs=1e-12)
            # the variance split by sums of squares (residual by subtraction), not the module's route
            S, V = matrix.shape
            grand = matrix.mean()
            ss_total = ((matrix - grand) ** 2).sum()
            ss_seed = V * ((matrix.mean(axis=1) - grand) ** 2).sum()
            ss_view = S * ((matrix.mean(axis=0) - grand) ** 2).sum()
            ms_res = (ss_total - ss_seed - ss_view) / ((S - 1) * (V - 1))
            split = aggregate["variance"][metric]
            assert split["var_residual"] == pytest.approx(ms_res, rel=1e-9, abs=1e-12)
            assert split["var_seed"] == pytest.approx(max(0.0, (ss_seed / (S - 1) - ms_res) / V), rel=1e-9, abs=1e-12)
            assert split["var_view"] == pytest.approx(max(0.0, (ss_view / (V - 1) - ms_res) / S), rel=1e-9, abs=1e-12)


def test_leaderboard_intervals_and_paired_rows_match_an_independent_bootstrap(seeded):
    _, out = seeded
    board = read(out / "leaderboard.json")
    ours = board["methods"]["compact-nerf"]
    for entry_id in IDS:
        scene = ours["scenes"][entry_id]
        aggregate = read(out / "results" / "compact-nerf" / entry_id / "aggregate.json")
        assert scene["psnr_ci95"] == aggregate["ci95"]["psnr"] and scene["seeds"] == list(SEEDS)
        assert scene["values"]["psnr"] == aggregate["mean"]["psnr"]
    # the suite mean's interval: each dataset's two-level resample in turn from one default_rng(0)
    rng = np.random.default_rng(EVALUATE_SEED)
    suite_means = np.zeros(RESAMPLES)
    for entry_id in IDS:
        rows = [frame_values(d) for d in per_seed_documents(out, "compact-nerf", entry_id)]
        seed_index = rng.integers(0, len(rows), size=(RESAMPLES, len(rows)))
        view_index = rng.integers(0, len(rows[0]), size=(RESAMPLES, len(rows[0])))
        for b in range(RESAMPLES):
            suite_means[b] += sum(rows[s][v] for s in seed_index[b] for v in view_index[b]) / (
                len(rows) * len(rows[0])) / len(IDS)
    low, high = percentile_linear(suite_means, 2.5), percentile_linear(suite_means, 97.5)
    assert abs(ours["ci95"]["psnr"][0] - low) < 1e-9 and abs(ours["ci95"]["psnr"][1] - high) < 1e-9
    assert low < ours["mean"]["psnr"] < high
    # paired: ours minus nearest per (seed, view); nearest (deterministic, no seed) repeated per seed
    rows = {(row["scene"], row["reference"], row["method"]): row for row in board["paired"]["rows"]}
    for entry_id in IDS:
        row = rows[(entry_id, "compact-nerf", "nearest")]
        nearest = frame_values(read(out / "results" / "nearest" / entry_id / "metrics.json"))
        differences = [[a - b for a, b in zip(frame_values(d), nearest)]
                       for d in per_seed_documents(out, "compact-nerf", entry_id)]
        low, high = loop_bootstrap(differences, EVALUATE_SEED)
        assert abs(row["ci95"][0] - low) < 1e-9 and abs(row["ci95"][1] - high) < 1e-9
        assert row["mean_difference"] == pytest.approx(np.mean(differences), abs=1e-12)
        per_view = np.mean(differences, axis=0)
        assert row["p_value"] == pytest.approx(wilcoxon(per_view).pvalue, abs=1e-12)
        assert row["seeds"] == list(SEEDS) and row["views"] == 4
    markdown = (out / "leaderboard.md").read_text()
    assert "PSNR per seed (std)" in markdown and "0,1,2" in markdown and "PSNR 95% CI" in markdown
    assert "PSNR variance: seed / view / residual" in markdown and "(seeds " in markdown


@pytest.mark.slow
def test_a_second_run_resumes_every_finished_job(seeded, tmp_path, capsys):
    toml, out = seeded
    copy = tmp_path / "copy"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns(".nerfgauge.lock"))
    before = {entry_id: read(copy / "results" / "compact-nerf" / entry_id / "aggregate.json") for entry_id in IDS}
    (copy / "jobs" / "compact-nerf" / "seed-1" / "random-3.json").unlink()  # as if that job had been interrupted
    code, stdout, err = run(capsys, "suite", "run", toml, "--out", copy, "--seeds", "3")
    assert code == 0, err
    assert stdout.count("finished earlier, skipped") == 7 and "compact-nerf/seed-1/random-3: " in stdout
    assert "compact-nerf/seed-1/random-3: finished earlier" not in stdout
    for entry_id in IDS:
        after = read(copy / "results" / "compact-nerf" / entry_id / "aggregate.json")
        assert after["mean"] == before[entry_id]["mean"] and after["ci95"] == before[entry_id]["ci95"]


@pytest.mark.parametrize("value", ["0", "-1", "abc", "1,1", ",", "2000", "3.5"])
def test_bad_seeds_are_one_line_exit_2(value, tmp_path, capsys):
    code, _, err = run(capsys, "suite", "run", "smoke", "--out", tmp_path / "x", f"--seeds={value}")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--seeds" in err, err
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_suite_evaluate_with_seeds_pairs_by_seed(seeded, tmp_path, capsys):
    """Another tool run once per seed (PRED_ROOT/seed-<s>/<id>/): `suite evaluate --seeds`
    scores and aggregates it like ours; the paired row pairs run s with run s (here the same
    renders: every difference is 0, p = 1)."""
    toml, out = seeded
    copy = tmp_path / "copy"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns(".nerfgauge.lock"))
    code, _, err = run(capsys, "suite", "evaluate", toml, copy, "--method", "again", "--pred",
                       copy / "predictions" / "compact-nerf", "--seeds", "0,1,2")
    assert code == 0, err
    code, _, err = run(capsys, "suite", "report", copy)
    assert code == 0, err
    board = read(copy / "leaderboard.json")
    for entry_id in IDS:
        ours = read(copy / "results" / "compact-nerf" / entry_id / "aggregate.json")
        again = read(copy / "results" / "again" / entry_id / "aggregate.json")
        assert again["ci95"] == ours["ci95"] and again["per_seed"] == ours["per_seed"]
        row = next(r for r in board["paired"]["rows"]
                   if r["scene"] == entry_id and (r["reference"], r["method"]) == ("again", "compact-nerf"))
        assert row["seeds"] == list(SEEDS) and row["mean_difference"] == 0 and row["p_value"] == 1.0
    code, _, err = run(capsys, "suite", "evaluate", toml, copy, "--method", "x", "--pred",
                       copy / "predictions" / "compact-nerf", "--seeds", "0,7")
    assert code == 2 and "seed-7/primitives" in err and len(err.strip().splitlines()) == 1, err


def test_a_bad_scheduler_is_one_line_before_anything_is_written(tmp_path, capsys):
    code, _, err = run(capsys, "suite", "run", "smoke", "--out", tmp_path / "x", "--seeds", "2", "--scheduler", "nowhere")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "local:N" in err, err
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_a_two_worker_local_cluster_gives_the_same_per_run_metrics(seeded, tmp_path, capsys):
    """Same seeds on `--scheduler local:2`: the method jobs and the scoring jobs run on the
    cluster, and every per-run metrics.json has the same means and per-frame values as the
    local run; only timing (wall clock) may differ."""
    toml, out = seeded
    cluster = tmp_path / "cluster"
    code, stdout, err = run(capsys, "suite", "run", toml, "--out", cluster, "--seeds", "3", "--scheduler", "local:2")
    assert code == 0, err
    assert stdout.count("8 jobs on local:2") == 2  # 8 trainings and baselines, then 8 scorings, on the cluster
    for method, folders in (("compact-nerf", [f"{i}/seed-{s}" for i in IDS for s in SEEDS]), ("nearest", IDS)):
        for folder in folders:
            local = read(out / "results" / method / folder / "metrics.json")
            remote = read(cluster / "results" / method / folder / "metrics.json")
            assert local["mean"] == remote["mean"] and local["ci95"] == remote["ci95"]
            strip = [{k: v for k, v in frame.items() if k != "file"} for frame in local["frames"]]
            assert strip == [{k: v for k, v in frame.items() if k != "file"} for frame in remote["frames"]]
    for entry_id in IDS:
        a = read(out / "results" / "compact-nerf" / entry_id / "aggregate.json")
        b = read(cluster / "results" / "compact-nerf" / entry_id / "aggregate.json")
        assert a["ci95"] == b["ci95"] and a["variance"] == b["variance"]
    assert math.isfinite(read(cluster / "leaderboard.json")["methods"]["compact-nerf"]["mean"]["psnr"])


@pytest.mark.slow
def test_smoke_suite_with_three_seeds(tmp_path, capsys):
    """Issue 36's done-when: `suite run smoke --seeds 3` gives a leaderboard with intervals
    and the paired comparison of our NeRF with the nearest-view baseline, as recomputed here."""
    out = tmp_path / "smoke"
    code, _, err = run(capsys, "suite", "run", "smoke", "--out", out, "--seeds", "3")
    assert code == 0, err
    board = read(out / "leaderboard.json")
    ours = board["methods"]["compact-nerf"]
    assert ours["ci95"]["psnr"][0] <= ours["mean"]["psnr"] <= ours["ci95"]["psnr"][1]
    rows = {(row["scene"], row["reference"], row["method"]): row for row in board["paired"]["rows"]}
    for entry_id, scene in ours["scenes"].items():
        assert scene["seeds"] == [0, 1, 2] and len(scene["psnr_per_seed"]) == 3
        documents = [read(out / "results" / "compact-nerf" / entry_id / f"seed-{s}" / "metrics.json") for s in range(3)]
        nearest = frame_values(read(out / "results" / "nearest" / entry_id / "metrics.json"))
        differences = [[a - b for a, b in zip(frame_values(d), nearest)] for d in documents]
        low, high = loop_bootstrap(differences, EVALUATE_SEED)
        row = rows[(entry_id, "compact-nerf", "nearest")]
        assert abs(row["ci95"][0] - low) < 1e-9 and abs(row["ci95"][1] - high) < 1e-9


@pytest.mark.slow
def test_run_with_seeds_keeps_every_run_and_aggregates_them(tmp_path, capsys):
    """`nerfgauge run --seeds 0,2`: the first seed in OUT/run, the other in OUT/seeds/seed-2/run,
    both scored (with their training record) and aggregated as an independent loop
    bootstrap does; a rerun with --overwrite and no --seeds removes the seeded outputs."""
    out = tmp_path / "run"
    args = ["run", "primitives", "--out", out, "--res", "16", "--views", "4", "--test-views", "3", "--spp", "2",
            "--steps", "20", "--quiet"]
    code, stdout, err = run(capsys, *args, "--seeds", "0,2")
    assert code == 0, err
    assert (out / "run" / "model.pt").is_file() and (out / "seeds" / "seed-2" / "run" / "model.pt").is_file()
    documents = [read(out / "eval" / "compact" / f"seed-{s}" / "metrics.json") for s in (0, 2)]
    assert [d["training"]["seed"] for d in documents] == [0, 2]
    assert all(d["training"]["steps"] == 20 and d["training"]["steps_per_second"] > 0 for d in documents)
    assert documents[0]["mean"] == read(out / "eval" / "compact" / "metrics.json")["mean"]
    aggregate = read(out / "eval" / "compact" / "aggregate.json")
    low, high = loop_bootstrap([frame_values(d) for d in documents], EVALUATE_SEED)
    assert abs(aggregate["ci95"]["psnr"][0] - low) < 1e-9 and abs(aggregate["ci95"]["psnr"][1] - high) < 1e-9
    assert "PSNR over 2 seeds x 3 views" in stdout
    code, _, err = run(capsys, *args, "--overwrite")
    assert code == 0, err
    assert not (out / "seeds").exists() and not (out / "eval" / "compact" / "aggregate.json").exists()
    assert not (out / "eval" / "compact" / "seed-2").exists()


@pytest.mark.parametrize("cores, scheduler, given, suite_threads, expected", [
    (2, None, None, None, 2),            # no cluster: the training default (TrainConfig.threads)
    (2, "local:2", None, None, 1),       # 2 workers x 2 threads on 2 cores: a share each
    (8, "local:2", None, None, 2),       # room for both: the default stands
    (2, "local:4", None, None, 1),       # never below one
    (2, "local:2", None, 1, 1),          # the suite's own threads fit
    (2, "local:2", 3, None, 3),          # --threads wins, even oversubscribed: the user asked
    (2, "tcp://10.0.0.5:8786", None, None, 2),  # a remote cluster's workers have their own cores
])
def test_training_threads_share_a_local_clusters_cores(monkeypatch, cores, scheduler, given, suite_threads, expected):
    from nerfgauge.orchestrate.suite import run as suite_run
    from nerfgauge.orchestrate.suite.definition import load_suite
    monkeypatch.setattr(suite_run.os, "sched_getaffinity", lambda pid: set(range(cores)), raising=False)
    suite = load_suite("smoke")
    train = {key: value for key, value in suite.train.items() if key != "threads"}
    if suite_threads is not None:
        train["threads"] = suite_threads
    suite = dataclasses.replace(suite, train=train)
    threads, why = suite_run.training_threads(suite, scheduler, given)
    assert threads == expected and why


def test_bad_threads_are_one_line_exit_2(tmp_path, capsys):
    code, _, err = run(capsys, "suite", "run", "smoke", "--out", tmp_path / "x", "--threads", "0")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--threads" in err, err
    assert not (tmp_path / "x").exists()
