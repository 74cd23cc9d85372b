"""`nerfgauge generate` loses nothing, never resumes a stale dataset, and leaves no orphan
workers (RELIABILITY.md). Each defect as it was reported, shown fixed."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from nerfgauge.cli import main
from nerfgauge.core import dataset, folders

TINY = ["--views", "2", "--val-views", "0", "--test-views", "1", "--res", "16", "--spp", "2", "--quiet"]


def run_cli(*args) -> int:
    """The exit code of `nerfgauge generate ARGS`, argparse's refusals included."""
    try:
        return main(["generate", *map(str, args)])
    except SystemExit as stop:
        return stop.code


def tree(root: Path) -> dict:
    """{relative path: bytes} of every file, the lock file aside (it names its last holder's PID)."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != folders.LOCK}


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err, err
    return err.splitlines()[-1]


# --- nothing lost ---------------------------------------------------------------------


def test_a_user_folder_with_config_json_survives_overwrite_untouched(tmp_path, capsys):
    """The reported data loss: any folder holding config.json was taken for a dataset and
    --overwrite (which the error suggested) deleted it."""
    project = tmp_path / "P"
    (project / "src").mkdir(parents=True)
    (project / "config.json").write_text('{"name": "my app"}')
    (project / "src" / "keep").write_text("precious")
    before = sorted(p.relative_to(project).as_posix() for p in project.rglob("*"))
    assert run_cli("primitives", "--out", project, "--overwrite", *TINY) == 2
    assert "not made by nerfgauge" in one_line_error(capsys)
    assert sorted(p.relative_to(project).as_posix() for p in project.rglob("*")) == before  # no file added
    assert (project / "src" / "keep").read_text() == "precious"
    assert (project / "config.json").read_text() == '{"name": "my app"}'


def test_a_folder_in_use_is_refused_naming_the_holder(tmp_path, capsys):
    """One writer per folder: a second generate exits 2 naming the first one's PID and
    writes nothing (here the holder is this test process)."""
    out = tmp_path / "ds"
    with folders.folder_lock(out):
        assert run_cli("primitives", "--out", out, *TINY) == 2
        assert f"in use by another nerfgauge process (PID {os.getpid()})" in one_line_error(capsys)
        assert [p.name for p in out.iterdir()] == [folders.LOCK]


@pytest.mark.slow
def test_concurrent_runs_on_one_folder_never_crash_and_leave_a_complete_dataset(tmp_path):
    """Six generates on one folder at once: each either holds the folder or exits 2 naming
    the holder; none crashes or deletes another's temporary files, and the dataset ends
    complete and identical to one made alone."""
    out, alone = tmp_path / "shared", tmp_path / "alone"
    args = ["primitives", *TINY[:-1], "--views", "6", "--quiet"]
    command = [sys.executable, "-m", "nerfgauge.cli", "generate", *args, "--out"]
    runs = [subprocess.Popen(command + [str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            for _ in range(6)]
    results = [(run.wait(timeout=300), run.stderr.read()) for run in runs]
    for run in runs:
        run.stdout.close()
        run.stderr.close()
    for code, err in results:
        assert "Traceback" not in err, err
        # A refusal is one line naming the holder, also while the holder is still writing its
        # marker (the lock and the marker's temporary do not make the folder look foreign).
        assert code == 0 or (code == 2 and len(err.strip().splitlines()) == 1
                             and err.startswith("nerfgauge generate: error: ")
                             and "in use by another nerfgauge process (PID" in err), (code, err)
    assert any(code == 0 for code, _ in results)
    assert subprocess.run(command + [str(out)], capture_output=True).returncode == 0  # finishes what a refusal left
    assert run_cli(*args, "--out", alone) == 0
    assert dataset.verify_manifest(out) == []
    assert tree(out) == tree(alone)


# --- nothing stale --------------------------------------------------------------------


def write_tent(path: Path, apex) -> Path:
    """A square pyramid over [-1, 1]^2 x [0, 1] whose apex may move without changing the
    bounding box (an in-place edit that a bounding-box check cannot see)."""
    vertices = [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0), apex]
    faces = [(1, 3, 2), (1, 4, 3), (1, 2, 5), (2, 3, 5), (3, 4, 5), (4, 1, 5)]
    path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in vertices) + "".join(f"f {a} {b} {c}\n" for a, b, c in faces))
    return path


def test_an_edited_user_mesh_is_refused_then_rerendered_with_overwrite(tmp_path, capsys):
    mesh = write_tent(tmp_path / "tent.obj", (0, 0, 1))
    out = tmp_path / "ds"
    assert run_cli(f"mesh:{mesh}", "--out", out, *TINY) == 0
    recorded = json.loads((out / "config.json").read_text())["inputs"]
    assert recorded == {str(mesh): hashlib.sha256(mesh.read_bytes()).hexdigest()}
    assert json.loads((out / "scene.json").read_text())["inputs"] == recorded
    old = tree(out)

    write_tent(mesh, (0.9, 0.9, 1))  # same bounding box, another shape
    capsys.readouterr()
    assert run_cli(f"mesh:{mesh}", "--out", out, *TINY) == 2
    err = one_line_error(capsys)
    assert f"{out} was made from another version of tent.obj" in err and "--overwrite" in err, err
    assert tree(out) == old  # refused untouched, and never reported complete

    assert run_cli(f"mesh:{mesh}", "--out", out, *TINY, "--overwrite") == 0
    new = tree(out)
    assert new["meshes/user_mesh.ply"] != old["meshes/user_mesh.ply"]
    assert new["train/r_000.exr"] != old["train/r_000.exr"]
    assert json.loads(new["config.json"])["inputs"] == {str(mesh): hashlib.sha256(mesh.read_bytes()).hexdigest()}
    assert dataset.verify_manifest(out) == []
    manifest = json.loads(new["manifest.json"])["files"]
    assert set(manifest) == set(new) - {"manifest.json", folders.MARKER}
    capsys.readouterr()
    assert run_cli(f"mesh:{mesh}", "--out", out, *TINY) == 0  # the same inputs resume: nothing to do
    assert "nothing to render" in capsys.readouterr().out


def test_another_renderer_version_is_refused(tmp_path, capsys, monkeypatch):
    from nerfgauge.generate import pipeline

    out = tmp_path / "ds"
    assert run_cli("primitives", "--out", out, *TINY) == 0
    installed = pipeline.renderer_versions()
    assert set(installed) == {"mitsuba", "drjit", "nerfgauge"}
    before = tree(out)
    monkeypatch.setattr(pipeline, "renderer_versions", lambda: {**installed, "mitsuba": "0.0.1"})
    capsys.readouterr()
    assert run_cli("primitives", "--out", out, *TINY) == 2
    err = one_line_error(capsys)
    assert f"mitsuba {installed['mitsuba']} (this is mitsuba 0.0.1)" in err and "--overwrite" in err, err
    assert tree(out) == before


# --- bad input: one line, exit 2, nothing written -------------------------------------


@pytest.mark.parametrize("flag,value", [
    ("--fov", "nan"), ("--fov", "inf"), ("--radius", "inf"), ("--radius", "nan"), ("--radius", "-1"),
    ("--elevation", "nan,10"), ("--elevation", "10,inf"), ("--spp", "nan"), ("--views", "1e3"),
    ("--seed", "-1"), ("--workers", "0"), ("--max-depth", "0"), ("--val-views", "-1"), ("--out", ""),
])
def test_non_finite_and_out_of_range_flags_are_refused(tmp_path, capsys, flag, value):
    out = tmp_path / "out"
    args = ["primitives", "--out", out, *TINY]
    args = args[:1] + [flag, value] + (args[3:] if flag == "--out" else args[1:])
    assert run_cli(*args) == 2
    err = one_line_error(capsys)
    assert flag in err or "elevation" in err, err
    assert not out.exists() and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".glb", ".stl", ".off"])
def test_random_bytes_as_a_mesh_are_one_line_naming_the_file(tmp_path, capsys, monkeypatch, suffix):
    """The reported "No module named 'charset_normalizer'": trimesh reaches for optional
    parsers on text that is not UTF-8; without them the file is still just not a mesh."""
    monkeypatch.setitem(sys.modules, "charset_normalizer", None)  # as where it is not installed
    mesh = tmp_path / f"noise{suffix}"
    mesh.write_bytes(np.random.default_rng(0).bytes(4096))
    assert run_cli(f"mesh:{mesh}", "--out", tmp_path / "out", *TINY) == 2
    err = one_line_error(capsys)
    assert str(mesh) in err and "No module named" not in err, err
    assert not (tmp_path / "out").exists()


def test_an_empty_mesh_is_one_line_naming_the_file(tmp_path, capsys):
    mesh = tmp_path / "empty.stl"
    mesh.write_bytes(b"")
    assert run_cli(f"mesh:{mesh}", "--out", tmp_path / "out", *TINY) == 2
    assert f"mesh {mesh} is empty" in one_line_error(capsys)


def test_gltf_buffers_count_as_inputs(tmp_path):
    """A .gltf's geometry lives in the .bin files it names: editing one is an input change."""
    import trimesh

    from nerfgauge.scenes import make_scene
    from nerfgauge.scenes.registry import scene_inputs

    trimesh.creation.box().export(tmp_path / "box.gltf")
    inputs = scene_inputs(make_scene(f"mesh:{tmp_path / 'box.gltf'}", 0))
    buffers = sorted(tmp_path.glob("*.bin"))
    assert buffers and set(inputs) == {str(tmp_path / "box.gltf")} | {str(p) for p in buffers}
    for path, digest in inputs.items():
        assert digest == hashlib.sha256(Path(path).read_bytes()).hexdigest()


