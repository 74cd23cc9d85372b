"""A run is tied to the dataset it was trained on (issue 31, deliver 2).

A run records the sha256 of its dataset's manifest.json (config.json's recipe, whose hash
the run's marker holds); every command that reads a run with a dataset (render, render
--dataset, mesh, geometry --run) refuse a dataset with another manifest: exit 2, one line
naming both hashes (12 hex digits) and both paths, nothing changed; `evaluate` refuses a
run's renders against a dataset with other cameras or another scene. Changing a dataset
here means rewriting its manifest.json with another indent: the same frames, another hash,
as far as a hash knows another dataset (fast); the slow test regenerates the folder as
another scene, as the issue found it.
"""

from __future__ import annotations

import hashlib
import json
import shutil

import pytest
from cli_errors import one_line_exit_2
from test_cli_reliability import snapshot

from nerfgauge.cli import main
from nerfgauge.core.folders import MARKER


def sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def reindent_manifest(root) -> None:
    """Another manifest.json (same entries, another indent): another dataset by content."""
    manifest = json.loads((root / "manifest.json").read_text())
    (root / "manifest.json").write_text(json.dumps(manifest, indent=4))


@pytest.fixture(scope="module")
def trained(tiny_dataset, tmp_path_factory):
    """A copy of the tiny dataset, a 2-step run on it and that run's test renders."""
    base = tmp_path_factory.mktemp("bound")
    data = base / "data"
    shutil.copytree(tiny_dataset, data)
    run = base / "run"
    assert main(["train", str(data), "--out", str(run), "--steps", "2", "--quiet"]) == 0
    assert main(["render", str(run), "--quiet"]) == 0
    return data, run


@pytest.fixture
def changed(trained):
    """The run's dataset with another manifest for the test, restored afterwards."""
    data, run = trained
    original = (data / "manifest.json").read_bytes()
    recorded = sha(data / "manifest.json")
    reindent_manifest(data)
    yield data, run, recorded, sha(data / "manifest.json")
    (data / "manifest.json").write_bytes(original)


def test_the_run_records_the_hash_resume_compares(trained):
    data, run = trained
    recipe = json.loads((run / "config.json").read_text())["recipe"]
    assert recipe["dataset_sha256"] == sha(data / "manifest.json")
    timing = json.loads((run / "renders" / "timing.json").read_text())
    assert timing["dataset"] == str(data)
    assert timing["dataset_files"] == {name: sha(data / name) for name in ("transforms_test.json", "scene.json")}


@pytest.mark.parametrize("command", ["render", "render --dataset", "mesh", "geometry --run"])
def test_every_reader_of_a_run_refuses_a_changed_dataset(changed, tmp_path, capsys, command):
    data, run, recorded, now = changed
    before_run, before_data = snapshot(run), snapshot(data)
    argv = {"render": ["render", run, "--out", tmp_path / "r", "--quiet"],
            "render --dataset": ["render", run, "--dataset", data, "--out", tmp_path / "r", "--quiet"],
            "mesh": ["mesh", run, "-o", tmp_path / "m.ply", "--resolution", "16"],
            "geometry --run": ["geometry", data, "--pred-depth", run / "renders", "--run", run,
                               "-o", tmp_path / "g.json", "--samples", "1000"]}[command]
    one_line_exit_2(capsys, argv, recorded[:12], now[:12], str(data / "manifest.json"), f"({data})", str(run))
    assert snapshot(run) == before_run and snapshot(data) == before_data
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no output made


def test_the_same_dataset_moved_renders_and_other_scenes_need_the_flag(trained, tmp_path, capsys):
    data, run = trained
    moved = tmp_path / "moved"
    shutil.copytree(data, moved)  # the same manifest at another path
    assert main(["render", str(run), "--dataset", str(moved), "--out", str(tmp_path / "r"), "--quiet"]) == 0
    timing = json.loads((tmp_path / "r" / "timing.json").read_text())
    assert timing["dataset"] == str(moved) and timing["dataset_files"]["scene.json"] == sha(data / "scene.json")
    reindent_manifest(moved)  # another dataset of the same scene
    one_line_exit_2(capsys, ["render", run, "--dataset", moved, "--out", tmp_path / "r2"], "--other-dataset",
                    sha(moved / "manifest.json")[:12])
    assert main(["render", str(run), "--dataset", str(moved), "--other-dataset", "--out", str(tmp_path / "r2"),
                 "--quiet"]) == 0
    scene = json.loads((moved / "scene.json").read_text())
    scene["seed"] += 1  # another scene: refused even with the flag
    (moved / "scene.json").write_text(json.dumps(scene))
    from nerfgauge.core.dataset import read_manifest, write_manifest

    write_manifest(moved, read_manifest(moved).keys())
    one_line_exit_2(capsys, ["render", run, "--dataset", moved, "--other-dataset", "--out", tmp_path / "r3"],
                    "shows scene")
    one_line_exit_2(capsys, ["render", run, "--other-dataset", "--out", tmp_path / "r4"], "--other-dataset goes with")
    assert not (tmp_path / "r3").exists() and not (tmp_path / "r4").exists()


