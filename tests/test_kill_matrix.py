"""kill -9 at seeded moments, then the same command again (RELIABILITY.md): the result must be
what an uninterrupted run makes, byte for byte (datasets) or tensor for tensor (models).

- generate, --workers 1 and 2: SIGKILL to the parent only (never its group) after k views
  are on disk (the folder is polled); every worker must die within a few seconds of it;
  the rerun's dataset has the sha256 of every file of the uninterrupted run's (the lock
  file, which names a PID, excepted) and no temporary left behind. At 64 px and 64 spp
  (issue 31): at 16 px and 8 spp mi.render's thread-ordered sums happened to agree, at
  64 px they did not (tests/test_determinism.py); 6 views keep the CI moments short.
- train --steps N --checkpoint-every K: SIGKILL after the j-th checkpoint write (plus a
  seeded delay), rerun with --resume (plainly when no checkpoint was written yet); every
  tensor of model.pt equals the uninterrupted run's (torch.equal) at the same threads.
- a second writer while the first holds the folder: one line, exit 2, the first unharmed.
- linked variants (issue 47): after the kill a symbolic link to a user's folder is planted
  inside the folder (generate: train/; train: log.jsonl); the rerun is refused with one
  line naming the link, and the user's folder is unchanged (paths, sizes, mtimes, contents).

Commands run as subprocesses (`python -m nerfgauge.cli`). The unmarked tests (one kill per
worker count, one training kill) run in CI every time; the `slow` matrix adds moments.
"""

from __future__ import annotations

import hashlib
import os
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fuzzing import run_cli, snapshot, snapshot_changes

LOCK = ".nerfgauge.lock"  # holds the writer's PID: differs between runs by design
GENERATE = ["generate", "primitives", "--res", "64", "--views", "4", "--val-views", "1", "--test-views", "1",
            "--spp", "64", "--quiet"]
TOTAL_VIEWS = 6
WORKER_GRACE_SECONDS = 5.0
TRAIN_STEPS, CHECKPOINT_EVERY = 60, 10
VIEW_PNG = re.compile(r"^r_\d+\.png$")


def command(argv) -> list:
    return [sys.executable, "-m", "nerfgauge.cli", *map(str, argv)]


