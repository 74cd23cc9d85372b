"""One configuration story: each stage's flags are defined once beside its frozen config
(generate/options.py, nerf/options.py, eval/options.py) and `nerfgauge run` composes them;
the flags read back as the configs' fields, and `run` builds the same TrainConfig and
EvaluateConfig as `train` and `evaluate` do from the same words."""

from __future__ import annotations

import argparse
import ast
import dataclasses
from pathlib import Path

import pytest

import nerfgauge
from nerfgauge.cli import build_parser
from nerfgauge.core.errors import InputError
from nerfgauge.eval.evaluate import EvaluateConfig
from nerfgauge.nerf.config import AUTO, DEFAULT_BUDGET_SECONDS, FLAGS, SWITCH, TrainConfig
from nerfgauge.nerf.options import train_fields
from nerfgauge.run import RunConfig
from nerfgauge.splat.config import OWN_FLAGS as SPLAT_OWN_FLAGS

REPOSITORY = Path(__file__).resolve().parent.parent
# train's flags that `run` has no use for: the run folder (--out names OUT/run's parent there,
# with its own meaning) and continuing one (--resume: `run` reruns only with --overwrite).
TRAIN_FOLDER_FLAGS = {"--out", "--resume"}
# `train --model splat`'s own flags: SplatConfig's (splat.config), refused for a NeRF; `run`
# trains a NeRF only
SPLAT_FLAGS = {flag for flag, _, _ in SPLAT_OWN_FLAGS.values()}


def subcommand(name: str) -> argparse.ArgumentParser:
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices[name]


def flags(parser: argparse.ArgumentParser) -> set:
    return {flag for action in parser._actions for flag in action.option_strings}


def test_run_takes_every_train_flag_and_every_scoring_flag():
    """run's flags include train's, but for those of the run folder; and evaluate's scoring
    ones (--protocol among them), which --help offers."""
    run, train, evaluate = subcommand("run"), subcommand("train"), subcommand("evaluate")
    not_run = TRAIN_FOLDER_FLAGS | SPLAT_FLAGS
    assert flags(train) - not_run <= flags(run), sorted(flags(train) - not_run - flags(run))
    scoring = {"--background", "--protocol", "--no-held-out"}
    assert scoring <= flags(evaluate) and scoring <= flags(run)
    assert "--protocol" in run.format_help() and "--refine-grid" in run.format_help()


def test_every_train_flag_is_a_config_fields_and_reads_back_as_it():
    """Each training flag (but --out, --resume, --overwrite, --quiet, --help) sets the
    TrainConfig field whose metadata names it (nerf.config.FLAGS)."""
    train = subcommand("train")
    by_flag = {flag: action.dest for action in train._actions for flag in action.option_strings}
    own = {"--out", "--resume", "--overwrite", "--quiet", "-h", "--help"} | SPLAT_FLAGS
    assert {flag: by_flag[flag] for flag in set(by_flag) - own} == {flag: name for name, flag in FLAGS.items()}


@pytest.mark.parametrize("name", [name for name, flag in FLAGS.items() if name in
                                  {f.name for f in dataclasses.fields(TrainConfig) if "words" in f.metadata}])
def test_a_flags_words_map_to_the_fields_values_through_one_table(name):
    """auto is None (the data decides) for every worded field; a switch's on and off are True
    and False; the flag's default is the word of the field's default."""
    words = next(f.metadata["words"] for f in dataclasses.fields(TrainConfig) if f.name == name)
    assert words in (AUTO, SWITCH)
    parser = subcommand("train")
    assert parser.get_default(name) == "auto"
    for word, value in words.items():
        args = parser.parse_args(["d", "--out", "r", FLAGS[name], word])
        assert train_fields(args)[name] is value


def test_run_and_train_read_the_same_words_into_the_same_train_config(monkeypatch):
    """The same training flags given to `train` and to `run` make the same TrainConfig (but
    its dataset, OUT/dataset for `run`); `run` records only what differs from the defaults."""
    argv = ["--threads", "1", "--pixel-filter", "centre", "--refine-grid", "off", "--resolution", "48",
            "--no-prune", "--eval-every", "2.5", "--steps", "30", "--seed", "3", "--sparse-priors", "on"]
    train_args = subcommand("train").parse_args(["data", "--out", "r", *argv])
    from_train = TrainConfig(dataset="data", **train_fields(train_args))
    captured = {}
    monkeypatch.setattr("nerfgauge.run.run_pipeline", lambda config, **_: captured.setdefault("config", config))
    parser = build_parser()
    args = parser.parse_args(["run", "--out", "o", *argv])
    assert args.func(args) == 0
    config = captured["config"]
    assert config.train_options == {"threads": 1, "pixel_filter": "centre", "refine_grid": False,
                                    "final_resolution": 48, "prune": False, "eval_every_seconds": 2.5,
                                    "sparse_priors": True}
    assert dataclasses.replace(config.train_config(), dataset="data") == from_train
    assert config.evaluate_options == {}