# --- no orphan workers ----------------------------------------------------------------


def alive(pid: int) -> bool:
    """True while `pid` runs (a zombie waiting for an init that does not reap counts as dead)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return False
    return stat[stat.rindex(")") + 2] not in "ZX"


def children(pid: int) -> set:
    """PIDs of `pid`'s child processes (Linux /proc)."""
    found = set()
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found.update(int(c) for c in (task / "children").read_text().split())
        except FileNotFoundError:
            pass
    return found


def wait_until_gone(pids, seconds: float) -> set:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and any(alive(pid) for pid in pids):
        time.sleep(0.1)
    return {pid for pid in pids if alive(pid)}


GRANDCHILD = """
import sys, time
if sys.argv[2] == "portable":
    sys.platform = "portable"  # no prctl: only the parent-PID watch is left
from nerfgauge.generate.workers import die_with_parent
die_with_parent(int(sys.argv[1]))
print("ready", flush=True)
time.sleep(120)
"""
PARENT = """
import os, subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c", sys.argv[1], str(os.getpid()), sys.argv[2]])
print(child.pid, flush=True)
time.sleep(120)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("mode", ["linux", "portable"])
def test_a_worker_dies_with_its_parent(mode):
    """die_with_parent, both ways: the kernel's parent-death signal and the portable watch."""
    parent = subprocess.Popen([sys.executable, "-c", PARENT, GRANDCHILD, mode], stdout=subprocess.PIPE, text=True)
    worker = None
    try:
        worker = int(parent.stdout.readline())
        assert parent.stdout.readline().strip() == "ready"
        assert alive(worker)
        parent.kill()
        parent.wait()
        assert wait_until_gone([worker], 5.0) == set()
    finally:
        parent.stdout.close()
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        if worker is not None and alive(worker):
            os.kill(worker, signal.SIGKILL)


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_kill_9_with_two_workers_leaves_no_orphans_and_resumes_byte_identical(tmp_path):
    out, clean = tmp_path / "killed", tmp_path / "clean"
    args = ["primitives", "--views", "40", "--val-views", "0", "--test-views", "2", "--res", "32", "--spp", "16",
            "--workers", "2", "--quiet"]
    command = [sys.executable, "-m", "nerfgauge.cli", "generate", *args, "--out"]
    process = subprocess.Popen(command + [str(out)])
    workers = set()
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and len(list(out.glob("train/*.png"))) < 4:
            workers |= children(process.pid)
            time.sleep(0.05)
        workers |= children(process.pid)
        assert len(list(out.glob("train/*.png"))) >= 4, "the workers never rendered"
        assert len(workers) >= 2
        process.send_signal(signal.SIGKILL)
        process.wait()
        assert wait_until_gone(workers, 10.0) == set()
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        for pid in workers:
            if alive(pid):
                os.kill(pid, signal.SIGKILL)
    assert not (out / "manifest.json").exists()
    assert subprocess.run(command + [str(out)], capture_output=True).returncode == 0
    assert run_cli(*args[:-3], "--quiet", "--out", clean) == 0  # one process: the bytes do not depend on workers
    assert dataset.verify_manifest(out) == []
    assert tree(out) == tree(clean)


