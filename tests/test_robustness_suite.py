"""The robustness suite (issue 35 item 7): suites set degradation fields per entry like any
GenerateConfig field, and the leaderboard draws each method's score against the level
(orchestrate.suite.robustness). The tiny suite below runs end to end in seconds; the
built-in `robustness` suite is the slow test."""

from __future__ import annotations

import math

import pytest
from suite_toml import suite_toml

from nerfgauge.cli import main
from nerfgauge.core.files import read_json
from nerfgauge.core.errors import InputError
from nerfgauge.orchestrate.suite.definition import load_suite, parse_suite
from nerfgauge.orchestrate.suite.robustness import robustness

ENTRIES = ({"id": "clean"}, {"id": "pose-2", "pose_noise_rotation": 2.0}, {"id": "pose-4", "pose_noise_rotation": 4.0},
           {"id": "ev-1", "exposure_ev": 1.0}, {"id": "both", "exposure_ev": 1.0, "vignetting": 0.2})
TINY = suite_toml("tiny-robustness",
                  {"width": 16, "height": 16, "views": 6, "val_views": 0, "test_views": 2, "spp": 2, "degrade_seed": 4},
                  {"steps": 15, "final_resolution": 24, "eval_views": 1},
                  [{"id": e["id"], "scene": "primitives", "seed": 0} | {k: v for k, v in e.items() if k != "id"}
                   for e in ENTRIES])


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    root = tmp_path_factory.mktemp("robust")
    toml = root / "tiny.toml"
    toml.write_text(TINY)
    out = root / "suite"
    assert main(["suite", "run", str(toml), "--out", str(out)]) == 0
    return load_suite(toml), out


@pytest.mark.slow
def test_suite_entries_pass_degradations_to_generate(ran):
    suite, out = ran
    for entry in suite.scenes:
        config = read_json(out / "datasets" / entry.id / "config.json")["config"]
        for field in ("pose_noise_rotation", "exposure_ev", "vignetting"):
            assert config.get(field, 0.0) == entry.dataset.get(field, 0.0)
        assert config["degrade_seed"] == 4
    scene = read_json(out / "datasets" / "pose-4" / "scene.json")
    assert scene["degradations"]["pose_noise_rotation"] == 4.0


@pytest.mark.slow
def test_curves_have_a_row_per_level_and_method_with_the_metrics_json_scores(ran):
    suite, out = ran
    board = read_json(out / "leaderboard.json")
    curves = {curve["field"]: curve for curve in board["robustness"]["curves"]}
    assert set(curves) == {"pose_noise_rotation", "exposure_ev"}
    assert curves["pose_noise_rotation"]["levels"] == [0.0, 2.0, 4.0]
    assert curves["pose_noise_rotation"]["entries"] == ["clean", "pose-2", "pose-4"]
    assert curves["exposure_ev"]["levels"] == [0.0, 1.0] and curves["exposure_ev"]["entries"] == ["clean", "ev-1"]
    assert board["robustness"]["combined"] == [{"entry": "both", "levels": {"exposure_ev": 1.0, "vignetting": 0.2}}]
    methods = set(board["methods"])
    assert methods == {"compact-nerf", "nearest"}
    for curve in curves.values():
        assert set(curve["scores"]) == methods
        for method in methods:
            result = read_json(out / "results" / method / "result.json")
            for k, entry_id in enumerate(curve["entries"]):
                metrics = read_json(out / result["datasets"][entry_id]["metrics"])
                assert curve["scores"][method]["psnr"][k] == metrics["mean"]["psnr"]
                assert curve["scores"][method]["ssim"][k] == metrics["mean"]["ssim"]
    table = [line for line in (out / "leaderboard.md").read_text().splitlines()
             if line.startswith("| pose_noise_rotation") or line.startswith("| exposure_ev")]
    assert len(table) == (3 + 2) * len(methods)
    png = (out / "robustness.png").read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 1000
    assert "robustness.png" in (out / "leaderboard.html").read_text()