def run_to_end(argv, cwd) -> subprocess.CompletedProcess:
    done = subprocess.run(command(argv), cwd=cwd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"{' '.join(map(str, argv))}: exit {done.returncode}: {done.stderr[-800:]}"
    return done


def tree_digest(folder: Path) -> dict:
    """{relative path: sha256} of every file (symlinks as their target text), lock excepted."""
    digest = {}
    for path in sorted(folder.rglob("*")):
        rel = path.relative_to(folder).as_posix()
        if path.name == LOCK or path.is_dir() and not path.is_symlink():
            continue
        body = os.readlink(path).encode() if path.is_symlink() else path.read_bytes()
        digest[rel] = hashlib.sha256(body).hexdigest()
    return digest


def describe_difference(got: dict, want: dict) -> str:
    missing = sorted(want.keys() - got.keys())
    extra = sorted(got.keys() - want.keys())
    changed = sorted(k for k in want.keys() & got.keys() if want[k] != got[k])
    return f"missing {missing[:5]}, extra {extra[:5]}, different {changed[:8]} ({len(changed)} in all)"


# --------------------------------------------------------------------------------------
# processes


def _parents() -> dict:
    """{pid: parent pid} of every live process (from /proc)."""
    table = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            table[int(entry)] = int(stat.rsplit(")", 1)[1].split()[1])
    return table


def descendants(pid: int) -> set:
    table = _parents()
    found, frontier = set(), {pid}
    while frontier:
        frontier = {child for child, parent in table.items() if parent in frontier} - found
        found |= frontier
    return found


def alive(pid: int) -> bool:
    """Running (a zombie waiting for a reaper has died)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


def kill_parent_and_watch(process: subprocess.Popen) -> list:
    """SIGKILL the parent only; return the descendants still running after the grace period
    (they are then killed, by PID, so nothing outlives the test)."""
    children = descendants(process.pid)
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=30)
    deadline = time.monotonic() + WORKER_GRACE_SECONDS
    while time.monotonic() < deadline and any(alive(pid) for pid in children):
        time.sleep(0.05)
    survivors = sorted(pid for pid in children if alive(pid))
    for pid in survivors:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return survivors


def wait_for(condition, process: subprocess.Popen, timeout: float = 300.0) -> bool:
    """Poll until condition() holds (True) or the process ended first (False)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        if process.poll() is not None:
            return condition()
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting; the process is {'running' if process.poll() is None else 'done'}")


def kill_when(process: subprocess.Popen, condition, delay: float = 0.0) -> tuple[bool, list]:
    """Wait until condition() holds, then `delay` s, then kill -9 the parent (if it is still
    running). Returns (killed, descendants that outlived it). The process is always reaped."""
    try:
        landed = wait_for(condition, process)
        time.sleep(delay)
        landed = landed and process.poll() is None
        survivors = kill_parent_and_watch(process) if landed else []
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        process.stderr.close()
    return landed, survivors


# --------------------------------------------------------------------------------------
# generate


def views_on_disk(folder: Path) -> int:
    """Views whose PNG exists (the PNG is each view's last file)."""
    return sum(1 for p in folder.rglob("r_*.png") if VIEW_PNG.match(p.name)) if folder.is_dir() else 0


@pytest.fixture(scope="module")
def reference_dataset(tmp_path_factory):
    """The uninterrupted run, with one worker."""
    folder = tmp_path_factory.mktemp("kill") / "reference"
    run_to_end(GENERATE + ["--out", folder], folder.parent)
    return tree_digest(folder)


def kill_generate_and_resume(folder: Path, workers: int, views_before_kill: int, reference: dict) -> str:
    """Start, kill -9 once `views_before_kill` views are on disk, rerun; returns how it went
    (the assertions carry the reproduction)."""
    argv = GENERATE + ["--out", folder, "--workers", str(workers)]
    repro = (f"nerfgauge {' '.join(map(str, argv))} & (kill -9 after {views_before_kill} views); "
             f"nerfgauge {' '.join(map(str, argv))}")
    process = subprocess.Popen(command(argv), cwd=folder.parent, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, start_new_session=True)
    if views_before_kill == 0:
        def started():
            return (folder / "config.json").is_file() or folder.is_dir() and any(folder.iterdir())
    else:
        def started():
            return views_on_disk(folder) >= views_before_kill
    landed, survivors = kill_when(process, started)
    assert not survivors, f"workers {survivors} outlived their killed parent by {WORKER_GRACE_SECONDS} s\n  {repro}"
    rerun = subprocess.run(command(argv), cwd=folder.parent, capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, f"rerun after kill: exit {rerun.returncode}: {rerun.stderr[-600:]}\n  {repro}"
    leftovers = [p.name for p in folder.rglob(".*.tmp*")]
    assert not leftovers, f"temporaries left after the rerun: {leftovers}\n  {repro}"
    got = tree_digest(folder)
    assert got == reference, f"resumed dataset differs from the uninterrupted one: " \
                             f"{describe_difference(got, reference)}\n  {repro}"
    return "killed" if landed else "finished before the kill"


def seeded_moments(seed: int, count: int) -> list:
    """`count` distinct numbers of views after which to kill, from 0 (before any view) to
    TOTAL_VIEWS - 1, drawn from a seeded generator."""
    return sorted(random.Random(seed).sample(range(TOTAL_VIEWS), count))


@pytest.mark.parametrize("workers", [1, 2])
def test_generate_killed_once_resumes_to_the_same_bytes(tmp_path, reference_dataset, workers):
    (moment,) = seeded_moments(seed=18 + workers, count=1)
    moment = max(moment, 1)
    how = kill_generate_and_resume(tmp_path / "ds", workers, moment, reference_dataset)
    assert how == "killed", f"the kill after {moment} views came too late to test anything"


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 2])
def test_generate_kill_matrix(tmp_path, reference_dataset, workers):
    """Three more seeded moments per worker count, including before the first view."""
    moments = sorted({0, *seeded_moments(seed=1800 + workers, count=2)})
    landed = [kill_generate_and_resume(tmp_path / f"ds-{m}", workers, m, reference_dataset) for m in moments]
    assert landed.count("killed") >= len(moments) - 1, dict(zip(moments, landed))


def plant_link(path: Path, user: Path) -> dict:
    """Move `path` (a folder or file of ours) into the user's folder `user` beside a file of
    their own, and put a symbolic link to it in its place. Returns the user's folder's
    snapshot: paths, sizes and mtimes, with every file's sha256."""
    user.mkdir()
    (user / "my_notes.txt").write_text("the user's own notes\n")
    moved = user / path.name
    os.rename(path, moved)
    path.symlink_to(moved, target_is_directory=moved.is_dir())
    return user_state(user)


