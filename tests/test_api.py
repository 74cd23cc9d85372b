"""The library API (`import nerfgauge`): lazy exports, the CLI's errors, the CLI's stages."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import types
from pathlib import Path

import pytest

import nerfgauge
from nerfgauge.cli import build_parser, main

REPOSITORY = Path(__file__).resolve().parent.parent


def test_import_is_light_and_has_no_side_effects(tmp_path):
    code = ("import os, sys; before = dict(os.environ); import nerfgauge, nerfgauge.core, nerfgauge.core.errors; "
            "print(sorted(m for m in ('numpy', 'torch', 'mitsuba', 'drjit', 'nerfgauge.api') if m in sys.modules)); "
            "print(dict(os.environ) == before)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=60)
    assert result.stdout.split() == ["[]", "True"], result.stderr
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_the_cli_parses_without_trimesh_or_torch(tmp_path):
    """Every command imports the scene recipes before it parses its arguments; trimesh (1.4 s
    with scipy and networkx) and torch load only in the commands that use them, so a bad
    argument's exit 2 and `--help` come in about a second."""
    code = ("import sys; from nerfgauge.cli import build_parser; build_parser(); "
            "print(sorted(m for m in ('trimesh', 'torch', 'scipy.spatial') if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=60)
    assert result.stdout.split() == ["[]"], result.stderr


def test_exports_stay_functions_after_every_module_is_imported():
    import nerfgauge.api
    import nerfgauge.run  # noqa: F401  (the `nerfgauge run` command's module)

    build_parser()  # imports every stage's commands: nerfgauge.generate and friends become attributes
    for name in nerfgauge.__all__:
        value = getattr(nerfgauge, name)
        assert not isinstance(value, types.ModuleType), name
        assert name in dir(nerfgauge)
    assert issubclass(nerfgauge.InputError, ValueError) and issubclass(nerfgauge.NumericalError, RuntimeError)
    with pytest.raises(AttributeError, match="no attribute 'generate_dataste'"):
        nerfgauge.generate_dataste


@pytest.mark.parametrize("call,names", [
    (lambda out: nerfgauge.generate_dataset("primitives", out, view=3, res=32), "res, view"),
    (lambda out: nerfgauge.generate_dataset("primitives", out, scene="thin"), "scene"),
    (lambda out: nerfgauge.train(out / "data", out, step=3), "step"),
    (lambda out: nerfgauge.run_pipeline("primitives", out, budget=1), "budget"),
])
def test_unknown_options_are_input_errors_naming_them(tmp_path, call, names):
    with pytest.raises(nerfgauge.InputError) as caught:
        call(tmp_path / "out")
    message = str(caught.value)
    assert "\n" not in message and names in message
    assert not (tmp_path / "out").exists()  # refused before anything was written


def _cli_error(argv, capsys) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    prefix = f"nerfgauge {argv[0]}: error: "
    assert err.startswith(prefix) and "\n" not in err, err
    return err[len(prefix):]


def test_api_errors_are_the_cli_messages(tmp_path, capsys):
    missing = str(tmp_path / "missing")
    thresholds = str(REPOSITORY / "thresholds.toml")
    cases = [
        (lambda: nerfgauge.generate_dataset("no-such-scene", tmp_path / "d"),
         ["generate", "no-such-scene", "--out", str(tmp_path / "d")]),
        (lambda: nerfgauge.train(missing, tmp_path / "r", steps=5), ["train", missing, "--out", str(tmp_path / "r"),
                                                                    "--steps", "5"]),
        (lambda: nerfgauge.render(missing), ["render", missing]),
        (lambda: nerfgauge.evaluate(missing, tmp_path), ["evaluate", missing, "--pred", str(tmp_path)]),
        (lambda: nerfgauge.check(missing, thresholds), ["check", missing, "--thresholds", thresholds]),
        # an OSError on the user's path (a folder under a regular file): the same one line
        (lambda: nerfgauge.generate_dataset("primitives", tmp_path / "file" / "d", width=16, height=16, views=2),
         ["generate", "primitives", "--out", str(tmp_path / "file" / "d"), "--res", "16", "--views", "2"]),
    ]
    (tmp_path / "file").write_text("a regular file where a folder is needed")
    for call, argv in cases:
        with pytest.raises(nerfgauge.InputError) as caught:
            call()
        assert str(caught.value) == _cli_error(argv, capsys)


def test_check_takes_documents_or_files_like_the_cli(tmp_path, capsys):
    document = {"schema": 1, "scene": "primitives", "split": "test", "mean": {"psnr": 30.0, "ssim": 0.9}}
    tables = {"*": {"ssim": {"min": 0.95}}, "primitives": {"psnr": {"min": 25.0, "max": 60.0}}}
    results = nerfgauge.check(document, tables)
    assert [(r.metric, r.kind, r.passed) for r in results] == [("ssim", "min", False), ("psnr", "min", True),
                                                              ("psnr", "max", True)]
    assert [r.margin for r in results] == pytest.approx([0.9 - 0.95, 30.0 - 25.0, 60.0 - 30.0])
    metrics_file, thresholds_file = tmp_path / "metrics.json", tmp_path / "thresholds.toml"
    metrics_file.write_text(json.dumps(document))
    thresholds_file.write_text('["*"]\nssim = { min = 0.95 }\n[primitives]\npsnr = { min = 25.0, max = 60.0 }\n')
    assert nerfgauge.check(metrics_file, thresholds_file) == results
    assert main(["check", str(metrics_file), "--thresholds", str(thresholds_file)]) == 1  # the CLI agrees: a failure
    capsys.readouterr()
    with pytest.raises(nerfgauge.InputError) as caught:
        nerfgauge.check(document, tables, scene="no-such-scene")
    assert str(caught.value) == _cli_error(["check", str(metrics_file), "--thresholds", str(thresholds_file),
                                            "--scene", "no-such-scene"], capsys)
    with pytest.raises(nerfgauge.InputError, match="unknown metric 'psnr_db'"):
        nerfgauge.check(document, {"primitives": {"psnr_db": {"min": 1}}})


@pytest.mark.slow
def test_train_render_evaluate_check_on_a_tiny_dataset(tiny_dataset, tmp_path):
    summary = nerfgauge.train(tiny_dataset, tmp_path / "run", steps=3, eval_views=1)
    assert summary["steps"] == 3
    renders = nerfgauge.render(tmp_path / "run")
    assert renders == tmp_path / "run" / "renders"
    assert sorted(p.name for p in (renders / "test").glob("*.png")) == ["r_000.png", "r_001.png"]
    metrics = nerfgauge.evaluate(nerfgauge.Dataset(tiny_dataset), renders, out=tmp_path / "metrics.json")  # or a path
    assert json.loads((tmp_path / "metrics.json").read_text())["mean"] == metrics["mean"]
    assert metrics["scene"] == "primitives" and len(metrics["frames"]) == 2
    results = nerfgauge.check(metrics, {"primitives": {"psnr": {"min": 0.0}, "depth_delta1": {"max": 1.0}}})
    assert all(result.passed for result in results) and len(results) == 2


def readme_example() -> str:
    """The first ```python block of the Python API page (docs/reference/api.md; README's
    "Python API" section until issue 51 moved it there)."""
    text = (REPOSITORY / "docs" / "reference" / "api.md").read_text()
    match = re.search(r"```python\n(.*?)```", text, re.S)
    assert match, "docs/reference/api.md has no ```python block"
    return match.group(1)


@pytest.mark.slow  # generates a dataset and trains 20 steps: well over 5 s
def test_readme_example_runs_as_written(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    exec(compile(readme_example(), str(REPOSITORY / "docs" / "reference" / "api.md"), "exec"), {"__name__": "__main__"})
    out = capsys.readouterr().out
    assert (tmp_path / "tiny" / "data" / "manifest.json").is_file()
    assert (tmp_path / "tiny" / "run" / "renders" / "metrics.json").is_file()
    assert "gate: " in out