def test_clean_test_views_are_the_same_in_every_entry(ran):
    """What the methods are scored against does not depend on the train degradation."""
    suite, out = ran
    clean = out / "datasets" / "clean" / "test"
    for entry in suite.scenes:
        for png in sorted(clean.glob("r_???.png")):
            assert (out / "datasets" / entry.id / "test" / png.name).read_bytes() == png.read_bytes()


def test_a_suite_without_levels_has_no_curves():
    suite = load_suite("smoke")
    assert robustness(suite, {"methods": {}}) is None


def test_bad_degradation_in_a_suite_is_an_input_error_naming_the_entry():
    import tomllib

    data = tomllib.loads(TINY.replace("exposure_ev = 1.0\nvignetting = 0.2", "vignetting = 1.5"))
    with pytest.raises(InputError, match=r"scenes\[4\].*--vignetting"):
        parse_suite(data, "tiny.toml")


def test_builtin_robustness_suite_crosses_pose_noise_and_exposure_levels():
    suite = load_suite("robustness")
    levels = {}
    for entry in suite.scenes:
        for field in ("pose_noise_rotation", "exposure_ev"):
            levels.setdefault(field, set()).add(entry.dataset.get(field, 0.0))
    assert levels["pose_noise_rotation"] == {0.0, 0.5, 1.0, 2.0}
    assert levels["exposure_ev"] == {0.0, 0.25, 0.5, 1.0}


def builtin_robustness_at_test_size() -> str:
    """The built-in robustness suite with its entries, levels, methods and scoring as shipped
    and only its size cut (16 px, 6 train / 2 test views, 4 spp, 40 steps): the whole path
    its full size runs, in a fraction of the time (the shipped file itself is read above)."""
    import tomllib

    from nerfgauge.orchestrate.suite.definition import builtin_suites

    data = tomllib.loads(builtin_suites()["robustness"].read_text())
    dataset = data["dataset"] | {"width": 16, "height": 16, "views": 6, "test_views": 2, "spp": 4}
    methods = [method | ({"settings": method["settings"] | {"batch_rays": 256, "final_resolution": 24}}
                         if "settings" in method else {}) for method in data["methods"]]
    return suite_toml("robustness-small", dataset, data["train"] | {"steps": 40}, data["scenes"],
                      protocol=data["scoring"], methods=methods)


@pytest.mark.slow
def test_builtin_robustness_suite_runs_end_to_end(tmp_path):
    toml = tmp_path / "robustness.toml"
    toml.write_text(builtin_robustness_at_test_size())
    shipped = load_suite("robustness")
    small = load_suite(toml)
    size = {"width", "height", "views", "test_views", "spp"}
    assert [(e.id, e.scene, e.seed, {k: v for k, v in e.dataset.items() if k not in size}) for e in small.scenes] == \
        [(e.id, e.scene, e.seed, {k: v for k, v in e.dataset.items() if k not in size}) for e in shipped.scenes]
    assert [(m.name, m.method) for m in small.methods] == [(m.name, m.method) for m in shipped.methods]
    assert small.scoring == shipped.scoring
    out = tmp_path / "robustness"
    assert main(["suite", "run", str(toml), "--out", str(out)]) == 0
    board = read_json(out / "leaderboard.json")
    curves = {curve["field"]: curve for curve in board["robustness"]["curves"]}
    assert curves["pose_noise_rotation"]["levels"] == [0.0, 0.5, 1.0, 2.0]
    assert curves["exposure_ev"]["levels"] == [0.0, 0.25, 0.5, 1.0]
    for curve in curves.values():
        assert set(curve["scores"]) == {"compact-nerf", "nearest"}
        for scores in curve["scores"].values():
            assert all(value is not None and math.isfinite(value) for value in scores["psnr"])
    assert (out / "robustness.png").is_file()
