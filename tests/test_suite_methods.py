"""Issue 49 item 4: suites over any method. One suite run (`suite run --seeds 2`) over one
16x16 dataset with every kind of method: our compact NeRF (a 2 s budget), the nearest
baseline, a Python class (tests/fake_method.py, `fake_method:Grey`), another tool's method as
a spec file over a small program (tests/fake_tool.py) that renders noisy ground truth, and specs that fail each way (a
command that exits non-zero, one that runs past twice its budget, one that writes no
renders). Grouped by what could go wrong: a method's failure reaching past its job, scores
that differ from `nerfgauge evaluate`, intervals and pairs that differ from an independent
computation, lengths given to the wrong methods, a suite file or flag read wrongly."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import wilcoxon
from suite_toml import suite_toml
from test_suite import one_line_error, run
from test_uncertainty import loop_bootstrap

from nerfgauge.cli import main
from nerfgauge.eval.uncertainty import EVALUATE_SEED
from nerfgauge.orchestrate.suite.definition import load_suite

DATASET = {"width": 16, "height": 16, "views": 4, "val_views": 0, "test_views": 2, "spp": 2}
SCENES = ({"scene": "primitives", "seed": 0},)
TRAIN = {"steps": 4, "budget_seconds": 2.0, "threads": 1}  # the budget to the methods that accept one
PROGRAM = Path(__file__).with_name("fake_tool.py")
FAILING = {"crasher": "exited with status 3", "sleeper": "twice its budget", "blank": "wrote no images"}
SCORED = ("compact-nerf", "copycat", "grey", "nearest")
SEEDED = {"compact-nerf": True, "copycat": True, "grey": False, "nearest": False}
METHODS = [{"name": "compact-nerf", "method": "compact"}, {"method": "nearest"}, {"method": "fake_method:Grey"},
           {"method": "copycat.toml"}, {"method": "crasher.toml"},
           {"method": "sleeper.toml", "budget_seconds": 0.5},  # its own length, in place of the suite's
           {"method": "blank.toml"}]


def write_spec(folder: Path, name: str, train=("train", "{run}", "{seed}"),
               render=("render", "{dataset}", "{split}", "{out}", "{seed}"), length="steps") -> Path:
    argv = lambda args: json.dumps([sys.executable, str(PROGRAM), *args])  # noqa: E731
    path = folder / f"{name}.toml"
    path.write_text(f'name = "{name}"\nsummary = "a test method"\n[train]\ncommand = {argv(train)}\n'
                    f'length = "{length}"\n[render]\ncommand = {argv(render)}\nlayout = "nerfgauge"\n')
    return path


def write_suite(folder: Path, name: str = "methods", methods=METHODS, **scoring) -> Path:
    for spec, kwargs in (("copycat", {}), ("crasher", {"train": ("fail",)}),
                         ("sleeper", {"train": ("sleep",), "length": "seconds"}),
                         ("blank", {"render": ("nothing",)})):
        write_spec(folder, spec, **kwargs)
    path = folder / f"{name}.toml"
    path.write_text(suite_toml(name, DATASET, TRAIN, SCENES, protocol=scoring or None, methods=methods))
    return path


def quiet(*argv) -> tuple[int, str]:
    """main(argv) with its stdout captured (for module fixtures, which have no capsys)."""
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        code = main([str(a) for a in argv])
    return code, buffer.getvalue()


def read(path: Path):
    return json.loads(path.read_text())


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    """`suite run methods.toml --seeds 2`: (suite file, suite folder, its stdout)."""
    root = tmp_path_factory.mktemp("methods")
    toml = write_suite(root)
    out = root / "S"
    code, stdout = quiet("suite", "run", toml, "--out", out, "--seeds", "2")
    assert code == 0, stdout
    return toml, out, stdout


def frame_values(document, metric="psnr"):
    return [frame[metric] for frame in document["frames"]]


def documents(out: Path, method: str, seeded: bool) -> list:
    folder = out / "results" / method / "primitives"
    return [read(folder / f"seed-{s}" / "metrics.json") for s in (0, 1)] if seeded else [read(folder / "metrics.json")]


# --- a failing method: its row, and nothing outside its run folder ---------------------------------


@pytest.mark.slow
def test_each_failure_is_one_row_with_its_reason_and_the_suite_finishes(ran):
    _, out, stdout = ran
    board = read(out / "leaderboard.json")
    assert set(board["methods"]) == set(SCORED) | set(FAILING)
    for method, words in FAILING.items():
        data = board["methods"][method]
        assert data["scenes"] == {} and set(data["failed"]) == {"primitives"}
        assert data["failed"]["primitives"].startswith("seed 0: ") and words in data["failed"]["primitives"]
        assert f"{method} failed on 1 dataset(s)" in stdout
    for method in SCORED:
        assert "failed" not in board["methods"][method] and "primitives" in board["methods"][method]["scenes"]
    markdown = (out / "leaderboard.md").read_text()
    mean_table = markdown.split("\n## ")[1]
    for method, words in FAILING.items():
        row = next(line for line in mean_table.splitlines() if line.startswith(f"| {method} |"))
        assert "1/1: seed 0: " in row and words in row  # one row, with the reason


@pytest.mark.slow
def test_a_failed_job_leaves_nothing_outside_its_run_folder(ran):
    """Every path naming a failed method lies in its run folders (with its log and the
    traceback) or is its leaderboard row (results/<method>/result.json); no renders, no
    job record (the next run tries it again)."""
    _, out, _ = ran
    for method in FAILING:
        paths = {p.relative_to(out).as_posix() for p in out.rglob("*") if method in p.relative_to(out).parts}
        outside = {p for p in paths if not p.startswith(f"runs/{method}/")} - {
            f"runs/{method}", f"results/{method}", f"results/{method}/result.json"}
        assert outside == set() and f"runs/{method}/seed-0/primitives/failure.txt" in paths
    sleeper = out / "runs" / "sleeper" / "seed-0" / "primitives"
    assert "stopped" in (sleeper / "failure.txt").read_text() and (sleeper / "train.log").is_file()


# --- scores through any method equal `nerfgauge evaluate` ---------------------------------------------


@pytest.mark.parametrize("method, seed", [("copycat", 1), ("grey", None), ("compact-nerf", 0)])
def test_scores_equal_evaluate_on_the_same_renders(ran, tmp_path, method, seed):
    _, out, _ = ran
    where = "primitives" if seed is None else f"seed-{seed}/primitives"
    single = tmp_path / "single.json"
    assert main(["evaluate", str(out / "datasets" / "primitives"), "--pred", str(out / "predictions" / method / where),
                 "--out", str(single)]) == 0
    scored = read(out / "results" / method / "primitives" / ("" if seed is None else f"seed-{seed}") / "metrics.json")
    assert scored["mean"] == read(single)["mean"] and scored["protocol"] == "nerfgauge"


# --- intervals and pairs against an independent computation -------------------------------------------


def test_every_pair_of_methods_is_compared_as_an_independent_bootstrap_computes_it(ran):
    _, out, _ = ran
    board = read(out / "leaderboard.json")
    rows = {(row["reference"], row["method"]): row for row in board["paired"]["rows"]}
    assert set(rows) == {(a, b) for a in SCORED for b in SCORED if a < b}  # every pair, in name order
    for (a, b), row in rows.items():
        ours, theirs = documents(out, a, SEEDED[a]), documents(out, b, SEEDED[b])
        if len(ours) != len(theirs):  # a method run once is paired with every seed of the other
            ours, theirs = ours * (2 // len(ours)), theirs * (2 // len(theirs))
        differences = [[x - y for x, y in zip(frame_values(p), frame_values(q))] for p, q in zip(ours, theirs)]
        low, high = loop_bootstrap(differences, EVALUATE_SEED)
        assert abs(row["ci95"][0] - low) < 1e-9 and abs(row["ci95"][1] - high) < 1e-9
        assert row["mean_difference"] == pytest.approx(np.mean(differences), abs=1e-12)
        with warnings.catch_warnings():  # scipy computes its normal approximation's z for n = 2 too (0/0)
            warnings.simplefilter("ignore", RuntimeWarning)
            expected = wilcoxon(np.mean(differences, axis=0)).pvalue  # exact for 2 views
        assert row["p_value"] == pytest.approx(expected, abs=1e-12)
        assert row["seeds"] == ([0, 1] if SEEDED[a] or SEEDED[b] else None)
    for method in SCORED:  # each method's interval: seeds then views for the seeded, views for the others
        data = board["methods"][method]
        rows = [frame_values(d) for d in documents(out, method, SEEDED[method])]
        assert data["scenes"]["primitives"].get("seeds") == ([0, 1] if SEEDED[method] else None)
        if SEEDED[method]:
            low, high = loop_bootstrap(rows, EVALUATE_SEED)
            assert abs(data["scenes"]["primitives"]["psnr_ci95"][0] - low) < 1e-9


# --- lengths: budgets to the methods that accept one; cost reported for every method ----------------


def test_budgets_go_to_the_methods_that_accept_one_and_every_method_reports_its_cost(ran):
    _, out, stdout = ran
    result = {m: read(out / "results" / m / "result.json")["datasets"]["primitives"] for m in SCORED}
    runs = {m: row.get("runs", [row]) for m, row in result.items()}
    assert "compact-nerf (2 s budget), nearest (no training), grey (no training), copycat (4 steps)" in stdout
    for method, steps, budget in (("compact-nerf", None, 2.0), ("copycat", 4, None)):
        for run in runs[method]:  # ours accepts a budget and gets the suite's; the spec takes steps only
            assert run["budget_seconds"] == budget and (steps is None or run["steps"] == steps)
            assert run["steps"] >= 1 and run["steps_per_second"] == pytest.approx(run["steps"] / run["train_seconds"],
                                                                                   rel=1e-9)
    for method in SCORED:  # wall time and render time for every method; memory for those that train
        for run in runs[method]:
            assert run["train_seconds"] >= 0 and run["ms_per_frame"] > 0
            assert (run["peak_memory_bytes"] or 0) > 0 or not SEEDED[method]
    board = read(out / "leaderboard.json")
    assert {"train_seconds", "steps_per_second", "peak_memory_bytes"} <= set(board["columns"])
    assert board["methods"]["copycat"]["mean"]["steps_per_second"] > 0


# --- the command line: --methods, resuming ---------------------------------------------------------


@pytest.mark.slow
def test_methods_flag_replaces_the_suites_and_resumes_their_jobs(ran, tmp_path, capsys):
    toml, out, _ = ran
    copy = tmp_path / "S"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns(".nerfgauge.lock"))
    code, stdout, err = run(capsys, "suite", "run", toml, "--out", copy, "--seeds", "2", "--methods",
                            "copycat,nearest")
    assert code == 0, err
    jobs = [line for line in stdout.splitlines() if line.startswith("    job ") and " score/" not in line]
    assert len(jobs) == 3 and all("finished earlier, skipped" in line for line in jobs), jobs
    assert "2 jobs\n" not in stdout and "copycat (4 steps), nearest (no training)" in stdout
    assert "compact-nerf/" not in stdout


@pytest.mark.parametrize("methods, words", [
    ("copycat,nerf-w", ("unknown method 'nerf-w'",)),
    ("nearest,nearest", ("used twice",)),
    ("copycat,", ("--methods must be",)),
])
def test_a_bad_methods_flag_is_one_line_before_anything_is_written(tmp_path, capsys, methods, words):
    toml = write_suite(tmp_path)
    code, _, err = run(capsys, "suite", "run", toml, "--out", tmp_path / "x", "--methods", methods)
    one_line_error(code, err, *words)
    assert not (tmp_path / "x").exists()


# --- the suite file: [[methods]] checked when read; [protocol] renamed [scoring] -----------------------


@pytest.mark.parametrize("methods, words", [
    ([{"method": "compact", "settings": {"bogus": 1}}], ("methods[0]", "unknown setting 'bogus'")),
    ([{"method": "nearest", "budget_seconds": 5.0}], ("methods[0]", "does not train")),
    ([{"method": "copycat.toml", "budget_seconds": 5.0}], ("takes a step count, not a time budget",)),
    ([{"method": "nearest"}, {"method": "nearest"}], ("'nearest' is used twice",)),
    ([{"method": "nearest", "name": "Near Est"}], ("name 'Near Est'",)),
    ([{"method": "missing.toml"}], ("method spec not found",)),
    ([{"method": "nearest", "seeds": 3}], ("unknown field 'seeds'",)),
])
def test_a_bad_methods_table_is_the_files_one_line_error(tmp_path, capsys, methods, words):
    toml = write_suite(tmp_path, methods=methods)
    code, _, err = run(capsys, "suite", "run", toml, "--out", tmp_path / "x")
    one_line_error(code, err, str(toml), *words)
    assert not (tmp_path / "x").exists()


def test_an_older_protocol_table_is_read_with_a_one_line_note(ran, tmp_path, capsys):
    """[protocol] with baselines (the older file) is the same suite as [scoring] with
    [[methods]]: the same sha256, so its folder is resumed; the note is one line on stderr."""
    toml, out, _ = ran
    text = toml.read_text()
    old = tmp_path / "old.toml"
    old.write_text(text.split("\n[train]")[0] + '\n[train]\nsteps = 4\n\n[protocol]\nsplit = "test"\n'
                   'background = "white"\ndepth_kind = "distance"\nbaselines = ["nearest"]\n\n[[scenes]]'
                   + text.split("[[scenes]]", 1)[1])
    suite, new = load_suite(old), load_suite(toml)
    assert suite.sha256 == new.sha256 and [m.name for m in suite.methods] == ["compact-nerf", "nearest"]
    copy = tmp_path / "S"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns(".nerfgauge.lock"))
    code, stdout, err = run(capsys, "suite", "generate", old, "--out", copy)
    assert code == 0 and "complete, skipped" in stdout
    assert len(err.strip().splitlines()) == 1 and "[protocol] is now called [scoring]" in err, err
    recorded = read(copy / "suite.json")  # a folder an older nerfgauge made: its hash covered [protocol]
    recorded["definition"]["protocol"], recorded["suite_sha256"] = recorded["definition"].pop("scoring"), "0" * 64
    (copy / "suite.json").write_text(json.dumps(recorded))
    code, _, err = run(capsys, "suite", "generate", toml, "--out", copy)
    one_line_error(code, err, "made by an older nerfgauge", "--overwrite")
    both = tmp_path / "both.toml"
    both.write_text(old.read_text().replace("[protocol]", "[scoring]\nsplit = \"test\"\n[protocol]", 1))
    code, _, err = run(capsys, "suite", "generate", both, "--out", tmp_path / "y")
    one_line_error(code, err, "the older name of [scoring]")


def test_a_suite_chooses_its_scoring_protocol(ran, tmp_path, capsys):
    """[scoring] protocol = "ns-eval" (on black, as ns-eval composites): every metrics.json
    scored that way, equal to `nerfgauge evaluate --protocol ns-eval` on the same renders; a
    background the protocol contradicts is the file's one-line error."""
    _, out, _ = ran
    wrong = write_suite(tmp_path, "ns", [{"method": "nearest"}], protocol="ns-eval")
    code, _, err = run(capsys, "suite", "generate", wrong, "--out", tmp_path / "x")
    one_line_error(code, err, "composites onto black", 'scoring.background = "black"')
    toml = write_suite(tmp_path, "ns", [{"method": "nearest"}], protocol="ns-eval", background="black")
    folder = tmp_path / "ns"
    renders = out / "predictions" / "copycat" / "seed-0"
    assert quiet("suite", "generate", toml, "--out", folder)[0] == 0
    code, _, err = run(capsys, "suite", "evaluate", toml, folder, "--method", "copycat", "--pred", renders)
    assert code == 0, err
    single = tmp_path / "single.json"
    assert main(["evaluate", str(folder / "datasets" / "primitives"), "--pred", str(renders / "primitives"),
                 "--protocol", "ns-eval", "--background", "black", "--out", str(single)]) == 0
    scored = read(folder / "results" / "copycat" / "primitives" / "metrics.json")
    assert scored["protocol"] == "ns-eval" and scored["mean"] == read(single)["mean"]


