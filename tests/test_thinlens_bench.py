"""The defocus bench end to end on a tiny light field (slow: it trains a model)."""

from __future__ import annotations

import json

import pytest


@pytest.mark.slow
def test_lens_bench_scores_every_method_at_every_aperture(tmp_path):
    from nerfgauge.cli import main
    from nerfgauge.orchestrate.bench.lens import METHODS

    out = tmp_path / "lens"
    assert main(["bench", "lens", "--out", str(out), "--views", "9", "--test-views", "2", "--res", "16", "--spp", "4",
                 "--budget-seconds", "5", "--aperture-samples", "4", "--apertures", "0.1"]) == 0
    summary = json.loads((out / "lens.json").read_text())
    assert summary["apertures"] == [0.0, 0.1]
    for method in METHODS:
        assert set(summary["mean"][method]) == {"0", "0.1"}
        assert all(0 < summary["mean"][method][a]["psnr"] < 100 for a in ("0", "0.1"))
    assert summary["nerf_ms_per_lens_frame"]["0.1"] > 0 and summary["nerf_psnr_minus_pinhole"]["0"] == 0
    for name in ("lens.md", "lens.png", "lens.html"):
        assert (out / name).stat().st_size > 0
    assert main(["bench", "lens", "--out", str(tmp_path / "bad"), "--views", "10"]) == 2  # not a square grid: one error, exit 2
