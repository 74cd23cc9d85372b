"""Benchmark suites (nerfgauge/orchestrate/suite/definition.py, suite/run.py, suite/report.py): definitions, the suite
folder and its manifest, results tied to a suite version, and the leaderboard's numbers."""

from __future__ import annotations

import hashlib
import json
import os
import shutil

import pytest
from suite_toml import suite_toml

from nerfgauge.cli import main
from nerfgauge.core.files import read_json, write_json
from nerfgauge.orchestrate.suite.definition import SUITE_MANIFEST, load_suite

TINY_DATASET = {"width": 16, "height": 16, "views": 4, "val_views": 0, "test_views": 2, "spp": 2}


def tiny(version: int = 1, steps: int = 10) -> str:
    """Two 16x16 datasets, 10 steps of our NeRF, the nearest baseline."""
    return suite_toml("tiny", TINY_DATASET, {"steps": steps}, version=version, description="two 16x16 datasets")


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def one_line_error(code, err, *words):
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1, err
    for word in words:
        assert word in err, err


@pytest.fixture(scope="module")
def tiny_toml(tmp_path_factory):
    path = tmp_path_factory.mktemp("suites") / "tiny.toml"
    path.write_text(tiny())
    return path


@pytest.fixture(scope="module")
def suite_dir(tiny_toml, tmp_path_factory):
    out = tmp_path_factory.mktemp("suite") / "tiny"
    assert main(["suite", "generate", str(tiny_toml), "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def gt_predictions(suite_dir, tmp_path_factory):
    """Another tool's renders: each dataset's test PNGs with a stripe painted in, as plain
    folders named in their own way (matched by order)."""
    import numpy as np

    from nerfgauge.core.images import read_png, write_png

    root = tmp_path_factory.mktemp("preds") / "other-tool"
    for entry_id in ("primitives", "random-3"):
        folder = root / entry_id
        folder.mkdir(parents=True)
        for k, png in enumerate(sorted((suite_dir / "datasets" / entry_id / "test").glob("r_???.png"))):
            image = np.round(read_png(png) * 255).astype(np.uint8)
            image[3 + k: 6 + k, :, :3] = 200
            image[3 + k: 6 + k, :, 3] = 255
            write_png(folder / f"view{k}.png", image)
    return root


def test_builtin_suites_list_and_standard_covers_every_scene(capsys):
    from nerfgauge.scenes import CHECK_SCENES, HARD_SCENES
    from nerfgauge.scenes.registry import RECIPES

    code, out, _ = run(capsys, "suite", "list")
    assert code == 0 and "smoke" in out and "standard" in out
    standard = load_suite("standard")
    assert {entry.scene for entry in standard.scenes} == set(RECIPES) - set(CHECK_SCENES) and set(HARD_SCENES) < set(RECIPES)
    smoke = load_suite("smoke")
    assert smoke.version >= 1 and len(smoke.scenes) <= 3
    assert all(entry.dataset["width"] <= 32 for entry in smoke.scenes)


@pytest.mark.parametrize("edit, words", [
    (lambda t: t.replace('name = "tiny"\n', ""), ("missing field name",)),
    (lambda t: t.replace("version = 1\n", ""), ("missing field version",)),
    (lambda t: t.replace("width = 16\n", ""), ("missing field dataset.width",)),
    (lambda t: t.replace("[train]\nsteps = 10\n", ""), ("missing field [train]",)),
    (lambda t: t.replace('id = "random-3"\nscene = "random"\nseed = 3', 'scene = "random"'), ("missing field seed",)),
    (lambda t: t.replace('scene = "random"', 'scene = "teapot"'), ("unknown scene 'teapot'",)),
    (lambda t: t.replace("spp = 2", "spp = 2\nsamples = 3"), ("unknown field 'samples'",)),
    (lambda t: t.replace('id = "random-3"', 'id = "primitives"'), ("used twice",)),
    (lambda t: t.replace("version = 1", 'version = "1"'), ("version must be a positive integer",)),
    (lambda t: t.replace("spp = 2", "spp = 0"), ("--spp must be a positive integer",)),
    (lambda t: t.replace('method = "nearest"', 'method = "nerf-w"'), ("methods[1]", "unknown method 'nerf-w'")),
    (lambda t: t + "\n[[scenes", ("not valid TOML",)),
])
def test_bad_suite_files_are_refused_before_anything_is_written(tmp_path, capsys, edit, words):
    bad = tmp_path / "bad.toml"
    bad.write_text(edit(tiny()))
    code, _, err = run(capsys, "suite", "generate", bad, "--out", tmp_path / "out")
    one_line_error(code, err, str(bad), *words)
    assert not (tmp_path / "out").exists()


def test_unknown_suite_is_one_line(tmp_path, capsys):
    code, _, err = run(capsys, "suite", "generate", "nightly", "--out", tmp_path / "out")
    one_line_error(code, err, "unknown suite 'nightly'", "smoke", "standard")
    code, _, err = run(capsys, "suite", "run", tmp_path / "missing.toml", "--out", tmp_path / "out")
    one_line_error(code, err, "suite file not found")
    assert not (tmp_path / "out").exists()


def test_manifest_hashes_every_file_and_generate_resumes(suite_dir, tiny_toml, capsys):
    manifest = read_json(suite_dir / SUITE_MANIFEST)
    assert manifest["suite"] == "tiny" and manifest["version"] == 1
    assert manifest["suite_sha256"] == load_suite(tiny_toml).sha256
    for entry_id in ("primitives", "random-3"):
        folder = suite_dir / "datasets" / entry_id
        on_disk = {p.relative_to(folder).as_posix() for p in folder.rglob("*")
                   if p.is_file() and not p.name.startswith(".") and p.name != "manifest.json"}
        record = manifest["datasets"][entry_id]
        assert set(record["files"]) == on_disk
        for rel, digest in record["files"].items():
            assert digest == hashlib.sha256((folder / rel).read_bytes()).hexdigest()
        assert record["manifest_sha256"] == hashlib.sha256((folder / "manifest.json").read_bytes()).hexdigest()
    before = {p: p.stat().st_mtime_ns for p in (suite_dir / "datasets").rglob("*.png")}
    code, out, err = run(capsys, "suite", "generate", tiny_toml, "--out", suite_dir)
    assert code == 0, err
    assert out.count("complete, skipped") == 2
    assert {p: p.stat().st_mtime_ns for p in (suite_dir / "datasets").rglob("*.png")} == before


def test_leaderboard_equals_single_run_evaluate(suite_dir, tiny_toml, gt_predictions, tmp_path, capsys):
    code, _, err = run(capsys, "suite", "evaluate", tiny_toml, suite_dir, "--method", "other-tool",
                       "--pred", gt_predictions)
    assert code == 0, err
    code, _, err = run(capsys, "suite", "report", suite_dir)
    assert code == 0, err
    board = json.loads((suite_dir / "leaderboard.json").read_text())
    method = board["methods"]["other-tool"]
    for entry_id in ("primitives", "random-3"):
        single = tmp_path / f"{entry_id}.json"
        code, _, err = run(capsys, "evaluate", suite_dir / "datasets" / entry_id, "--pred", gt_predictions / entry_id,
                           "--out", single)
        assert code == 0, err
        means = json.loads(single.read_text())["mean"]
        values = method["scenes"][entry_id]["values"]
        for metric, value in means.items():
            assert values[metric] == value  # exactly: the same function, the same floats through JSON
    psnrs = [json.loads((tmp_path / f"{i}.json").read_text())["mean"]["psnr"] for i in ("primitives", "random-3")]
    assert method["mean"]["psnr"] == pytest.approx(sum(psnrs) / 2, rel=1e-15)
    markdown = (suite_dir / "leaderboard.md").read_text()
    assert "| other-tool |" in markdown and f"{method['mean']['psnr']:.2f}" in markdown
    assert "<table class='sortable'>" in (suite_dir / "leaderboard.html").read_text()
    # The protocol-sensitivity table: the same renders under each protocol, and the spread.
    sensitivity = board["protocol_sensitivity"]["other-tool"]
    assert set(sensitivity["protocols"]) == {"nerfgauge", "nerfbaselines", "ns-eval"}
    scored = [row["psnr"] for row in sensitivity["protocols"].values() if row["psnr"] is not None]
    assert sensitivity["spread"]["psnr"] == pytest.approx(max(scored) - min(scored), abs=1e-12)
    from nerfgauge.eval.report import PROTOCOL_CAPTION
    assert PROTOCOL_CAPTION in markdown and PROTOCOL_CAPTION.split(":")[0] in (suite_dir / "leaderboard.html").read_text()


def test_results_of_another_version_or_dataset_are_refused(suite_dir, tiny_toml, gt_predictions, tmp_path, capsys):
    assert main(["suite", "evaluate", str(tiny_toml), str(suite_dir), "--method", "tool-b",
                 "--pred", str(gt_predictions)]) == 0
    v2 = tmp_path / "tiny-v2.toml"
    v2.write_text(tiny(version=2))
    code, _, err = run(capsys, "suite", "evaluate", v2, suite_dir, "--method", "x", "--pred", gt_predictions)
    one_line_error(code, err, "version 1", "not version 2")
    edited = tmp_path / "tiny-edited.toml"
    edited.write_text(tiny().replace('background = "white"', 'background = "black"'))  # the scoring: the suite's
    code, _, err = run(capsys, "suite", "evaluate", edited, suite_dir, "--method", "x", "--pred", gt_predictions)
    one_line_error(code, err, "another definition", "bump the version")

    foreign_root = tmp_path / "foreign"
    shutil.copytree(gt_predictions, foreign_root)
    write_json(foreign_root / "suite.json", {"suite": "tiny", "version": 2, "suite_sha256": "0" * 64})
    code, _, err = run(capsys, "suite", "evaluate", tiny_toml, suite_dir, "--method", "x", "--pred", foreign_root)
    one_line_error(code, err, "suite.json", "not version 1")

    result_path = suite_dir / "results" / "tool-b" / "result.json"
    original = result_path.read_bytes()
    try:
        result = json.loads(original)
        result["version"] = 2
        write_json(result_path, result)
        code, _, err = run(capsys, "suite", "report", suite_dir)
        one_line_error(code, err, str(result_path), "version 2")
        result["version"] = 1
        result["datasets"]["random-3"]["manifest_sha256"] = "f" * 64
        write_json(result_path, result)
        code, _, err = run(capsys, "suite", "report", suite_dir)
        one_line_error(code, err, "random-3", "manifest hash differs")
    finally:
        result_path.write_bytes(original)


def test_missing_or_mismatched_renders_leave_no_result(suite_dir, tiny_toml, gt_predictions, tmp_path, capsys):
    partial = tmp_path / "partial"
    shutil.copytree(gt_predictions, partial)
    shutil.rmtree(partial / "random-3")
    code, _, err = run(capsys, "suite", "evaluate", tiny_toml, suite_dir, "--method", "partial", "--pred", partial)
    one_line_error(code, err, "no predictions for 1 of the suite's 2 datasets", "random-3")
    shutil.copytree(gt_predictions / "random-3", partial / "random-3")
    (partial / "random-3" / "view1.png").unlink()
    code, _, err = run(capsys, "suite", "evaluate", tiny_toml, suite_dir, "--method", "partial", "--pred", partial)
    one_line_error(code, err, "1 colour image(s)", "2 frames")
    assert not (suite_dir / "results" / "partial" / "result.json").exists()


def test_changed_dataset_is_refused(tiny_toml, tmp_path, capsys, suite_dir, gt_predictions):
    copy = tmp_path / "copy"
    shutil.copytree(suite_dir, copy, ignore=shutil.ignore_patterns(".nerfgauge.lock"))
    manifest = copy / "datasets" / "primitives" / "manifest.json"
    manifest.write_text(manifest.read_text().replace('"schema": 2', '"schema": 2 '))
    code, _, err = run(capsys, "suite", "evaluate", tiny_toml, copy, "--method", "y", "--pred", gt_predictions)
    one_line_error(code, err, "manifest hash differs")


@pytest.mark.slow
def test_smoke_suite_end_to_end(tmp_path, capsys):
    """`suite run smoke`: datasets, our NeRF, the baselines, the leaderboard and reports;
    our NeRF's leaderboard numbers equal `nerfgauge evaluate` on its renders."""
    out = tmp_path / "smoke"
    code, stdout, err = run(capsys, "suite", "run", "smoke", "--out", out)
    assert code == 0, err
    board = json.loads((out / "leaderboard.json").read_text())
    assert {"compact-nerf", "nearest", "lightfield-nearest", "lightfield-quadrilinear"} == set(board["methods"])
    ours = board["methods"]["compact-nerf"]
    assert set(ours["scenes"]) == {entry.id for entry in load_suite("smoke").scenes}
    assert set(board["methods"]["lightfield-quadrilinear"]["scenes"]) == {"primitives-lightfield"}
    for entry_id, scene in ours["scenes"].items():
        assert scene["values"]["train_seconds"] > 0 and scene["values"]["model_bytes"] > 0
        assert scene["values"]["ms_per_frame"] > 0
        single = tmp_path / f"{entry_id}.json"
        assert main(["evaluate", str(out / "datasets" / entry_id), "--pred",
                     str(out / "predictions" / "compact-nerf" / entry_id), "--out", str(single)]) == 0
        for metric, value in json.loads(single.read_text())["mean"].items():
            assert scene["values"][metric] == value
        assert (out / "report" / entry_id / "report.html").is_file()
    assert os.path.getsize(out / "leaderboard.html") > 0 and (out / "leaderboard.md").is_file()
    # issue 36: our NeRF against the nearest-view baseline, paired, on every dataset both scored
    pairs = {(row["scene"], row["reference"], row["method"]): row for row in board["paired"]["rows"]}
    for entry_id in set(ours["scenes"]) & set(board["methods"]["nearest"]["scenes"]):
        row = pairs[(entry_id, "compact-nerf", "nearest")]
        assert row["views"] > 0 and row["ci95"][0] <= row["mean_difference"] <= row["ci95"][1]
        assert 0 < row["p_value"] <= 1 and row["significant"] == (row["p_value"] < 0.05)


def test_generate_over_another_version_needs_overwrite(suite_dir, tmp_path, capsys):
    copy = tmp_path / "copy"
    shutil.copytree(suite_dir, copy, ignore=shutil.ignore_patterns(".nerfgauge.lock", "results", "leaderboard.*"))
    v2 = tmp_path / "tiny-v2.toml"
    v2.write_text(tiny(version=2))
    code, _, err = run(capsys, "suite", "generate", v2, "--out", copy)
    one_line_error(code, err, "version 1, not version 2", "--overwrite")
    assert read_json(copy / SUITE_MANIFEST)["version"] == 1  # untouched
    code, _, err = run(capsys, "suite", "generate", v2, "--out", copy, "--overwrite")
    assert code == 0, err
    assert read_json(copy / SUITE_MANIFEST)["version"] == 2 and read_json(copy / "suite.json")["version"] == 2


def test_leaderboard_pairs_every_two_methods(suite_dir, tiny_toml, gt_predictions, tmp_path, capsys):
    """The paired table (eval.uncertainty): each pair, the first (in name order) minus the
    second, here ours minus the other tool, on the per-frame PSNR of the two metrics.json files, equal to paired_comparison on those values; the per-dataset
    tables carry the PSNR interval copied from metrics.json's ci95."""
    import numpy as np

    from nerfgauge.eval.uncertainty import EVALUATE_SEED, paired_comparison

    out = tmp_path / "tiny"
    shutil.copytree(suite_dir, out, ignore=shutil.ignore_patterns(".nerfgauge.lock", "results", "leaderboard.*",
                                                                  "report"))
    exact = tmp_path / "exact"  # "our NeRF": the ground truth itself, by frame name
    for entry_id in ("primitives", "random-3"):
        (exact / entry_id / "test").mkdir(parents=True)
        for png in (out / "datasets" / entry_id / "test").glob("r_???.png"):
            shutil.copy(png, exact / entry_id / "test" / png.name)
    for method, pred in (("compact-nerf", exact), ("other-tool", gt_predictions)):
        code, _, err = run(capsys, "suite", "evaluate", tiny_toml, out, "--method", method, "--pred", pred)
        assert code == 0, err
    code, _, err = run(capsys, "suite", "report", out)
    assert code == 0, err
    board = json.loads((out / "leaderboard.json").read_text())
    paired = board["paired"]
    assert paired["difference"] == "reference - method" and paired["alpha"] == 0.05 and paired["metric"] == "psnr"
    assert [(row["scene"], row["reference"], row["method"]) for row in paired["rows"]] == [
        ("primitives", "compact-nerf", "other-tool"), ("random-3", "compact-nerf", "other-tool")]
    for row in paired["rows"]:
        docs = [json.loads((out / board["methods"][m]["scenes"][row["scene"]]["metrics"]).read_text())
                for m in ("compact-nerf", "other-tool")]
        theirs = {frame["name"]: frame["psnr"] for frame in docs[1]["frames"]}
        ours = [frame["psnr"] for frame in docs[0]["frames"]]
        expected = paired_comparison(ours, [theirs[frame["name"]] for frame in docs[0]["frames"]],
                                     np.random.default_rng(EVALUATE_SEED))
        assert row["mean_difference"] == expected["mean_difference"] > 0 and row["ci95"] == expected["ci95"]
        # two views: the smallest exact two-sided Wilcoxon p is 0.5, never significant
        assert row["views"] == 2 and row["p_value"] == 0.5 and row["significant"] is False
        assert board["methods"]["other-tool"]["scenes"][row["scene"]]["psnr_ci95"] == docs[1]["ci95"]["psnr"]
    markdown = (out / "leaderboard.md").read_text()
    assert "Paired comparison on PSNR" in markdown and "no (not significant)" in markdown and "PSNR 95% CI" in markdown
    assert "Paired comparison on PSNR" in (out / "leaderboard.html").read_text()
