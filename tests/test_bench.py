"""`nerfgauge bench`: argument checks, and the table and speed-up arithmetic on known rows."""

import json

import pytest
from nerfgauge.orchestrate.bench import speedups, table_markdown

from nerfgauge.cli import main


@pytest.mark.parametrize("argv,expected", [
    (["bench", "train", "--variants", "compact,bogus"], "unknown variant"),
    (["bench", "train", "--budgets", "30,0"], "--budgets"),
    (["bench", "train", "--budgets", "soon"], "--budgets"),
    (["bench", "generate", "--repeats", "0"], "--repeats"),
])
def test_bad_bench_arguments_exit_2_before_any_work(tmp_path, capsys, argv, expected):
    assert main(argv + (["--out", str(tmp_path / "b")] if argv[1] == "train" else [])) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expected in err
    assert not (tmp_path / "b").exists()


def write_log(path, points):
    path.write_text("".join(json.dumps({"step": i, "seconds": s, "val_psnr": p}) + "\n"
                            for i, (s, p) in enumerate(points)))
    return str(path)


def test_speedup_is_vanilla_time_over_the_time_compact_first_reaches_its_psnr(tmp_path):
    vanilla = write_log(tmp_path / "v.jsonl", [(0, 12.0), (60, 14.0), (120, 15.0)])
    compact = write_log(tmp_path / "c.jsonl", [(0, 12.5), (5, 14.9), (10, 15.2), (20, 30.0)])
    rows = [{"scene": "s", "variant": "vanilla", "budget": 120, "train_seconds": 120.0, "log": vanilla},
            {"scene": "s", "variant": "compact", "budget": 120, "train_seconds": 121.0, "log": compact}]
    (line,) = speedups(rows)
    assert "15.00 dB" in line and "at 10.0 s" in line and "12x sooner" in line


def test_table_has_a_row_per_run_and_marks_missing_metrics():
    rows = [{"scene": "s", "variant": "vanilla", "budget": 30, "val_psnr": 14.0, "psnr": None, "ssim": None,
             "depth_absrel": None, "train_seconds": 31, "steps_per_second": 0.1, "render_ms_per_frame": None,
             "model_mb": 4.8, "peak_memory_mb": 6000},
            {"scene": "s", "variant": "compact", "budget": 30, "error": "exit 2"}]
    lines = table_markdown(rows).splitlines()
    assert len(lines) == 4 and "| s | vanilla | 30 | 14.00 | – | – | – |" in lines[2] and "exit 2" in lines[3]


def test_bench_read_times_both_verification_modes(tiny_dataset):
    from nerfgauge.orchestrate.bench_read import READS, bench_read, table_markdown

    rows = bench_read(tiny_dataset, "train", repeats=1)
    assert [row["read"] for row in rows] == list(READS)
    assert all(row["frames"] == 4 and 0 < row["ms_sizes_only"] < 1e5 and 0 < row["ms_sha256"] < 1e5 for row in rows)
    assert table_markdown(rows).count("\n") == 1 + len(rows)


def test_the_plots_draw_each_budgets_test_psnr_against_seconds_and_steps(tmp_path, monkeypatch):
    """One line a scene and variant through its budgets, in budget order, on the time and
    the steps panels; the PNG is written whole."""
    from PIL import Image

    from nerfgauge.orchestrate import bench

    rows = []
    for budget, steps, psnr in ((120, 4000, 41.0), (30, 900, 37.0), (600, 16000, 43.0)):
        log = write_log(tmp_path / f"c{budget}.jsonl", [(0, 20.0), (budget, psnr - 5)])
        rows.append({"scene": "s", "variant": "compact", "budget": budget, "val_psnr": psnr - 5, "psnr": psnr,
                     "train_seconds": budget + 0.5, "steps": steps, "model_mb": 1.0, "log": log})
    rows.append({"scene": "s", "variant": "vanilla", "budget": 30, "error": "exit 2"})
    drawn = {}
    original = bench.write_png_figure

    def keep(figure, path):
        drawn["axes"] = figure.axes
        original(figure, path)

    monkeypatch.setattr(bench, "write_png_figure", keep)
    bench.pareto_plots(rows, tmp_path)
    by_time, by_steps = drawn["axes"][2], drawn["axes"][3]
    (time_line,), (steps_line,) = by_time.get_lines(), by_steps.get_lines()
    assert list(time_line.get_xdata()) == [30.5, 120.5, 600.5] and list(time_line.get_ydata()) == [37.0, 41.0, 43.0]
    assert list(steps_line.get_xdata()) == [900, 4000, 16000] and list(steps_line.get_ydata()) == [37.0, 41.0, 43.0]
    assert Image.open(tmp_path / "pareto.png").size == (1210, 880)
