"""The wheel a user installs: one top-level name, `nerfgauge`, holding every stage."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPOSITORY = Path(__file__).resolve().parent.parent
SUBPACKAGES = ("core", "scenes", "generate", "nerf", "splat", "eval", "orchestrate")


def can_build_wheels_here() -> bool:
    """This interpreter's setuptools meets pyproject's `setuptools>=68` and has bdist_wheel
    (built in from setuptools 70.1; before that it needs the `wheel` package)."""
    from importlib.metadata import PackageNotFoundError, version
    from importlib.util import find_spec

    try:
        release = tuple(int(part) for part in version("setuptools").split(".")[:2])
    except (PackageNotFoundError, ValueError):
        return False
    return release >= (70, 1) or (release >= (68, 0) and find_spec("wheel") is not None)


@pytest.mark.slow
def test_wheel_installs_only_the_nerfgauge_package(tmp_path):
    # Build from a copy: setuptools writes build/ and *.egg-info into the source tree.
    source = tmp_path / "source"
    shutil.copytree(REPOSITORY, source, ignore=shutil.ignore_patterns(
        ".git", ".venv", ".tox", "build", "*.egg-info", "__pycache__", ".pytest_cache", ".hypothesis", ".benchmarks"))
    wheels = tmp_path / "wheels"
    # The environment's own setuptools when it can build wheels (tox's can); else pip
    # fetches pyproject's build requirements into an isolated build environment.
    isolation = ["--no-build-isolation"] if can_build_wheels_here() else []
    result = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", *isolation, "-q",
                             str(source), "-w", str(wheels)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    (wheel,) = wheels.glob("nerfgauge-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top_level = {name.split("/")[0] for name in names if not name.split("/")[0].endswith(".dist-info")}
    assert top_level == {"nerfgauge"}
    for package in SUBPACKAGES:
        assert any(name.startswith(f"nerfgauge/{package}/") and name.endswith(".py") for name in names), package
    for module in ("nerfgauge/__init__.py", "nerfgauge/api.py", "nerfgauge/cli.py", "nerfgauge/generate/variant.py",
                   "nerfgauge/eval/check.py", "nerfgauge/nerf/train.py", "nerfgauge/scenes/registry.py",
                   "nerfgauge/orchestrate/suite/builtin/smoke.toml"):
        assert module in names, module
    assert not any(name.startswith("nerfgauge/tests/") for name in names)
    entry_points = next(name for name in names if name.endswith(".dist-info/entry_points.txt"))
    assert "nerfgauge = nerfgauge.cli:main" in zipfile.ZipFile(wheel).read(entry_points).decode()
