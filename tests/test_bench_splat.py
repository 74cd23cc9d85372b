"""`nerfgauge bench splat`: its flags refused before any work, the issue's targets judged from
known figures, and one tiny run end to end (its children run in this process, to keep it
short: common.run_child's own measurement is the other benches' and is tested there)."""

from __future__ import annotations

import json
import shlex
import time

import numpy as np
import pytest

from nerfgauge.cli import build_parser, main
from nerfgauge.orchestrate.bench import splat as bench


@pytest.mark.parametrize("flags, expected", [
    (["--methods", "splat,nerfacto"], "--methods"),
    (["--methods", "splat,splat"], "--methods"),
    (["--budgets", "120,0"], "--budgets"),
    (["--budgets", "60,60"], "--budgets"),
    (["--seeds", "-1"], "--seeds"),
    (["--res", "0"], "--res"),
    (["--scenes", "nowhere"], "unknown scene"),
    (["--geometry-samples", "0"], "--geometry-samples"),
    (["--threads", "nan"], "--threads"),
])
def test_bad_arguments_exit_2_before_any_work(tmp_path, capsys, flags, expected):
    out = tmp_path / "bench"
    assert main(["bench", "splat", "--out", str(out), *flags]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expected in err, err
    assert not out.exists()


def aggregate(method: str, budget: float, psnr: float, ms: float) -> dict:
    return {"scene": "primitives", "method": method, "budget": budget, "seeds": 1, "mean": {"psnr": psnr},
            "ci95": {"psnr": None}, "render_ms_per_frame": ms}


def test_the_issues_targets_are_judged_only_on_their_own_case():
    config = bench.SplatBenchConfig()
    document = {"config": vars(config) | {"scenes": ["primitives"]},
                "aggregates": [aggregate("splat", 120.0, 36.5, 12.0), aggregate("splat", 600.0, 39.9, 25.0),
                               aggregate("compact", 120.0, 30.0, 90.0)]}
    lines = bench.targets_lines(document)
    assert "- 120 s: 36.50 dB against >= 36 dB: met" in lines
    assert "- 600 s: 39.90 dB against >= 40 dB: not met" in lines
    assert "- render at 600 s: 25.0 ms a frame against <= 20: not met" in lines
    assert not any("30.00" in line for line in lines)  # the NeRF is not judged against splat's targets
    smaller = document | {"config": document["config"] | {"width": 64, "height": 64}}
    assert bench.targets_lines(smaller) == []  # another resolution is not the issue's case


@pytest.mark.slow
def test_a_tiny_run_writes_its_table_plot_and_the_command_that_reproduces_it(tmp_path, monkeypatch):
    import torch

    def in_process(argv):
        start = time.perf_counter()
        return main([str(arg) for arg in argv]), time.perf_counter() - start, 0.0

    monkeypatch.setattr(bench, "run_child", in_process)
    threads = torch.get_num_threads()
    config = bench.SplatBenchConfig(width=32, height=32, views=4, test_views=2, spp=4, budgets=(1.0,), seeds=(0,),
                                    geometry_samples=2000)
    try:
        document = bench.bench_splat(config, tmp_path / "bench", progress_print=lambda _: None)
    finally:
        torch.set_num_threads(threads)
    out = tmp_path / "bench"
    assert json.loads((out / "splat.json").read_text()) == json.loads(json.dumps(document))
    assert [(row["method"], "error" in row) for row in document["rows"]] == [("splat", False), ("compact", False)]
    for row in document["rows"]:
        assert row["steps"] >= 1 and row["render_ms_per_frame"] > 0 and row["model_mb"] > 0
        assert np.isfinite([row["psnr"], row["ssim"], row["depth_absrel"]]).all()
        assert (row["lpips"] is None) == bool(row["lpips_note"])  # LPIPS, or why not (its weights absent)
    # the paired difference is the difference of the two means over the same views
    rows = {row["method"]: row for row in document["aggregates"]}
    comparison = document["comparisons"][0]
    assert comparison["n_views"] == 2 and comparison["seeds"] == [0]
    assert comparison["mean_difference"] == pytest.approx(rows["splat"]["mean"]["psnr"] - rows["compact"]["mean"]["psnr"],
                                                          abs=1e-9)
    assert (out / "splat.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = (out / "splat.md").read_text()
    assert f"| primitives | splat | 1 | 1 | {rows['splat']['mean']['psnr']:.2f} [" in table
    # the command it writes parses back to the same configuration
    command = shlex.split(document["command"])
    assert command[:3] == ["nerfgauge", "bench", "splat"] and f"`{document['command']}`" in table
    args = build_parser().parse_args(command[1:])
    assert (args.scenes, args.res, args.views, args.test_views, args.spp, args.budgets, args.seeds, args.threads,
            args.methods, args.geometry_samples, str(args.out)) == \
        (("primitives",), "32x32", 4, 2, 4, (1.0,), (0,), 2, ("splat", "compact"), 2000, str(out))
