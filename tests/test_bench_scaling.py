"""`nerfgauge bench scaling`: argument checks, time-to-target, growth ratios, fits and tables on
known rows, and one tiny end-to-end run (slow)."""

import json
import math
import shlex
from dataclasses import asdict

import numpy as np
import pytest
from nerfgauge.orchestrate.bench.common import first_time_reaching
from nerfgauge.orchestrate.bench.scaling import (
    ScalingConfig,
    generation_fits,
    growth,
    growth_line,
    nerf_table,
    report_markdown,
)

from nerfgauge.cli import build_parser, main
from nerfgauge.core.errors import InputError


@pytest.mark.parametrize("argv,expected", [
    (["--resolutions", "64,0"], "argument --resolutions: expected an integer from 1 to 8192, got '0' (in '64,0')"),
    (["--resolutions", "64,-128"], "argument --resolutions: expected an integer from 1 to 8192, got '-128'"),
    (["--resolutions", "64,1.5"], "argument --resolutions: expected an integer, got '1.5'"),
    (["--resolutions", "64,128,64"], "argument --resolutions: 64 appears more than once in '64,128,64'"),
    (["--resolutions", "64,9000"], "expected an integer from 1 to 8192, got '9000'"),
    (["--view-counts", "25,,50"], "argument --view-counts: expected comma-separated values, got '25,,50'"),
    (["--view-counts", "25,25"], "argument --view-counts: 25 appears more than once"),
    (["--views", "0"], "argument --views: expected an integer from 1 to 100000, got '0'"),
    (["--views", "ten"], "argument --views: expected an integer, got 'ten'"),
    (["--view-counts-res", "12.5"], "argument --view-counts-res: expected an integer, got '12.5'"),
    (["--gen-views", "25,0"], "argument --gen-views: expected an integer from 1 to 100000, got '0'"),
    (["--gen-spp", "16,16"], "argument --gen-spp: 16 appears more than once"),
    (["--gen-spp", ""], "argument --gen-spp: expected comma-separated values, got ''"),
    (["--gen-views-spp", "-1"], "argument --gen-views-spp: expected an integer from 1 to 65536, got '-1'"),
    (["--gen-spp-views", "0"], "argument --gen-spp-views: expected an integer from 1 to 100000, got '0'"),
    (["--gen-res", "x"], "argument --gen-res: expected an integer, got 'x'"),
    (["--budget-seconds", "0"], "argument --budget-seconds: expected a number above 0, up to 1e+07, got '0'"),
    (["--budget-seconds", "inf"], "argument --budget-seconds: expected a finite number, got 'inf'"),
    (["--target-psnr", "nan"], "argument --target-psnr: expected a finite number, got 'nan'"),
    (["--target-psnr", "high"], "argument --target-psnr: expected a number, got 'high'"),
    (["--scene", "no-such-scene"], "unknown scene 'no-such-scene'"),
])
def test_bad_scaling_arguments_exit_2_with_one_line_before_any_work(tmp_path, capsys, argv, expected):
    out = tmp_path / "b"
    assert main(["bench", "scaling", *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("nerfgauge bench scaling: error: ") and expected in err, err
    assert not out.exists()


def test_the_counts_of_a_config_are_checked_like_the_flags():
    """ScalingConfig built in Python (not through argparse) is held to the same rules."""
    with pytest.raises(InputError, match="--resolutions lists 64 more than once"):
        ScalingConfig(resolutions=(64, 64)).validate()
    with pytest.raises(InputError, match="--budget-seconds must be a number above 0"):
        ScalingConfig(budget_seconds=float("nan")).validate()


def test_the_shared_case_runs_once_and_belongs_to_both_axes():
    cases = ScalingConfig().nerf_cases()
    assert [(r, v) for r, v, _ in cases] == [(64, 100), (128, 100), (256, 100), (128, 25), (128, 50)]
    assert dict(((r, v), axes) for r, v, axes in cases)[(128, 100)] == ("resolution", "views")


def test_the_printed_command_parses_back_to_the_same_settings(tmp_path):
    config = ScalingConfig(resolutions=(16, 24), views=6, view_counts=(6, 8), view_counts_res=16, budget_seconds=2.5,
                           target_psnr=28.5, gen_views=(2, 3), gen_views_spp=2, gen_spp=(1, 2), gen_spp_views=3,
                           gen_res=16)
    argv = shlex.split(config.command(tmp_path / "my out"))
    assert argv[:3] == ["nerfgauge", "bench", "scaling"]
    args = build_parser().parse_args(argv[1:])
    assert (args.resolutions, args.views, args.view_counts, args.view_counts_res) == ((16, 24), 6, (6, 8), 16)
    assert (args.budget_seconds, args.target_psnr) == (2.5, 28.5)
    assert (args.gen_views, args.gen_views_spp, args.gen_spp, args.gen_spp_views, args.gen_res) == \
        ((2, 3), 2, (1, 2), 3, 16)
    assert args.out == tmp_path / "my out"


def test_time_to_target_is_the_first_logged_training_second_at_or_above_it():
    log = [{"seconds": s, "val_psnr": p} for s, p in [(0.0, 14.1), (2.01, 29.99), (4.02, 30.0), (6.0, 29.5),
                                                      (8.0, 31.0)]]
    assert first_time_reaching(log, 30.0) == 4.02  # exactly the target counts; the later dip does not matter
    assert first_time_reaching(log, 14.0) == 0.0
    assert first_time_reaching(log, 31.5) is None
    assert first_time_reaching([{"seconds": 0.0, "val_psnr": math.nan}], 30.0) is None


def nerf_row(resolution, views, axes, **values):
    row = {"resolution": resolution, "views": views, "axes": axes, "train_pixels": views * resolution ** 2,
           "time_to_target_s": 10.0, "val_psnr": 33.0, "psnr": 32.5, "ssim": 0.98, "steps_per_second": 10.0,
           "render_ms_per_frame": 50.0, "model_mb": 3.0, "peak_memory_mb": 800.0, "generation_seconds": 20.0}
    return row | values


def test_growth_is_largest_over_smallest_and_its_ratio_to_the_size_ratio():
    rows = [nerf_row(256, 100, ["resolution"], render_ms_per_frame=160.0, time_to_target_s=None),
            nerf_row(64, 100, ["resolution"], render_ms_per_frame=10.0, time_to_target_s=4.0),
            nerf_row(128, 100, ["resolution", "views"], render_ms_per_frame=40.0),
            nerf_row(128, 25, ["views"], steps_per_second=12.0),
            nerf_row(128, 50, ["views"], error="train exit 1")]
    ratio, size, relative = growth(rows, "resolution", "train_pixels", "render_ms_per_frame")
    assert (ratio, size, relative) == pytest.approx((16.0, 16.0, 1.0))
    assert growth(rows, "resolution", "train_pixels", "time_to_target_s") is None  # not reached at 256
    ratio, size, relative = growth(rows, "views", "train_pixels", "steps_per_second")  # 25 -> 100, error row skipped
    assert (ratio, size, relative) == pytest.approx((10.0 / 12.0, 4.0, 10.0 / 48.0))
    line = growth_line(rows, "resolution", (("render_ms_per_frame", "render ms/frame"),
                                            ("time_to_target_s", "time to {target:g} dB")), "train_pixels", 30)
    assert line.startswith("- resolution 64 → 256 (pixel ratio ×16.00)")
    assert "render ms/frame ×16.00 (1.00 of the pixel ratio)" in line and "time to 30 dB n/a (not reached at 256)" in line
    assert "fewer than two" in growth_line(rows[:1], "resolution", (), "train_pixels")


def test_generation_fits_recover_a_known_line():
    rows = [{"views": v, "spp": 64, "axes": ["views"], "seconds": 1.5 + 0.2 * v} for v in (25, 100)]
    rows.insert(1, {"views": 50, "spp": 64, "axes": ["views", "spp"], "seconds": 1.5 + 0.2 * 50})
    rows += [{"views": 50, "spp": s, "axes": ["spp"], "seconds": 1.5 + 0.2 * 50 + 0.002 * 50 * (s - 64)}
             for s in (16, 256)]
    fits = generation_fits(rows)
    assert fits["views"]["slope"] == pytest.approx(0.2) and fits["views"]["intercept"] == pytest.approx(1.5)
    assert fits["spp"]["seconds_per_spp_per_view"] == pytest.approx(0.002)
    assert fits["spp"]["intercept"] == pytest.approx(1.5 + 0.2 * 50 - 0.002 * 50 * 64)
    assert generation_fits(rows[:1]) == {"views": None, "spp": None}


def test_tables_say_when_the_target_was_not_reached_and_show_errors():
    rows = [nerf_row(64, 100, ["resolution"], time_to_target_s=None, psnr=None),
            nerf_row(128, 100, ["resolution"], time_to_target_s=12.34),
            {"resolution": 256, "views": 100, "axes": ["resolution"], "error": "train exit 1"}]
    lines = nerf_table(rows, 30, 120).splitlines()
    assert len(lines) == 5 and "time to 30 dB (s)" in lines[0]
    assert lines[2].startswith("| 64x64 | 100 | not reached in 120 s | 33.00 | – |")
    assert lines[3].startswith("| 128x128 | 100 | 12.3 |")
    assert "train exit 1" in lines[4] and lines[4].count("|") == lines[0].count("|")
    document = {"command": "nerfgauge bench scaling ...", "config": asdict(ScalingConfig()), "eval_every_seconds": 2.0,
                "nerf": rows, "generation": [], "fits": {"views": None, "spp": None}}
    report = report_markdown(document)
    assert report.startswith("```bash\nnerfgauge bench scaling ...\n```") and "not reached in 120 s" in report


@pytest.mark.slow
def test_tiny_scaling_run_writes_json_markdown_and_plot(tmp_path):
    out = tmp_path / "scaling"
    # Two NeRF cases, (16, 6) on both axes: each is three child processes, mostly imports.
    argv = ["bench", "scaling", "--resolutions", "16,32", "--views", "6", "--view-counts", "6",
            "--view-counts-res", "16", "--budget-seconds", "2", "--target-psnr", "10", "--gen-views", "2,3",
            "--gen-views-spp", "2", "--gen-spp", "1,2", "--gen-spp-views", "3", "--gen-res", "16", "--out", str(out)]
    assert main(argv) == 0
    document = json.loads((out / "scaling.json").read_text())
    assert (out / "scaling.png").stat().st_size > 10_000
    assert (out / "scaling.md").read_text().startswith("```bash\nnerfgauge bench scaling --scene primitives")
    nerf_keys = {"resolution", "views", "time_to_target_s", "val_psnr", "psnr", "ssim", "steps_per_second",
                 "render_ms_per_frame", "model_mb", "peak_memory_mb", "generation_seconds"}
    assert [(r["resolution"], r["views"], r["axes"]) for r in document["nerf"]] == \
        [(16, 6, ["resolution", "views"]), (32, 6, ["resolution"])]
    # both scored on the common 16 px pixels (32 px area-averaged by 2), and the verdict says how they compare
    assert [r["common_resolution"] for r in document["nerf"]] == [16, 16]
    assert all(math.isfinite(r["psnr_at_common"]) for r in document["nerf"])
    assert "Scored on common 16 px pixels" in (out / "scaling.md").read_text()
    for row in document["nerf"]:
        assert "error" not in row and nerf_keys <= set(row)
        assert all(math.isfinite(row[key]) for key in nerf_keys), row  # 10 dB: reached by the first log point
    assert [(r["views"], r["spp"]) for r in document["generation"]] == [(2, 2), (3, 2), (3, 1)]
    for row in document["generation"]:
        assert all(math.isfinite(row[key]) and row[key] > 0 for key in ("seconds", "seconds_per_view", "render_seconds"))
    assert all(math.isfinite(value) for fit in document["fits"].values() for value in fit.values())


def test_detail_finer_than_the_common_resolution_does_not_count(tiny_dataset, tmp_path):
    """Renders equal to the ground truth except for a +d/-d pattern inside each 2x2 block of
    opaque pixels (block sums unchanged, in 8-bit integers): natively their PSNR is finite,
    on the 2x coarser common pixels they match exactly (the 100 dB cap)."""
    from nerfgauge.core import dataset
    from nerfgauge.core.images import read_png, write_png
    from nerfgauge.orchestrate.bench.scaling import psnr_at_common_resolution
    from nerfgauge.eval.evaluate import evaluate
    from nerfgauge.eval.metrics import PSNR_CAP_DB

    d = 20
    pattern = np.array([[d, -d], [-d, d]])
    perturbed = 0
    for stem in dataset.Dataset(tiny_dataset).cameras("test").stems:
        rgba = np.round(read_png(tiny_dataset / f"{stem}.png") * 255).astype(np.int32)  # [32, 32, 4] 8-bit values
        for i in range(0, rgba.shape[0], 2):
            for j in range(0, rgba.shape[1], 2):
                block = rgba[i:i + 2, j:j + 2]
                if (block[..., 3] == 255).all() and (block[..., :3] >= d).all() and (block[..., :3] <= 255 - d).all():
                    block[..., :3] += pattern[..., None]
                    perturbed += 1
        (tmp_path / stem).parent.mkdir(parents=True, exist_ok=True)
        write_png(tmp_path / f"{stem}.png", rgba.astype(np.uint8))
    assert perturbed >= 4  # the pattern touched enough pixels to matter natively
    native = evaluate(tiny_dataset, tmp_path, "test", tmp_path / "metrics.json")["mean"]["psnr"]
    assert native < 60
    assert psnr_at_common_resolution(tiny_dataset, tmp_path, 2) == pytest.approx(PSNR_CAP_DB)


def test_the_verdict_line_names_each_finer_capture_that_scored_worse():
    from nerfgauge.orchestrate.bench.scaling import finer_never_worse_line

    def row(resolution, score):
        return {"resolution": resolution, "common_resolution": 64, "psnr_at_common": score}

    assert "never scored worse" in finer_never_worse_line([row(64, 30.0), row(128, 31.0), row(256, 31.0)])
    line = finer_never_worse_line([row(256, 30.5), row(64, 30.0), row(128, 31.0)])
    assert "256 px (30.50 dB) < 128 px (31.00)" in line and "128 px (31.00 dB) <" not in line
    assert "fewer than two" in finer_never_worse_line([row(64, 30.0), {"resolution": 128, "error": "x"}])