def moved_camera(transforms: dict) -> dict:
    """The first frame's camera half a unit along its x axis."""
    transforms["frames"][0]["transform_matrix"][0][3] += 0.5
    return transforms


def test_evaluate_refuses_renders_of_other_cameras_or_another_scene(trained, tmp_path, capsys):
    """timing.json of a run's renders names the sha256 of the transforms and scene.json they
    show: evaluate scores them against a dataset with those (another manifest is fine:
    ground truth rendered again shows the same cameras), not against other ones."""
    from nerfgauge.core.dataset import read_manifest, write_manifest

    data, run = trained
    copy = tmp_path / "copy"
    shutil.copytree(data, copy)
    reindent_manifest(copy)
    assert main(["evaluate", str(copy), "--pred", str(run / "renders"), "--out", str(tmp_path / "ok.json")]) == 0
    before = snapshot(tmp_path)
    for name, edit in (("scene.json", lambda doc: doc | {"seed": doc["seed"] + 1}),
                       ("transforms_test.json", moved_camera)):
        original = (copy / name).read_bytes()
        (copy / name).write_text(json.dumps(edit(json.loads(original))))
        write_manifest(copy, read_manifest(copy).keys())
        edited = snapshot(tmp_path)
        line = one_line_exit_2(capsys, ["evaluate", copy, "--pred", run / "renders", "--out", tmp_path / "m.json"],
                               name, sha(data / name)[:12], sha(copy / name)[:12], str(copy / name), str(data))
        assert str(run / "renders") in line and snapshot(tmp_path) == edited
        (copy / name).write_bytes(original)
        write_manifest(copy, read_manifest(copy).keys())
    assert snapshot(tmp_path).keys() == before.keys()


def test_other_dataset_still_needs_the_runs_own_dataset_unchanged(changed, tmp_path, capsys):
    data, run, recorded, now = changed
    copy = tmp_path / "copy"
    shutil.copytree(data, copy)
    one_line_exit_2(capsys, ["render", run, "--dataset", copy, "--other-dataset", "--out", tmp_path / "r"],
                    recorded[:12], now[:12], "cannot be checked")


def test_a_run_without_a_record_is_rendered_with_one_warning(trained, tmp_path, capsys):
    """Runs made before the record (no marker, no recipe): accepted, and stderr says why
    the dataset could not be checked."""
    _, finished = trained
    run = tmp_path / "old-run"
    shutil.copytree(finished, run, ignore=shutil.ignore_patterns("renders", ".nerfgauge.*"))
    config = json.loads((run / "config.json").read_text())
    del config["recipe"]
    (run / "config.json").write_text(json.dumps(config))
    capsys.readouterr()
    assert main(["render", str(run), "--out", str(tmp_path / "r"), "--quiet"]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "before nerfgauge recorded" in warnings[0] and "train again" in warnings[0]


def test_an_edited_record_is_refused(trained, tmp_path, capsys):
    """The marker holds the recipe's hash: a config.json whose recipe was edited (to point
    at another dataset) or removed no longer matches it."""
    data, finished = trained
    run = tmp_path / "run"
    shutil.copytree(finished, run, ignore=shutil.ignore_patterns("renders"))
    config = json.loads((run / "config.json").read_text())
    config["recipe"]["dataset_sha256"] = "0" * 64
    (run / "config.json").write_text(json.dumps(config))
    one_line_exit_2(capsys, ["render", run, "--out", tmp_path / "r"], "does not hold the recipe", MARKER)
    del config["recipe"]
    (run / "config.json").write_text(json.dumps(config))
    one_line_exit_2(capsys, ["mesh", run, "-o", tmp_path / "m.ply"], "does not hold the recipe")
    assert not (tmp_path / "r").exists() and not (tmp_path / "m.ply").exists()


@pytest.mark.slow
def test_a_dataset_folder_regenerated_as_another_scene_is_refused(tmp_path, capsys):
    """The issue's example: train, regenerate the dataset folder as another scene, render."""
    data, run = tmp_path / "data", tmp_path / "run"
    small = ["--res", "16", "--views", "4", "--test-views", "1", "--val-views", "1", "--spp", "4", "--quiet"]
    assert main(["generate", "primitives", "--out", str(data), *small]) == 0
    assert main(["train", str(data), "--out", str(run), "--steps", "5", "--quiet"]) == 0
    assert main(["render", str(run), "--quiet"]) == 0
    recorded = sha(data / "manifest.json")
    assert main(["generate", "tiny", "--out", str(data), "--overwrite", *small]) == 0
    now = sha(data / "manifest.json")
    assert now != recorded
    before = snapshot(run)
    line = one_line_exit_2(capsys, ["render", run, "--quiet"], recorded[:12], now[:12], str(run),
                           str(data / "manifest.json"))
    assert "changed since training" in line
    one_line_exit_2(capsys, ["render", run, "--dataset", data, "--quiet"], recorded[:12], now[:12])
    # the renders made before: evaluate scored them against the new scene's truth (69.96 dB)
    one_line_exit_2(capsys, ["evaluate", data, "--pred", run / "renders", "--out", tmp_path / "m.json"],
                    "scene.json", "another scene")
    assert snapshot(run) == before and not (tmp_path / "m.json").exists()
