"""Shared fixtures: the Mitsuba variant (set once, like Mitsuba's own test fixtures) and
small generated datasets, made once per session and shared read-only."""

from __future__ import annotations

import subprocess
import uuid
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def mi():
    """Mitsuba with the variant `auto` resolves to on this machine (llvm_ad_rgb here)."""
    from nerfgauge.generate.variant import resolve_variant, use_variant

    return use_variant(resolve_variant("auto"))


def generate_small(out, scene="primitives", **overrides):
    """Generate a tiny dataset in-process; returns its folder."""
    from nerfgauge.generate.pipeline import GenerateConfig, generate

    settings = dict(scene=scene, views=4, val_views=1, test_views=2, width=32, height=32, spp=4)
    settings.update(overrides)
    generate(GenerateConfig(**settings), out, progress=False)
    return out


@pytest.fixture(scope="session")
def make_dataset():
    """The in-process generator with tiny defaults: make_dataset(out, scene=..., **config)."""
    return generate_small


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """primitives, 4/1/2 views at 32x32, 4 spp: enough for format and depth checks."""
    return generate_small(tmp_path_factory.mktemp("datasets") / "primitives")


# --------------------------------------------------------------------------------------
# the fuzz seed: fresh hostile cases every run, reproducible from the printed seed

FUZZ_SEED_ENV = "NERFGAUGE_FUZZ_SEED"


def pytest_addoption(parser):
    parser.addoption("--fuzz-seed", type=int, default=None,
                     help=f"seed of the fuzz suite's fresh cases (default: ${FUZZ_SEED_ENV}, else a new random "
                          "seed, printed in the header and the summary)")
    parser.addoption("--record-file-seconds", metavar="PATH", default=None,
                     help=f"write each test file's seconds (setup + call + teardown, summed) to PATH as JSON: "
                          f"what {FILE_SECONDS.name} holds, measured on an idle machine")


# --------------------------------------------------------------------------------------
# longest files first: `-n auto --dist loadfile` gives each worker whole files, and a worker
# that draws an 8-minute file last keeps the run waiting while the other idles. xdist's own
# order (--loadscope-reorder, its default) puts the files with the most tests first, which
# put the slowest files, each a handful of long tests, last. tox.ini passes
# --no-loadscope-reorder and the files run in the order below: the longest first by
# FILE_SECONDS (a measured run's seconds a file, `--record-file-seconds`), a file it does not
# list first of all (new, so of unknown length), each file's tests in their own order.

FILE_SECONDS = Path(__file__).with_name("file_seconds.json")


def pytest_collection_modifyitems(config, items):
    import json

    seconds = json.loads(FILE_SECONDS.read_text()) if FILE_SECONDS.is_file() else {}
    unknown = float("inf")
    position = {}
    for index, item in enumerate(items):
        position.setdefault(item.nodeid.split("::", 1)[0], index)
    items.sort(key=lambda item: (-seconds.get(item.nodeid.split("::", 1)[0], unknown),
                                 position[item.nodeid.split("::", 1)[0]]))


_FILE_TOTALS: dict = {}
_FAST_SECONDS: dict = {}
FAST_LIMIT = 4.0  # seconds: a test past it carries @pytest.mark.slow (`tox -e scalar` runs the rest)


def pytest_runtest_logreport(report):
    """Sum each file's seconds and each unmarked test's (on xdist's controller, every
    worker's reports arrive here)."""
    path = report.nodeid.split("::", 1)[0]
    _FILE_TOTALS[path] = _FILE_TOTALS.get(path, 0.0) + report.duration
    if "slow" not in report.keywords:
        _FAST_SECONDS[report.nodeid] = _FAST_SECONDS.get(report.nodeid, 0.0) + report.duration


def pytest_sessionfinish(session):
    import json

    target = session.config.getoption("--record-file-seconds")
    if target and not hasattr(session.config, "workerinput"):  # the controller (or a run without xdist)
        ordered = dict(sorted(((k, round(v, 1)) for k, v in _FILE_TOTALS.items()), key=lambda kv: -kv[1]))
        Path(target).write_text(json.dumps(ordered, indent=1) + "\n")


def pytest_configure(config):
    """Fix the run's fuzz seed before test modules are imported: --fuzz-seed, else
    $NERFGAUGE_FUZZ_SEED, else a fresh random one. It is put in the environment, where
    tests/fuzzing.fuzz_seed() (and any subprocess) reads it."""
    import os
    import secrets

    seed = config.getoption("--fuzz-seed")
    if seed is None:
        seed = int(os.environ.get(FUZZ_SEED_ENV) or secrets.randbits(32))
    os.environ[FUZZ_SEED_ENV] = str(seed)
    config.addinivalue_line("markers", "fuzz_fresh: draws new cases from the run's fuzz seed (printed)")


def _seed_line() -> str:
    import os

    seed = os.environ[FUZZ_SEED_ENV]
    return f"nerfgauge fuzz seed: {seed} (rerun the same fresh cases: {FUZZ_SEED_ENV}={seed} or --fuzz-seed {seed})"


def pytest_report_header(config):
    return _seed_line()


def pytest_terminal_summary(terminalreporter):
    slow = sorted(((seconds, nodeid) for nodeid, seconds in _FAST_SECONDS.items() if seconds > FAST_LIMIT),
                  reverse=True)
    for seconds, nodeid in slow:  # the fast pass (scalar) reruns every unmarked test: keep it fast
        terminalreporter.write_line(f"unmarked test over {FAST_LIMIT:.0f} s: {nodeid} ({seconds:.1f} s): "
                                    "mark it @pytest.mark.slow, or make it smaller")
    terminalreporter.write_line(_seed_line())  # also under -q, which hides the header


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """A failing fresh fuzz case names the seed that reproduces it."""
    outcome = yield
    report = outcome.get_result()
    if report.failed and item.get_closest_marker("fuzz_fresh"):
        report.sections.append(("nerfgauge fuzz seed", _seed_line()))


@pytest.fixture
def mount_tmpfs(tmp_path):
    """mount_tmpfs(options) -> a fresh tmpfs under tmp_path (unmounted afterwards); skips
    where mounting is not allowed (not root, no CAP_SYS_ADMIN)."""
    mounted = []

    def mount(options: str) -> Path:
        point = tmp_path / f"mnt-{uuid.uuid4().hex[:6]}"
        point.mkdir()
        result = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(point)], capture_output=True)
        if result.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {result.stderr.decode().strip()}")
        mounted.append(point)
        return point

    yield mount
    for point in mounted:
        subprocess.run(["umount", str(point)], check=True)