def user_state(user: Path) -> dict:
    return {"stat": snapshot([user]), "sha256": tree_digest(user)}


def assert_refused_naming(done: subprocess.CompletedProcess, link: Path, repro: str) -> None:
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2 and len(lines) == 1 and "Traceback" not in done.stderr \
        and f"{link} is a symbolic link" in lines[0], \
        f"rerun with a planted link: exit {done.returncode}, stderr {done.stderr[-600:]!r}\n  {repro}"


def test_generate_killed_then_a_planted_link_is_refused_and_its_target_kept(tmp_path):
    """kill -9 after a view, train/ moved to a user's folder and linked back: the rerun (which
    would render the missing views into train/) is refused, the user's folder unchanged."""
    folder = tmp_path / "ds"
    argv = GENERATE + ["--out", folder, "--workers", "1"]
    repro = f"nerfgauge {' '.join(map(str, argv))} & (kill -9 after 1 view; train/ -> a user's folder); rerun"
    process = subprocess.Popen(command(argv), cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               start_new_session=True)
    landed, survivors = kill_when(process, lambda: views_on_disk(folder / "train") >= 1)
    assert landed and not survivors, f"killed {landed}, survivors {survivors}\n  {repro}"
    before = plant_link(folder / "train", tmp_path / "user")
    rerun = subprocess.run(command(argv), cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert_refused_naming(rerun, folder / "train", repro)
    after = user_state(tmp_path / "user")
    assert after == before, f"the link's target changed: {snapshot_changes(before['stat'], after['stat'])}\n  {repro}"


def test_second_writer_is_refused_and_the_first_finishes(tmp_path):
    """Concurrent writers: while one generate holds the folder, the same command in this
    process exits 2 with one line naming the holder; the first then finishes, complete.
    The first is paused (SIGSTOP) while the second tries, so they surely meet."""
    from nerfgauge.core.dataset import verify_manifest

    folder = tmp_path / "ds"
    argv = ["generate", "primitives", "--res", "16", "--views", "12", "--val-views", "0", "--test-views", "1",
            "--spp", "4", "--quiet", "--out", folder]
    first = subprocess.Popen(command(argv), cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                             text=True)
    try:
        assert wait_for(lambda: views_on_disk(folder) >= 1, first), "the first writer ended before the test"
        first.send_signal(signal.SIGSTOP)  # paused mid-run, holding the folder: no race with its end
        try:
            second = run_cli(argv, tmp_path)
        finally:
            first.send_signal(signal.SIGCONT)
        lines = [line for line in second.stderr.splitlines() if line.strip()]
        assert second.escaped is None and second.code == 2 and len(lines) == 1 \
            and lines[0].startswith("nerfgauge generate: error: ") and str(first.pid) in lines[0], \
            f"second writer: exit {second.code}, escaped {second.escaped}, stderr {second.stderr[-400:]!r}"
        assert first.wait(timeout=600) == 0, first.stderr.read()[-600:]
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
        first.stderr.close()
    assert (folder / "manifest.json").is_file() and not verify_manifest(folder)


# --------------------------------------------------------------------------------------
# train


def train_argv(dataset, run) -> list:
    return ["train", dataset, "--out", run, "--steps", str(TRAIN_STEPS), "--checkpoint-every",
            str(CHECKPOINT_EVERY), "--threads", "1", "--seed", "3", "--quiet"]


def model_tensors(path: Path) -> dict:
    """{dotted key: value} of model.pt, tensors and plain values alike."""
    import torch

    flat = {}

    def walk(value, where):
        if isinstance(value, dict):
            for key, item in value.items():
                walk(item, f"{where}.{key}" if where else str(key))
        else:
            flat[where] = value

    walk(torch.load(path, map_location="cpu", weights_only=True), "")
    return flat


def differing_entries(got: dict, want: dict) -> list:
    import torch

    differ = sorted(set(got) ^ set(want))
    for key in sorted(set(got) & set(want)):
        a, b = got[key], want[key]
        same = (torch.equal(a, b) if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor)
                and a.dtype == b.dtype else a == b)
        if not same:
            differ.append(key)
    return differ