def test_run_scores_as_evaluate_does_from_the_same_words(monkeypatch):
    argv = ["--background", "black", "--protocol", "ns-eval", "--no-held-out"]
    evaluate_args = subcommand("evaluate").parse_args(["data", "--pred", "p", *argv])
    from nerfgauge.eval.options import evaluate_fields

    from_evaluate = EvaluateConfig(**evaluate_fields(evaluate_args))
    captured = {}
    monkeypatch.setattr("nerfgauge.run.run_pipeline", lambda config, **_: captured.setdefault("config", config))
    args = build_parser().parse_args(["run", "--out", "o", *argv])
    args.func(args)
    assert captured["config"].evaluate_options == {"background": "black", "protocol": "ns-eval", "held_out": False}
    assert captured["config"].evaluate_config() == from_evaluate
    with pytest.raises(InputError, match="unknown scoring option split"):
        RunConfig(evaluate_options={"split": "val"}).evaluate_config()  # run renders and scores the test split


def test_one_default_budget_on_train_config():
    """Neither steps nor a budget: TrainConfig's DEFAULT_BUDGET_SECONDS (120 s, what the
    benches use), for `train`, `run`, the API and RunConfig alike; steps: no budget."""
    assert DEFAULT_BUDGET_SECONDS == 120.0
    assert TrainConfig("d").budget_seconds == DEFAULT_BUDGET_SECONDS
    assert TrainConfig("d", steps=5).budget_seconds is None
    args = subcommand("train").parse_args(["d", "--out", "r"])
    assert TrainConfig("d", **train_fields(args)).budget_seconds == DEFAULT_BUDGET_SECONDS
    assert RunConfig().train_config().budget_seconds == DEFAULT_BUDGET_SECONDS
    assert RunConfig(steps=4).train_config().budget_seconds is None
    assert "training time (default 120)" in " ".join(subcommand("run").format_help().split())
    with pytest.raises(InputError, match="not both"):
        TrainConfig("d", steps=5, budget_seconds=10.0).validate()


def test_the_api_routes_each_stages_options_and_refuses_unknown_ones(monkeypatch, tmp_path):
    """run_pipeline's keywords: a generator field to generate_options, a scoring field to
    evaluate_options, any other TrainConfig field to train_options (TrainConfig's width,
    shadowed by the image width, through train_options itself)."""
    captured = {}
    monkeypatch.setattr("nerfgauge.run.run_pipeline", lambda config, **_: captured.setdefault("config", config))
    nerfgauge.run_pipeline("primitives", tmp_path / "o", fov=50.0, threads=1, protocol="ns-eval", steps=3,
                           train_options={"width": 64}, width=32)
    config = captured["config"]
    assert (config.generate_options, config.evaluate_options) == ({"fov": 50.0}, {"protocol": "ns-eval"})
    assert config.train_options == {"width": 64, "threads": 1} and config.width == 32 and config.steps == 3
    assert config.train_config().width == 64 and config.generate_config().width == 32
    with pytest.raises(InputError, match="unknown option"):
        nerfgauge.run_pipeline("primitives", tmp_path / "o", no_such_option=1)
    with pytest.raises(InputError, match="unknown training option dataset"):
        RunConfig(train_options={"dataset": "elsewhere"}).train_config()


def test_evaluate_reads_every_option_as_a_flag_not_a_fallback():
    """eval/commands.py reads no option through getattr(args, ...): each command's
    arguments are its own parser's, and baseline --evaluate builds an EvaluateConfig."""
    tree = ast.parse((REPOSITORY / "eval" / "commands.py").read_text())
    fallbacks = [node.lineno for node in ast.walk(tree)
                 if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "getattr"
                 and node.args and isinstance(node.args[0], ast.Name) and node.args[0].id == "args"]
    assert fallbacks == []
