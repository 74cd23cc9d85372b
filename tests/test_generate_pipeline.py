"""The generator as a user runs it: format, determinism, resume, refusals, bad input."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from nerfgauge.cli import main
from nerfgauge.core import dataset
from nerfgauge.core.images import read_exr, read_png

SMALL = ["--views", "4", "--val-views", "1", "--test-views", "2", "--res", "24", "--spp", "4", "--quiet"]


def run_cli(*args):
    """The exit code of `nerfgauge generate ARGS`, argparse's refusals (SystemExit) included."""
    try:
        return main(["generate", *map(str, args)])
    except SystemExit as stop:
        return stop.code


def all_file_bytes(root):
    """Every file's bytes, but the lock file's (it names the PID that last held it)."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != ".nerfgauge.lock"}


def test_dataset_files_follow_the_design(tiny_dataset):
    root = tiny_dataset
    manifest = json.loads((root / "manifest.json").read_text())
    on_disk = {p.relative_to(root).as_posix() for p in root.rglob("*")
               if p.is_file() and not p.name.startswith(".")} - {"manifest.json"}  # marker and lock aside
    assert set(manifest["files"]) == on_disk
    assert dataset.verify_manifest(root) == []
    for split, count in (("train", 4), ("val", 1), ("test", 2)):
        meta = json.loads((root / f"transforms_{split}.json").read_text())
        assert len(meta["frames"]) == count
        frame = meta["frames"][0]
        assert not os.path.splitext(frame["file_path"])[1]  # extension-less, as NeRF-synthetic
        assert np.array(frame["transform_matrix"]).shape == (4, 4)
        assert meta["camera_angle_x"] == pytest.approx(np.radians(40.0))
    studio = json.loads((root / "transforms.json").read_text())
    assert {"fl_x", "fl_y", "cx", "cy", "w", "h"} <= set(studio)
    assert len(studio["frames"]) == 7 and len(studio["test_filenames"]) == 2
    for frame in studio["frames"]:
        for key in ("file_path", "depth_file_path", "mask_path"):
            assert (root / frame[key]).is_file()
    scene = json.loads((root / "scene.json").read_text())
    assert scene["recipe"] == "primitives" and scene["variant"].endswith("_rgb")
    assert scene["needs"]["view_dependent"] is False
    assert sorted(p.name for p in (root / "meshes").glob("*.ply")) == [
        "blue_box.ply", "checker_sphere.ply", "green_cylinder.ply", "red_sphere.ply"]
    rgba = read_png(root / "train/r_000.png")
    assert rgba.shape == (32, 32, 4)
    channels, header = read_exr(root / "train/r_000_distance.exr")
    assert header["nerfgauge_depth"] == "ray_distance" and list(channels) == ["Z"]
    _, header = read_exr(root / "train/r_000_zdepth.exr")
    assert header["nerfgauge_depth"] == "z_depth"
    mask = read_png(root / "train/r_000_mask.png") > 0.5
    np.testing.assert_array_equal(mask, channels["Z"] > 0)


def test_no_two_views_coincide(tiny_dataset):
    positions = np.concatenate([dataset.open_dataset(tiny_dataset).cameras(s).c2w[:, :3, 3] for s in dataset.SPLITS])
    gaps = np.linalg.norm(positions[:, None] - positions[None], axis=-1) + np.eye(len(positions)) * 1e9
    assert gaps.min() > 1e-3


def test_same_command_and_seed_give_identical_bytes(tmp_path):
    for name in ("a", "b"):
        assert run_cli("primitives", "--out", tmp_path / name, *SMALL) == 0
    assert all_file_bytes(tmp_path / "a") == all_file_bytes(tmp_path / "b")


def test_other_seed_changes_the_noise(tmp_path):
    for name, seed in (("a", 0), ("b", 1)):
        assert run_cli("primitives", "--out", tmp_path / name, "--seed", seed, *SMALL) == 0
    assert (tmp_path / "a/train/r_000.exr").read_bytes() != (tmp_path / "b/train/r_000.exr").read_bytes()


def test_resume_renders_only_missing_views_and_matches_a_clean_run(tmp_path, capsys):
    clean, resumed = tmp_path / "clean", tmp_path / "resumed"
    assert run_cli("primitives", "--out", clean, *SMALL) == 0
    assert run_cli("primitives", "--out", resumed, *SMALL) == 0
    # Simulate an interruption: two views lost, a half-written temp file, no manifest.
    for rel in ("train/r_002.png", "test/r_001_distance.exr", "manifest.json"):
        (resumed / rel).unlink()
    (resumed / "train/.r_002.png.tmp999").write_bytes(b"half")
    capsys.readouterr()
    assert run_cli("primitives", "--out", resumed, *SMALL) == 0
    assert "2 views rendered" in capsys.readouterr().out
    assert all_file_bytes(clean) == all_file_bytes(resumed)
    assert run_cli("primitives", "--out", resumed, *SMALL) == 0
    assert "nothing to render" in capsys.readouterr().out


@pytest.mark.slow
def test_resume_after_kill_9(tmp_path):
    out = tmp_path / "killed"
    args = [sys.executable, "-m", "nerfgauge.cli", "generate", "primitives", "--out", str(out),
            "--views", "30", "--val-views", "0", "--test-views", "0", "--res", "32", "--spp", "16", "--quiet"]
    process = subprocess.Popen(args)
    deadline = time.time() + 120
    while time.time() < deadline and len(list(out.glob("train/*.png"))) < 6:
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert not (out / "manifest.json").exists()  # not complete, and does not look complete
    with pytest.raises(Exception):
        dataset.open_dataset(out).root
    assert subprocess.run(args, capture_output=True, text=True).returncode == 0
    clean = tmp_path / "clean"
    assert subprocess.run(args[:6] + [str(clean)] + args[7:], capture_output=True).returncode == 0
    assert all_file_bytes(clean) == all_file_bytes(out)


def test_a_folder_of_another_recipe_is_refused_unless_overwrite(tmp_path, capsys):
    out = tmp_path / "ds"
    assert run_cli("primitives", "--out", out, *SMALL) == 0
    before = all_file_bytes(out)
    assert run_cli("primitives", "--out", out, "--seed", "3", *SMALL) == 2
    assert "another recipe" in capsys.readouterr().err
    assert all_file_bytes(out) == before
    assert run_cli("primitives", "--out", out, "--seed", "3", "--overwrite", *SMALL) == 0
    assert json.loads((out / "config.json").read_text())["config"]["seed"] == 3


def test_a_foreign_non_empty_folder_is_refused_even_with_overwrite(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    assert run_cli("primitives", "--out", tmp_path, "--overwrite", *SMALL) == 2
    assert "not made by nerfgauge" in capsys.readouterr().err
    assert [p.name for p in tmp_path.iterdir()] == ["notes.txt"]


BAD_INPUTS = {
    "unknown scene": (["nosuchscene"], "unknown scene"),
    "zero res": (["primitives", "--res", "0"], "--res"),
    "negative res": (["primitives", "--res", "-8"], "--res"),
    "garbage res": (["primitives", "--res", "12y9"], "--res"),
    "zero spp": (["primitives", "--spp", "0"], "--spp"),
    "zero views": (["primitives", "--views", "0"], "--views"),
    "negative test views": (["primitives", "--test-views", "-1"], "--test-views"),
    "fov 0": (["primitives", "--fov", "0"], "--fov"),
    "fov 180": (["primitives", "--fov", "180"], "--fov"),
    "radius inside aabb": (["primitives", "--radius", "0.5"], "inside the scene's AABB"),
    "zero workers": (["primitives", "--workers", "0"], "--workers"),
    "lightfield not square": (["primitives", "--layout", "lightfield", "--views", "10"], "square"),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys, case):
    args, expected = BAD_INPUTS[case]
    out = tmp_path / "out"
    smallest = ["--res", "8", "--spp", "1", "--quiet"]
    assert run_cli(args[0], "--out", out, *smallest, *args[1:]) == 2
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and expected in err.splitlines()[-1], err  # argparse adds a usage line
    assert not out.exists()


def test_output_path_that_is_a_file(tmp_path, capsys):
    target = tmp_path / "file.txt"
    target.write_text("x")
    assert run_cli("primitives", "--out", target, *SMALL) == 2
    assert "is not a folder" in capsys.readouterr().err
    assert target.read_text() == "x"


@pytest.mark.parametrize("content,expected", [(b"", "is empty"), (b"this is not a mesh\n", "")])
def test_bad_user_mesh(tmp_path, capsys, content, expected):
    mesh = tmp_path / "bad.obj"
    mesh.write_bytes(content)
    out = tmp_path / "out"
    assert run_cli(f"mesh:{mesh}", "--out", out, *SMALL) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(mesh) in err and expected in err
    assert not out.exists()


def test_missing_and_degenerate_user_mesh(tmp_path, capsys):
    assert run_cli(f"mesh:{tmp_path / 'none.ply'}", "--out", tmp_path / "o", *SMALL) == 2
    assert "not found" in capsys.readouterr().err
    flat = tmp_path / "flat.obj"
    flat.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")  # collinear: zero area
    assert run_cli(f"mesh:{flat}", "--out", tmp_path / "o", *SMALL) == 2
    err = capsys.readouterr().err
    assert "degenerate" in err or "no triangles" in err, err


@pytest.mark.slow
def test_worker_processes_give_the_same_bytes(tmp_path):
    """Each view's noise depends on (seed, split, index) only, so spreading views over
    processes changes nothing on disk."""
    assert run_cli("primitives", "--out", tmp_path / "one", *SMALL) == 0
    assert run_cli("primitives", "--out", tmp_path / "two", "--workers", "2", *SMALL) == 0
    assert all_file_bytes(tmp_path / "one") == all_file_bytes(tmp_path / "two")


@pytest.mark.parametrize("spp", [1, 2, 4, 8, 12, 16, 32, 35, 50, 64, 100, 128, 1000])
def test_the_sampler_draws_exactly_the_stated_sample_count(mi, spp):
    """scene.json states `spp`; Mitsuba's multijitter would round 32 up to 35."""
    from nerfgauge.generate.render import sampler_dict

    sampler = mi.load_dict(sampler_dict(spp))
    assert sampler.sample_count() == spp
