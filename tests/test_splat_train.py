"""Training, rendering and evaluating splatting runs end to end (slow: they generate a small
dataset with Mitsuba and train), and the commands' refusals (fast: they stop before any
dataset is read)."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from cli_errors import one_line_exit_2
from nerfgauge.splat.config import SplatConfig
from nerfgauge.splat.ply import read_ply

from nerfgauge.cli import main
from nerfgauge.core.errors import InputError


RUN_CONFIG = SplatConfig(steps=200, densify_every=50, eval_every_seconds=0.5)


@pytest.fixture(scope="module")
def splat_run(tiny_dataset, tmp_path_factory):
    """A 200-step run on the tiny primitives dataset (32 x 32, 4 train views, its 256 surface
    points): densification every 50 steps until step 100 (two), no opacity reset."""
    from nerfgauge.splat.train import train

    run = tmp_path_factory.mktemp("splat") / "run"
    summary = train(tiny_dataset, run, RUN_CONFIG, progress=False)
    return run, summary


@pytest.mark.slow
def test_a_run_writes_its_config_log_and_gaussians(splat_run, tiny_dataset):
    run, summary = splat_run
    config = json.loads((run / "config.json").read_text())
    assert config["model"] == "splat" and config["steps"] == 200 and config["recipe"]["dataset_sha256"]
    assert config["auto_reasons"]["init"].startswith("surface: the dataset's 256 points")
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert log[0]["step"] == 0 and log[-1]["step"] == 200 and len(log) >= 2
    assert log[-1]["val_psnr"] > log[0]["val_psnr"] + 3  # it learns (measured: 18.7 -> 23.5 dB)
    assert log[-1]["gaussians"] > 256  # and densifies
    gaussians = read_ply(run / "gaussians.ply")
    assert len(gaussians) == summary["gaussians"] and summary["steps"] == 200
    assert all(np.isfinite(getattr(gaussians, name)).all() for name in ("means", "log_scales", "quats", "sh"))


@pytest.mark.slow
def test_a_steps_run_is_reproducible(splat_run, tiny_dataset, tmp_path):
    from nerfgauge.splat.train import train

    run, _ = splat_run
    train(tiny_dataset, tmp_path / "again", dataclasses.replace(RUN_CONFIG, threads=1), progress=False)
    assert (tmp_path / "again" / "gaussians.ply").read_bytes() == (run / "gaussians.ply").read_bytes()


@pytest.mark.slow
def test_render_then_evaluate(splat_run, tiny_dataset, tmp_path, capsys):
    run, _ = splat_run
    assert main(["render", str(run), "--quiet"]) == 0
    timing = json.loads((run / "renders" / "timing.json").read_text())
    assert timing["model"] == "splat" and timing["frames"] == 2 and timing["dataset_files"]
    for stem in ("r_000", "r_001"):
        assert (run / "renders" / "test" / f"{stem}.png").is_file()
        assert (run / "renders" / "test" / f"{stem}_depth.exr").is_file()
    metrics = tmp_path / "metrics.json"
    assert main(["evaluate", str(tiny_dataset), "--pred", str(run / "renders"), "--out", str(metrics)]) == 0
    scores = json.loads(metrics.read_text())
    assert scores["mean"]["psnr"] > 15 and math.isfinite(scores["mean"]["depth_absrel"])
    assert scores["mean"]["depth_absrel"] < 0.2  # ray distance, as the ground truth holds it
    # the PLY alone renders with a dataset's cameras, the same frames
    assert main(["render", str(run / "gaussians.ply"), "--dataset", str(tiny_dataset), "--out",
                 str(tmp_path / "from_ply"), "--quiet"]) == 0
    for stem in ("r_000", "r_001"):
        ours = (run / "renders" / "test" / f"{stem}.png").read_bytes()
        assert (tmp_path / "from_ply" / "test" / f"{stem}.png").read_bytes() == ours


@pytest.mark.slow
def test_the_command_line_trains_and_refuses_a_second_run_into_the_same_folder(tiny_dataset, tmp_path, capsys):
    argv = ["train", str(tiny_dataset), "--model", "splat", "--steps", "5", "--out", str(tmp_path / "run"), "--quiet",
            "--init", "none", "--init-count", "300"]
    assert main(argv) == 0
    assert "5 steps" in capsys.readouterr().out
    one_line_exit_2(capsys, argv, "already holds this finished run")
    assert main(argv + ["--overwrite"]) == 0


@pytest.mark.slow
def test_init_of_points_the_dataset_lacks_is_refused(tiny_dataset, tmp_path, capsys):
    one_line_exit_2(capsys, ["train", str(tiny_dataset), "--model", "splat", "--steps", "5", "--out",
                             str(tmp_path / "run"), "--init", "random"], "holds surface points",
                    "nerfgauge export colmap")
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_nan_in_training_stops_with_exit_3(tiny_dataset, tmp_path, capsys, monkeypatch):
    """NaN from an upstream step (here: the initial Gaussians): one line, exit 3, no PLY."""
    import nerfgauge.splat.train as splat_train

    made = splat_train.initial_gaussians

    def poisoned(xyz, rgb):
        arrays = made(xyz, rgb)
        arrays.log_scales[7, 1] = math.nan
        return arrays

    monkeypatch.setattr(splat_train, "initial_gaussians", poisoned)
    code = main(["train", str(tiny_dataset), "--model", "splat", "--steps", "5", "--out", str(tmp_path / "run"),
                 "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 3 and len(err) == 1 and "diverged at step 0" in err[0], err
    assert not (tmp_path / "run" / "gaussians.ply").exists()


# --------------------------------------------------------------------------------------
# refusals before any dataset is read (fast)


@pytest.mark.parametrize("flags,expected", [
    (["--sh-degree", "4"], "--sh-degree"),
    (["--sh-degree", "x"], "--sh-degree"),
    (["--init", "mesh"], "--init"),
    (["--init-count", "0"], "--init-count"),
    (["--densify-until", "1.5"], "--densify-until"),
    (["--densify-grad", "-1"], "--densify-grad"),
    (["--densify-grad", "nan"], "--densify-grad"),
    (["--max-gaussians", "0"], "--max-gaussians"),
    (["--background", "grey"], "--background"),
])
def test_bad_splat_flags_are_one_line_exit_2(capsys, tmp_path, flags, expected):
    one_line_exit_2(capsys, ["train", str(tmp_path / "no-dataset"), "--model", "splat", "--out", str(tmp_path / "r"),
                             *flags], expected)


@pytest.mark.parametrize("flags,expected", [
    (["--model", "splat", "--resolution", "64"], "--resolution is not a splatting flag"),
    (["--model", "splat", "--resume"], "--resume is not a splatting flag"),
    (["--model", "splat", "--pixel-filter", "box"], "--pixel-filter is not a splatting flag"),
    (["--model", "compact", "--init", "none"], "--init is a --model splat flag"),
    (["--sh-degree", "1"], "--sh-degree is a --model splat flag"),
])
def test_flags_of_the_other_model_are_refused(capsys, tmp_path, flags, expected):
    one_line_exit_2(capsys, ["train", str(tmp_path / "no-dataset"), "--out", str(tmp_path / "r"), *flags], expected)
    assert not (tmp_path / "r").exists()


def test_render_flags_a_splatting_run_does_not_take_are_refused(capsys, tmp_path):
    ply = tmp_path / "g.ply"
    ply.write_bytes(b"ply\n")
    one_line_exit_2(capsys, ["render", str(ply), "--step-ratio", "1"], "--step-ratio is not a splatting flag")


def test_a_ply_needs_a_dataset_and_an_out_folder(capsys, tmp_path):
    ply = tmp_path / "g.ply"
    ply.write_bytes(b"ply\n")
    one_line_exit_2(capsys, ["render", str(ply)], "give the dataset")


@pytest.mark.parametrize("fields,expected", [
    ({}, "exactly one of --steps"),
    ({"steps": 10, "budget_seconds": 5.0}, "exactly one of --steps"),
    ({"steps": 0}, "--steps"),
    ({"steps": 10, "init": "mesh"}, "--init"),
    ({"steps": 10, "lr_position": -1.0}, "--lr-position"),
    ({"steps": 10, "densify_from": 0.9}, "densify_from"),
    ({"steps": 10, "sh_degree": 1.5}, "--sh-degree"),
    ({"steps": 10, "device": "tpu"}, "unknown device"),
])
def test_config_validation_through_the_api(fields, expected):
    with pytest.raises(InputError, match=expected) as error:
        SplatConfig(dataset="d", **fields).validate()
    assert "\n" not in str(error.value)


@pytest.mark.slow
def test_init_random_takes_the_datasets_random_export(tiny_dataset, tmp_path, capsys):
    """`--init random` starts from the dataset's own random-point export (generate.export),
    not from points of its own: the run's config says how many it read."""
    import shutil

    copy = tmp_path / "dataset"
    shutil.copytree(tiny_dataset, copy)
    assert main(["export", "colmap", str(copy), "--points", "random:200"]) == 0
    capsys.readouterr()
    assert main(["train", str(copy), "--model", "splat", "--steps", "3", "--init", "random", "--out",
                 str(tmp_path / "run"), "--quiet"]) == 0
    reasons = json.loads((tmp_path / "run" / "config.json").read_text())["auto_reasons"]
    # all 200: fewer than the default count, one per 4 pixels of a 32 x 32 view (256)
    assert reasons["init"] == ("random: the dataset's 200 points (sparse/0/points3D.txt; at most 256: one per 4 "
                               "pixels of a 32 x 32 view)")
    assert main(["train", str(copy), "--model", "splat", "--steps", "3", "--init", "random", "--init-count", "150",
                 "--out", str(tmp_path / "run150"), "--quiet"]) == 0
    reasons = json.loads((tmp_path / "run150" / "config.json").read_text())["auto_reasons"]
    assert reasons["init"].startswith("random: 150 of the dataset's 200 points")


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["thin", "far-object"])
def test_thin_and_far_scenes_train_without_diverging(scene, make_dataset, tmp_path):
    """60 steps on thin cylinders (Gaussians a fraction of a pixel across) and a small object far from
    cameras spread wide (position rate and densification scaled by the cameras' extent, not
    the object's): every logged loss and val PSNR finite, val PSNR ends above where it
    started, the PLY finite."""
    from nerfgauge.splat.train import train

    data = make_dataset(tmp_path / scene, scene=scene)
    summary = train(data, tmp_path / "run", SplatConfig(steps=60, eval_every_seconds=0.5), progress=False)
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert summary["steps"] == 60 and log[-1]["step"] == 60
    assert all(math.isfinite(entry["val_psnr"]) for entry in log)
    assert all(math.isfinite(entry["loss"]) for entry in log if entry["loss"] is not None)
    assert log[-1]["val_psnr"] > log[0]["val_psnr"]  # it learns, not drifts away (measured: thin +3.2, far-object +0.7 dB)
    gaussians = read_ply(tmp_path / "run" / "gaussians.ply")
    assert all(np.isfinite(getattr(gaussians, name)).all() for name in ("means", "log_scales", "quats", "sh", "opacity_logits"))