def test_a_scene_target_centres_the_orbit_inside_its_world():
    """A scene hint's target centres an orbit that stands inside the AABB on purpose (the
    far-reaching scene); without a target, cameras inside the AABB are still refused."""
    from nerfgauge.core.errors import InputError
    from nerfgauge.generate.layouts import LayoutSpec, camera_poses

    aabb = np.array([[-100.0, -100.0, -1.0], [100.0, 100.0, 30.0]])
    target = np.array([0.0, 0.0, 0.35])
    spec = LayoutSpec("orbit", (6, 0, 2), 3.2, (12.0, 12.0), target=tuple(target))
    poses = np.concatenate([p for p in camera_poses(spec, aabb, np.random.default_rng(0)).values() if len(p)])
    eyes = poses[:, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(eyes - target, axis=1), 3.2, rtol=1e-12)
    forward = -poses[:, :3, 2]  # OpenGL cameras look along -Z
    towards = (target - eyes) / np.linalg.norm(target - eyes, axis=1, keepdims=True)
    np.testing.assert_allclose(np.sum(forward * towards, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.degrees(np.arcsin((eyes[:, 2] - target[2]) / 3.2)), 12.0, atol=1e-9)
    with pytest.raises(InputError, match="inside the scene's AABB"):
        camera_poses(LayoutSpec("orbit", (6, 0, 2), 3.2, (12.0, 12.0)), aabb, np.random.default_rng(0))