@pytest.fixture(scope="module")
def reference_model(tmp_path_factory, tiny_dataset):
    folder = tmp_path_factory.mktemp("kill-train")
    run_to_end(train_argv(tiny_dataset, folder / "run"), folder)
    return model_tensors(folder / "run" / "model.pt")


def checkpoint_identity(run: Path):
    try:
        info = os.stat(run / "checkpoint.pt")
    except FileNotFoundError:
        return None
    return info.st_ino, info.st_mtime_ns


def kill_train_and_resume(run: Path, dataset, writes_before_kill: int, delay: float, reference: dict) -> str:
    """Kill -9 `delay` seconds after the `writes_before_kill`-th checkpoint write (0: as soon as
    the run folder has its config), then --resume (or rerun plainly without a checkpoint)."""
    argv = train_argv(dataset, run)
    repro = (f"nerfgauge {' '.join(map(str, argv))} & (kill -9 {delay:.2f} s after checkpoint write "
             f"{writes_before_kill}); rerun with --resume")
    process = subprocess.Popen(command(argv), cwd=run.parent, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               start_new_session=True)
    seen = []

    def written_enough():
        identity = checkpoint_identity(run)
        if identity is not None and (not seen or seen[-1] != identity):
            seen.append(identity)
        return len(seen) >= writes_before_kill if writes_before_kill else (run / "config.json").is_file()

    landed, survivors = kill_when(process, written_enough, delay)
    assert not survivors, f"processes {survivors} outlived the killed training\n  {repro}"
    resume = (run / "checkpoint.pt").is_file()
    rerun = subprocess.run(command(argv + (["--resume"] if resume else [])), cwd=run.parent,
                           capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, f"rerun ({'--resume' if resume else 'plain'}) after kill: exit " \
                                  f"{rerun.returncode}: {rerun.stderr[-600:]}\n  {repro}"
    differ = differing_entries(model_tensors(run / "model.pt"), reference)
    assert not differ, f"model.pt after kill and resume differs from the uninterrupted run in {differ[:8]}\n  {repro}"
    return "killed" if landed else "finished before the kill"


@pytest.mark.slow
def test_train_killed_after_a_checkpoint_resumes_bit_identical(tmp_path, tiny_dataset, reference_model):
    rng = random.Random(1810)
    writes, delay = rng.randint(1, 2), rng.uniform(0.0, 0.2)
    how = kill_train_and_resume(tmp_path / "run", tiny_dataset, writes, delay, reference_model)
    assert how == "killed", f"the kill after checkpoint write {writes} came too late to test anything"


@pytest.mark.slow
def test_train_kill_matrix(tmp_path, tiny_dataset, reference_model):
    """Before the first checkpoint, and two more seeded moments between checkpoints."""
    rng = random.Random(1811)
    moments = [(0, 0.0)] + [(rng.randint(1, TRAIN_STEPS // CHECKPOINT_EVERY - 2), rng.uniform(0.0, 0.3))
                            for _ in range(2)]
    landed = [kill_train_and_resume(tmp_path / f"run-{i}", tiny_dataset, w, d, reference_model)
              for i, (w, d) in enumerate(moments)]
    assert landed.count("killed") >= len(moments) - 1, dict(zip(moments, landed))


@pytest.mark.slow
def test_train_killed_then_a_planted_link_is_refused_and_its_target_kept(tmp_path, tiny_dataset):
    """kill -9 after a checkpoint, log.jsonl moved to a user's folder and linked back: --resume
    (which would truncate and append to the log) is refused, the user's file unchanged."""
    run = tmp_path / "run"
    argv = train_argv(tiny_dataset, run)
    repro = f"nerfgauge {' '.join(map(str, argv))} & (kill -9 after checkpoint 1; log.jsonl -> a user's file); --resume"
    process = subprocess.Popen(command(argv), cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               start_new_session=True)
    landed, survivors = kill_when(process, lambda: checkpoint_identity(run) is not None)
    assert landed and not survivors, f"killed {landed}, survivors {survivors}\n  {repro}"
    before = plant_link(run / "log.jsonl", tmp_path / "user")
    rerun = subprocess.run(command(argv + ["--resume"]), cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert_refused_naming(rerun, run / "log.jsonl", repro)
    after = user_state(tmp_path / "user")
    assert after == before, f"the link's target changed: {snapshot_changes(before['stat'], after['stat'])}\n  {repro}"