# --- bench train --methods: another tool's method against wall time beside ours ------------------------


@pytest.mark.slow
def test_bench_train_puts_other_methods_beside_ours_on_the_same_dataset(ran, tmp_path):
    """bench train's rows for --methods (orchestrate.bench.train.method_rows) on the suite's
    dataset: our compact NeRF (a 1 s budget, in this process), the spec method (4 steps), the
    nearest baseline and a failing spec: a row each (the failure's with its reason), every
    score the same `evaluate` gives on the run's renders, the table and the plot drawn."""
    from nerfgauge.eval.evaluate import evaluate
    from nerfgauge.methods.registry import resolve
    from nerfgauge.orchestrate.bench.train import method_rows, pareto_plots, table_markdown

    toml, out, _ = ran
    dataset, bench = out / "datasets" / "primitives", tmp_path / "bench"
    rows = []
    for name in ("compact", "copycat.toml", "nearest", "crasher.toml"):
        method = resolve(str(toml.parent / name) if name.endswith(".toml") else name)
        rows += method_rows(method, "primitives", dataset, bench, budgets=[1.0], steps=[4])
    by_name = {row["variant"]: row for row in rows}
    assert list(by_name) == ["compact", "copycat", "nearest", "crasher"] and len(rows) == 4
    assert "exited with status 3" in by_name["crasher"]["error"]
    assert by_name["compact"]["budget"] == 1.0 and by_name["copycat"]["method_steps"] == 4
    assert by_name["copycat"]["steps_per_second"] == pytest.approx(4 / by_name["copycat"]["train_seconds"], rel=1e-9)
    for name, label in (("compact", "1s"), ("copycat", "4steps"), ("nearest", "once")):
        again = evaluate(dataset, bench / "runs" / f"primitives-{name}-{label}" / "renders", "test", tmp_path / "e.json")
        assert by_name[name]["psnr"] == again["mean"]["psnr"] and by_name[name]["train_seconds"] >= 0
    assert by_name["compact"]["log"] and by_name["compact"]["val_psnr"] is not None  # our curve beside the others
    table = table_markdown(rows)
    assert "| primitives | copycat | 4 steps |" in table and "| primitives | nearest | – |" in table
    pareto_plots(rows, bench)
    assert (bench / "pareto.png").stat().st_size > 0


@pytest.mark.parametrize("argv, words", [
    (["--methods", "nerf-w"], ("unknown method 'nerf-w'",)),
    (["--methods", "COPYCAT"], ("takes a step count", "--steps")),
])
def test_bench_train_refuses_a_method_it_cannot_run_before_any_work(tmp_path, capsys, argv, words):
    write_spec(tmp_path, "copycat")
    argv = [str(tmp_path / "copycat.toml") if a == "COPYCAT" else a for a in argv]
    code, _, err = run(capsys, "bench", "train", "--out", tmp_path / "b", *argv)
    one_line_error(code, err, *words)
    assert not (tmp_path / "b").exists()
