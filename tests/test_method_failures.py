"""A method run through its spec that fails: its command exits non-zero, runs past twice its
budget, or writes no renders. Each gives MethodFailed (the result a suite turns into the
job's row: the method's name and a one-line reason naming the cause and the log), leaves
nothing that looks complete (no RUN/method.json after a failed training), and writes
nothing outside the job's folder (its run and its renders): the tool's temporary folder,
home and caches are inside the run (the harness's TMPDIR, the spec's variables), and this
process's own home, temporary folder, caches, the dataset and the spec's folder are as they
were, snapshotted before and after.

The tool here is a small Python program that writes into each of those places before it
fails, so the containment is exercised, not assumed.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from fuzzing import snapshot, snapshot_changes
from nerfgauge.methods.external import MethodFailed
from nerfgauge.methods.interface import TrainRequest
from nerfgauge.methods.registry import resolve

TOOL = textwrap.dedent('''
    import os, pathlib, subprocess, sys, time
    mode = sys.argv[1]
    # what a real tool leaves behind: temporary files, a file in its home, a cache entry
    for variable in ("TMPDIR", "HOME", "XDG_CACHE_HOME"):
        folder = pathlib.Path(os.environ[variable])
        folder.mkdir(parents=True, exist_ok=True)
        (folder / f"left-by-{mode}.txt").write_text("x")
    print("tool", mode, "started", flush=True)
    if mode == "train":
        (pathlib.Path.cwd() / "weights.txt").write_text("1")
    elif mode == "exit":
        sys.exit(3)
    elif mode == "hang":
        subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)  # grandchild"])
        time.sleep(120)
    elif mode == "nothing":
        pass
''')

OUTSIDE = ("HOME", "TMPDIR", "XDG_CACHE_HOME", "XDG_CONFIG_HOME", "XDG_DATA_HOME")


def spec_file(folder: Path, train: str, render: str, length: str = "steps", render_timeout: float | None = None) -> Path:
    tool = folder / "tool.py"
    tool.write_text(TOOL)
    argv = lambda mode: json.dumps([sys.executable, str(tool), mode])  # noqa: E731
    timeout = "" if render_timeout is None else f"timeout_seconds = {render_timeout}\n"
    spec = folder / "failing.toml"
    spec.write_text(f'name = "failing"\n[environment]\nvariables = {{ HOME = "{{run}}/home", '
                    f'XDG_CACHE_HOME = "{{run}}/cache" }}\n[train]\ncommand = {argv(train)}\nlength = "{length}"\n'
                    f'[render]\ncommand = {argv(render)}\nlayout = "nerfgauge"\n{timeout}'
                    '[files]\nweights = "{run}/weights.txt"\n')
    return spec


@pytest.fixture
def world(tmp_path, tiny_dataset, monkeypatch):
    """This process's home, temporary folder and caches (which a child inherits unless the
    harness redirects them), a folder for the spec, and the job's folder; `method(...)`
    writes the spec (spec_file's arguments) and snapshots everything outside the job's
    folder, `changes()` lists what changed there since."""
    outside = tmp_path / "outside"
    for variable in OUTSIDE:
        (outside / variable.lower()).mkdir(parents=True)
        monkeypatch.setenv(variable, str(outside / variable.lower()))
    (outside / "spec").mkdir()
    job = tmp_path / "job"
    roots, before = (tmp_path, tiny_dataset), {}

    def method(*args, **kwargs):
        found = resolve(str(spec_file(outside / "spec", *args, **kwargs)))
        before.update(snapshot(roots, exclude=(job,)))
        return found

    def changes() -> list[str]:
        return snapshot_changes(before, snapshot(roots, exclude=(job,)))

    return {"method": method, "job": job, "changes": changes}


def contained(run: Path, mode: str) -> None:
    """The tool's leavings are in the run: its TMPDIR, home and cache."""
    for where in (".tmp", "home", "cache"):
        assert (run / where / f"left-by-{mode}.txt").is_file(), where


def one_line(error: MethodFailed, cause: str, log: Path) -> None:
    assert error.method == "failing" and cause in error.reason and str(log) in error.reason
    assert str(error) == f"method failing: {error.reason}" and "\n" not in str(error)


def test_a_training_that_exits_non_zero_fails_with_its_reason_and_writes_only_its_run(world, tiny_dataset):
    run = world["job"] / "run"
    with pytest.raises(MethodFailed) as error:
        world["method"]("exit", "nothing").train(
            TrainRequest(dataset=tiny_dataset, run=run, steps=1))
    one_line(error.value, "exited with status 3", run / "train.log")
    assert "tool exit started" in (run / "train.log").read_text()
    assert not (run / "method.json").exists()  # a failed training never looks trained
    contained(run, "exit")
    assert world["changes"]() == []


def test_a_training_past_twice_its_budget_is_stopped_with_its_reason_and_writes_only_its_run(world, tiny_dataset):
    run = world["job"] / "run"
    start = time.perf_counter()
    with pytest.raises(MethodFailed) as error:
        world["method"]("hang", "nothing", length="seconds").train(
            TrainRequest(dataset=tiny_dataset, run=run, budget_seconds=0.5))
    assert time.perf_counter() - start < 1.0 + 10  # stopped at 2 x 0.5 s (and a loaded machine's slack)
    one_line(error.value, "ran past 1 s (twice its budget) and was stopped", run / "train.log")
    assert not (run / "method.json").exists()
    survivors = subprocess.run(["pgrep", "-f", "time.sleep\\(120\\)  # grandchild"], capture_output=True,
                               text=True).stdout.split()
    assert not [pid for pid in survivors if int(pid) != os.getpid()], "the tool's grandchild outlived it"
    contained(run, "hang")
    assert world["changes"]() == []


@pytest.mark.parametrize("mode, timeout, cause", [
    ("hang", 0.5, "ran past 0.5 s (its spec's render.timeout_seconds) and was stopped; log: {log}"),
    ("exit", None, "{program} exited with status 3; log: {log}"),
    ("nothing", None, "its render command wrote no images under {renders}"),
], ids=["stopped", "exit-non-zero", "no-renders"])
def test_a_render_that_fails_gives_its_reason_and_writes_only_its_job(world, tiny_dataset, mode, timeout, cause):
    """Stopped past its timeout, exited non-zero, or wrote no renders."""
    run, renders = world["job"] / "run", world["job"] / "renders"
    method = world["method"]("train", mode, render_timeout=timeout)
    method.train(TrainRequest(dataset=tiny_dataset, run=run, steps=1))
    with pytest.raises(MethodFailed) as error:
        method.render(run, tiny_dataset, "test", renders)
    reason = cause.format(log=run / "render-test.log", renders=renders, program=Path(sys.executable).name)
    assert error.value.method == "failing" and error.value.reason == reason
    assert str(error.value) == f"method failing: {error.value.reason}" and "\n" not in str(error.value)
    contained(run, mode)
    assert world["changes"]() == []
