"""Gaussian splatting behind the method interface (nerfgauge.methods.builtin.Splat): what
`nerfgauge methods` says it needs, the settings a job may give it, and a job's train, render
and score through the interface (what suites, seeds and the Dask runner call)."""

from __future__ import annotations

import json
import math

import pytest

from nerfgauge.core.errors import InputError
from nerfgauge.methods.interface import TrainRequest
from nerfgauge.methods.registry import resolve


def test_the_methods_command_lists_splat_with_the_colmap_points_it_starts_from(capsys):
    from nerfgauge.cli import main

    assert main(["methods", "--json"]) == 0
    rows = {row["name"]: row for row in json.loads(capsys.readouterr().out)}
    assert rows["splat"]["needs"] == ["transforms", "colmap model", "initial points", "manifest"]
    assert rows["splat"]["produces"] == ["colour", "depth"] and rows["splat"]["learned"] is True


@pytest.mark.parametrize("settings, length, message", [
    ({"seed": 3}, {"steps": 5}, "'seed' is set by the job"),
    ({"lr": 0.1}, {"steps": 5}, "unknown setting 'lr'"),  # a TrainConfig field, not SplatConfig's
    ({"init": "mesh"}, {"steps": 5}, "unknown --init 'mesh'"),
    ({}, {}, "give it steps or a time budget"),
])
def test_a_jobs_settings_are_splat_configs_fields(tmp_path, settings, length, message):
    request = TrainRequest(dataset=tmp_path / "d", run=tmp_path / "r", settings=settings, **length)
    with pytest.raises(InputError, match=message) as error:
        resolve("splat").config(request)
    assert "\n" not in str(error.value)


def test_a_jobs_seed_length_threads_and_settings_reach_the_config(tmp_path):
    request = TrainRequest(dataset=tmp_path / "d", run=tmp_path / "r", seed=4, budget_seconds=7.5, threads=1,
                           settings={"init": "sfm", "sh_degree": 1})
    config = resolve("splat").config(request)
    assert (config.seed, config.budget_seconds, config.steps, config.threads) == (4, 7.5, None, 1)
    assert (config.init, config.sh_degree, config.dataset) == ("sfm", 1, str(tmp_path / "d"))


@pytest.mark.slow
def test_a_job_trains_renders_and_is_scored_with_depth(tiny_dataset, tmp_path):
    from nerfgauge.eval.evaluate import evaluate

    method = resolve("splat")
    result = method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", seed=2, steps=40,
                                       settings={"init": "surface"}))
    assert result.steps == 40 and result.model_bytes == (tmp_path / "run" / "gaussians.ply").stat().st_size
    assert result.extra["gaussians"] > 0 and result.peak_memory_bytes > 0
    assert json.loads((tmp_path / "run" / "config.json").read_text())["seed"] == 2
    rendered = method.render(tmp_path / "run", tiny_dataset, "test", tmp_path / "renders")
    assert rendered.frames == 2 and rendered.pred_format == "nerfgauge"
    scores = evaluate(tiny_dataset, rendered.out, split="test")
    assert math.isfinite(scores["mean"]["psnr"]) and math.isfinite(scores["mean"]["depth_absrel"])


def test_the_initial_points_suite_reads_as_a_builtin_suite():
    """orchestrate/suite/builtin/splat-init.toml: the datasets and scoring of the experiment
    (its arms state their points: tests/test_suite_points.py)."""
    from nerfgauge.orchestrate.suite.definition import builtin_suites, load_suite

    assert "splat-init" in builtin_suites()
    suite = load_suite("splat-init")
    assert [entry.scene for entry in suite.scenes] == ["primitives", "random"]
    for entry in suite.scenes:
        assert (entry.dataset["width"], entry.dataset["views"], entry.dataset["test_views"]) == (128, 50, 10)
    arms = {entry.settings.get("init"): entry.points for entry in suite.methods if entry.method == "splat"}
    assert arms == {"surface": None, "sfm": "sfm", "random": "random", "none": None}
    for init in ("surface", "sfm", "random", "none"):  # each arm a setting the method takes
        assert resolve("splat").config(TrainRequest(dataset="d", run="r", steps=3000, settings={"init": init})).init == init
