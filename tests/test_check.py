"""`nerfgauge check`: exit codes, the table, margins, JUnit output, malformed input."""

import json
import re
import xml.etree.ElementTree as ET

import pytest
from nerfgauge.eval.check import Bound, evaluate_bounds, parse_thresholds

from nerfgauge.cli import main
from nerfgauge.core.errors import InputError

THRESHOLDS = """
["*"]
ssim = { min = 0.9 }

[primitives]
psnr = { min = 30.0 }
depth_absrel = { max = 0.02 }
depth_delta1 = { min = 0.97, max = 1.0 }
"""


def metrics_doc(**mean):
    values = {"psnr": 32.5, "ssim": 0.95, "depth_absrel": 0.015, "depth_rmse": 0.01,
              "depth_mae": 0.005, "depth_delta1": 0.99}
    values.update(mean)
    return {"schema": 1, "scene": "primitives", "split": "test", "mean": values,
            "std": {key: 0.0 for key in values}, "frames": [], "timing": {}}


@pytest.fixture
def files(tmp_path):
    """Write a metrics.json and a thresholds.toml; returns their paths as strings."""

    def write(metrics=None, thresholds=THRESHOLDS):
        metrics_path, thresholds_path = tmp_path / "metrics.json", tmp_path / "thresholds.toml"
        metrics_path.write_text(metrics if isinstance(metrics, str) else json.dumps(metrics or metrics_doc()))
        thresholds_path.write_text(thresholds)
        return str(metrics_path), str(thresholds_path)

    return write


