"""The project's own CI gate: a small train-and-evaluate pipeline, checked against the
repository's thresholds.toml exactly as users gate theirs (`nerfgauge check`)."""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest

from nerfgauge.cli import main

REPOSITORY = Path(__file__).resolve().parent.parent
# The CI pipeline's size: thresholds.toml's [primitives] floors were measured with these.
CI_PIPELINE = ["--res", "64", "--views", "36", "--test-views", "8", "--spp", "16", "--steps", "400", "--quiet"]


@pytest.mark.slow
def test_small_pipeline_passes_the_repository_thresholds(tmp_path, capsys):
    out = tmp_path / "ci-run"
    assert main(["run", "primitives", "--out", str(out), *CI_PIPELINE]) == 0
    assert (out / "report.html").is_file() and (out / "report" / "curve.png").is_file()
    junit = out / "junit.xml"
    code = main(["check", str(out / "eval" / "compact" / "metrics.json"),
                 "--thresholds", str(REPOSITORY / "thresholds.toml"), "--junit", str(junit)])
    report = capsys.readouterr().out
    assert code == 0, report
    suite = ElementTree.parse(junit).getroot()
    assert int(suite.get("tests")) >= 4 and int(suite.get("failures")) == 0
    assert int(suite.get("skipped", 0)) == 0  # geometry is scored by `run`, so its bounds are checked