def run(capsys, *argv):
    code = main(["check", *argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def rows(out):
    """Table rows keyed by (metric, bound) -> the row's cells."""
    table = {}
    for line in out.splitlines()[2:-1]:
        cells = line.split()
        table[(cells[1], f"{cells[3]} {cells[4]}")] = cells
    return table


# --- pass / fail ------------------------------------------------------------------------


def test_all_pass_exits_0_with_margins(files, capsys):
    metrics, thresholds = files()
    code, out, err = run(capsys, metrics, "--thresholds", thresholds)
    assert code == 0, err
    table = rows(out)
    # "*" ssim plus psnr, depth_absrel and two bounds of depth_delta1.
    assert len(table) == 5
    assert table[("psnr", ">= 30")][2:] == ["32.5", ">=", "30", "+2.5", "PASS"]
    assert table[("depth_absrel", "<= 0.02")][5] == "+0.005"
    assert table[("depth_delta1", "<= 1")][5] == "+0.01"
    assert "5 checks: 5 passed, 0 failed" in out


def test_a_failing_bound_exits_1_and_says_why(files, capsys):
    metrics, thresholds = files(metrics_doc(psnr=28.0))
    code, out, _ = run(capsys, metrics, "--thresholds", thresholds)
    assert code == 1
    psnr_row = rows(out)[("psnr", ">= 30")]
    assert psnr_row[5:7] == ["-2", "FAIL"]
    assert "psnr = 28 is below the minimum 30 by 2" in out
    assert "5 checks: 4 passed, 1 failed" in out


def test_value_equal_to_its_bound_passes(files, capsys):
    metrics, thresholds = files(metrics_doc(psnr=30.0, depth_absrel=0.02))
    code, out, _ = run(capsys, metrics, "--thresholds", thresholds)
    assert code == 0, out


def test_null_or_missing_metric_with_a_bound_fails(files, capsys):
    doc = metrics_doc(depth_absrel=None)
    del doc["mean"]["depth_delta1"]
    metrics, thresholds = files(doc)
    code, out, _ = run(capsys, metrics, "--thresholds", thresholds)
    assert code == 1
    assert "depth_absrel is null in the metrics file" in out
    assert "depth_delta1 is missing from the metrics file" in out
    assert rows(out)[("depth_absrel", "<= 0.02")][2] == "null"


def test_scene_table_overrides_the_default_table(files, capsys):
    metrics, thresholds = files(metrics_doc(ssim=0.93), THRESHOLDS + "ssim = { min = 0.95 }\n")
    code, out, _ = run(capsys, metrics, "--thresholds", thresholds)
    assert code == 1
    assert ("ssim", ">= 0.95") in rows(out) and ("ssim", ">= 0.9") not in rows(out)


def test_scene_option_selects_another_table(files, capsys):
    metrics, thresholds = files(thresholds=THRESHOLDS + "\n[glossy]\npsnr = { min = 40.0 }\n")
    code, out, _ = run(capsys, metrics, "--thresholds", thresholds, "--scene", "glossy")
    assert code == 1  # 32.5 < 40
    assert "bounds of scene glossy" in out
    assert ("psnr", ">= 40") in rows(out) and ("depth_absrel", "<= 0.02") not in rows(out)


def test_margins_and_kinds_from_the_api():
    results = evaluate_bounds("primitives", {"psnr": 31.25, "depth_rmse": 0.5},
                              [Bound("psnr", 30.0, 35.0), Bound("depth_rmse", max=0.25)])
    assert [(r.kind, r.margin, r.passed) for r in results] == [
        ("min", 1.25, True), ("max", 3.75, True), ("max", -0.25, False)]  # exact in binary


# --- JUnit ------------------------------------------------------------------------------


def test_junit_lists_every_check_and_its_failures(files, capsys, tmp_path):
    metrics, thresholds = files(metrics_doc(psnr=28.0, depth_absrel=None))
    junit = tmp_path / "reports" / "check.xml"
    junit.parent.mkdir()
    code, _, _ = run(capsys, metrics, "--thresholds", thresholds, "--junit", str(junit))
    assert code == 1
    suite = ET.parse(junit).getroot()
    assert suite.tag == "testsuite"
    assert (suite.get("tests"), suite.get("failures")) == ("5", "2")
    cases = suite.findall("testcase")
    assert [case.get("name") for case in cases] == [
        "ssim >= 0.9", "psnr >= 30", "depth_absrel <= 0.02", "depth_delta1 >= 0.97", "depth_delta1 <= 1"]
    failed = {case.get("name"): case.find("failure").get("message") for case in cases if case.find("failure") is not None}
    assert failed == {"psnr >= 30": "psnr = 28 is below the minimum 30 by 2",
                      "depth_absrel <= 0.02": "depth_absrel is null in the metrics file (not measured) but has a bound"}
    assert all(case.get("classname") == "nerfgauge.check.primitives" for case in cases)
    assert sorted(p.name for p in junit.parent.iterdir()) == ["check.xml"]  # no temp file left


def test_junit_written_when_all_pass(files, capsys, tmp_path):
    metrics, thresholds = files()
    junit = tmp_path / "ok.xml"
    assert run(capsys, metrics, "--thresholds", thresholds, "--junit", str(junit))[0] == 0
    suite = ET.parse(junit).getroot()
    assert suite.get("failures") == "0" and len(suite.findall("testcase")) == 5
    assert all(case.find("failure") is None for case in suite.findall("testcase"))


# --- malformed input: exit 2, one line naming the problem -----------------------------


@pytest.mark.parametrize("thresholds, message", [
    ("[primitives]\npnsr = { min = 30 }\n", "unknown metric 'pnsr'"),
    ("[primitives]\npsnr = { min = 30, minimum = 31 }\n", "unknown key 'minimum'"),
    ("[primitivs]\npsnr = { min = 30 }\n", "unknown scene 'primitivs'"),
    ("[primitives]\npsnr = 30\n", r"\[primitives\] psnr must be a table"),
    ("[primitives]\npsnr = { min = \"30\" }\n", r"psnr.min must be a finite number"),
    ("[primitives]\npsnr = { min = nan }\n", r"psnr.min must be a finite number"),
    ("[primitives]\npsnr = { min = 40, max = 30 }\n", "min 40 is greater than max 30"),
    ("[primitives]\npsnr = {}\n", "psnr has no bound"),
    ("psnr = { min = 30 }\n", "metric 'psnr' is outside a scene table"),
    ("[primitives\npsnr = { min = 30 }\n", "malformed TOML"),
    ("[glossy]\npsnr = { min = 30 }\n", "no bounds for scene 'primitives'.*nothing would be checked"),
])
def test_bad_thresholds_exit_2(files, capsys, thresholds, message):
    metrics, path = files(thresholds=thresholds)
    code, out, err = run(capsys, metrics, "--thresholds", path)
    assert code == 2
    assert out == ""
    assert len(err.strip().splitlines()) == 1
    assert err.startswith("nerfgauge check: error: ")
    assert re.search(message, err), err


@pytest.mark.parametrize("metrics, message", [
    (json.dumps({**metrics_doc(), "schema": 2}), "schema 2 is not supported"),
    (json.dumps({k: v for k, v in metrics_doc().items() if k != "schema"}), "no 'schema' field"),
    (json.dumps({**metrics_doc(), "mean": {"psnr": "high"}}), "mean.psnr must be a number or null"),
    (json.dumps([1, 2]), "expected a JSON object"),
    ("{not json", "malformed JSON"),
])
def test_bad_metrics_exit_2(files, capsys, metrics, message):
    metrics_path, thresholds = files(metrics)
    code, _, err = run(capsys, metrics_path, "--thresholds", thresholds)
    assert code == 2
    assert message in err


def test_missing_files_unknown_scene_option_and_junit_directory_exit_2(files, capsys, tmp_path):
    metrics, thresholds = files()
    assert run(capsys, str(tmp_path / "nope.json"), "--thresholds", thresholds)[0] == 2
    code, _, err = run(capsys, metrics, "--thresholds", str(tmp_path / "nope.toml"))
    assert code == 2 and "thresholds file not found" in err
    code, _, err = run(capsys, metrics, "--thresholds", thresholds, "--scene", "nowhere")
    assert code == 2 and "unknown scene 'nowhere'" in err
    code, _, err = run(capsys, metrics, "--thresholds", thresholds, "--junit", str(tmp_path / "no" / "j.xml"))
    assert code == 2 and "does not exist" in err


def test_mesh_scenes_and_default_table_are_accepted():
    tables = parse_thresholds({"*": {"ssim": {"min": 0.5}}, "mesh:assets/bunny.obj": {"psnr": {"max": 60}}})
    assert tables["mesh:assets/bunny.obj"]["psnr"] == Bound("psnr", None, 60.0)
    with pytest.raises(InputError, match="unknown scene 'mesh:'"):
        parse_thresholds({"mesh:": {"psnr": {"min": 1}}})


# --- geometry bounds: checked against a run's metrics, skipped for plain evaluate -------

GEOMETRY_THRESHOLDS = THRESHOLDS + "geometry_fscore_1pct = { min = 0.2 }\nnormal_angle_mean = { max = 35.0 }\n"


def test_geometry_bounds_are_skipped_for_metrics_without_geometry(files, capsys, tmp_path):
    """A plain `nerfgauge evaluate` metrics.json (no geometry table) passes a thresholds
    file with geometry floors: those checks are reported as skipped, not failed."""
    metrics, thresholds = files(metrics_doc(), GEOMETRY_THRESHOLDS)
    junit = tmp_path / "check.xml"
    code, out, _ = run(capsys, metrics, "--thresholds", thresholds, "--junit", str(junit))
    assert code == 0, out
    table = rows(out)
    assert table[("geometry_fscore_1pct", ">= 0.2")][2:7] == ["null", ">=", "0.2", "-", "SKIP"]
    assert table[("normal_angle_mean", "<= 35")][6] == "SKIP"
    assert "skipped: no geometry in metrics" in out
    assert "7 checks: 5 passed, 0 failed, 2 skipped" in out
    suite = ET.parse(junit).getroot()
    assert (suite.get("tests"), suite.get("failures"), suite.get("skipped")) == ("7", "0", "2")
    skipped = {case.get("name"): case.find("skipped").get("message") for case in suite.findall("testcase")
               if case.find("skipped") is not None}
    assert skipped == {"geometry_fscore_1pct >= 0.2": "skipped: no geometry in metrics",
                       "normal_angle_mean <= 35": "skipped: no geometry in metrics"}
    assert all(case.find("failure") is None for case in suite.findall("testcase"))


@pytest.mark.parametrize("geometry, code, reason", [
    ({"geometry_fscore_1pct": 0.3, "normal_angle_mean": 28.0}, 0, None),
    ({"geometry_fscore_1pct": 0.1, "normal_angle_mean": 28.0}, 1, "geometry_fscore_1pct = 0.1 is below the minimum 0.2"),
    ({"geometry_fscore_1pct": 0.3, "normal_angle_mean": 40.0}, 1, "normal_angle_mean = 40 is above the maximum 35"),
    # the run's field had no surface: every figure null, which fails rather than skips
    ({"geometry_fscore_1pct": None, "normal_angle_mean": None}, 1, "geometry_fscore_1pct is null in the metrics file"),
    ({"normal_angle_mean": 28.0}, 1, "geometry_fscore_1pct is missing from the metrics file"),
])
def test_geometry_bounds_are_checked_when_metrics_have_geometry(files, capsys, geometry, code, reason):
    metrics, thresholds = files({**metrics_doc(), "geometry": geometry}, GEOMETRY_THRESHOLDS)
    got, out, _ = run(capsys, metrics, "--thresholds", thresholds)
    assert got == code, out
    assert "SKIP" not in out and "skipped" not in out
    assert reason is None or reason in out


def test_only_geometry_bounds_and_no_geometry_is_an_error(files, capsys):
    """Nothing would be checked: exit 2, as for a scene without bounds."""
    metrics, thresholds = files(metrics_doc(), "[primitives]\ngeometry_fscore_1pct = { min = 0.2 }\n")
    code, out, err = run(capsys, metrics, "--thresholds", thresholds)
    assert (code, out) == (2, "")
    assert len(err.strip().splitlines()) == 1 and "nothing would be checked" in err and "no geometry table" in err


def test_skipped_results_from_the_api_do_not_fail_the_gate():
    bounds = [Bound("psnr", 30.0), Bound("geometry_chamfer_l1", max=0.1)]
    skipped = evaluate_bounds("primitives", {"psnr": 31.0}, bounds)
    assert [(r.metric, r.passed, r.skipped, r.value) for r in skipped] == [
        ("psnr", True, False, 31.0), ("geometry_chamfer_l1", True, True, None)]
    checked = evaluate_bounds("primitives", {"psnr": 31.0}, bounds, {"geometry_chamfer_l1": 0.25})
    assert [(r.passed, r.skipped) for r in checked] == [(True, False), (False, False)]
    assert checked[1].margin == pytest.approx(-0.15)


def test_run_summary_without_a_surface_is_all_null():
    """`nerfgauge run` writes this table when the field has no surface: every geometry
    bound then fails (null) instead of being skipped."""
    from nerfgauge.eval.geometry import SUMMARY_NAMES, summary

    assert summary(None) == dict.fromkeys(SUMMARY_NAMES)


# --- bounds on the confidence interval (on = "ci95") --------------------------------------

CI_THRESHOLDS = """
[primitives]
psnr = { min = 30.0, on = "ci95" }
depth_absrel = { max = 0.02, on = "ci95" }
ssim = { min = 0.9 }
"""


def test_ci95_bounds_check_the_interval_ends(files, capsys):
    doc = {**metrics_doc(), "ci95": {"psnr": [30.5, 34.5], "depth_absrel": [0.01, 0.025], "ssim": [0.9, 0.99]}}
    metrics, thresholds = files(doc, CI_THRESHOLDS)
    code, out, _ = run(capsys, metrics, "--thresholds", thresholds)
    assert code == 1  # the mean 0.015 passes, the upper end 0.025 does not
    table = rows(out)
    assert table[("psnr.ci95_low", ">= 30")][2:6] == ["30.5", ">=", "30", "+0.5"]
    assert table[("depth_absrel.ci95_high", "<= 0.02")][5:7] == ["-0.005", "FAIL"]
    assert "depth_absrel.ci95_high = 0.025 is above the maximum 0.02" in out
    assert table[("ssim", ">= 0.9")][2] == "0.95"  # on = "mean" (the default) reads the mean
    doc["ci95"]["psnr"] = [29.0, 34.0]  # mean 32.5 passes a plain min of 30, the lower end does not
    metrics, thresholds = files(doc, CI_THRESHOLDS)
    assert "psnr.ci95_low = 29 is below the minimum 30" in run(capsys, metrics, "--thresholds", thresholds)[1]
    doc["ci95"]["psnr"] = None
    metrics, thresholds = files(doc, CI_THRESHOLDS)
    assert "psnr.ci95_low is null in the metrics file" in run(capsys, metrics, "--thresholds", thresholds)[1]


def test_ci95_junit_names_the_interval_end(files, capsys, tmp_path):
    doc = {**metrics_doc(), "ci95": {"psnr": [30.5, 34.5], "depth_absrel": [0.01, 0.015]}}
    metrics, thresholds = files(doc, CI_THRESHOLDS)
    junit = tmp_path / "junit.xml"
    assert run(capsys, metrics, "--thresholds", thresholds, "--junit", str(junit))[0] == 0
    names = [case.get("name") for case in ET.parse(junit).getroot().iter("testcase")]
    assert "psnr.ci95_low >= 30" in names and "depth_absrel.ci95_high <= 0.02" in names


@pytest.mark.parametrize("thresholds, metrics, message", [
    ('[primitives]\npsnr = { min = 30, on = "ci_low" }\n', None, r"psnr.on must be one of 'mean', 'ci95'"),
    ('[primitives]\npsnr = { on = "ci95" }\n', None, "psnr has no bound"),
    ('[primitives]\ngeometry_fscore_1pct = { min = 0.2, on = "ci95" }\n', None, "has no interval"),
    ('[primitives]\npsnr = { min = 30, on = "ci95" }\n', metrics_doc(), "does not have"),
    (THRESHOLDS, {**metrics_doc(), "ci95": {"psnr": [31, 30]}}, r"ci95.psnr must be \[low, high\]"),
    (THRESHOLDS, {**metrics_doc(), "ci95": [30, 31]}, "'ci95' must be an object"),
])
def test_bad_ci95_input_exits_2_in_one_line(files, capsys, thresholds, metrics, message):
    metrics_path, path = files(metrics, thresholds)
    code, out, err = run(capsys, metrics_path, "--thresholds", path)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1
    assert re.search(message, err), err
