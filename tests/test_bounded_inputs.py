"""Bounded inputs (issue 31, deliver 5): values no parser or library should meet unbounded.

One section per class, each with the issue's example as a fixed case, fuzz families drawn
by hypothesis twice (derandomized: the fixed regression cases; `_fresh`: new cases every
run from the fuzz seed printed in pytest's header and summary), and a control that a value
inside the bound still works:

- nesting depth of JSON and TOML (a RecursionError traceback; in `check`, exit 1);
- file size of JSON and TOML (read before any check);
- numeric flags out of range (`train --step-ratio 1e-9`: OverflowError), for every numeric
  flag of every command, taken from the argparse parser itself; their ranges in --help;
- paths that are not UTF-8 (Mitsuba's path conversion crashed);
- compressed and self-describing files that inflate or declare more than a frame holds
  (.npy.gz depth, .npy headers, EXR channel counts);
- radiance that overflows float32 while rendering (an envmap pixel of 1e30).

Every refusal is judged as the rest of the suite does (tests/fuzzing.judge): exit 2, one
stderr line `nerfgauge <cmd>: error: ...`, no traceback, nothing changed outside the
command's output folder, which must not even be created.
"""

from __future__ import annotations

import argparse
import gzip
import io
import itertools
import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from fuzzing import REFUSE, Case, assert_judged, copy_tree, exr_bytes, exr_with_data_window, fresh_twin, \
    png_declaring, rehash_manifest, run_cli, write_raw
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from nerfgauge.core import arguments, bounded, validate
from nerfgauge.core.errors import InputError

FAST = dict(deadline=None, derandomize=True, database=None, phases=(Phase.explicit, Phase.generate),
            suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
_numbers = itertools.count()


def _folder(tmp_path_factory, family: str) -> Path:
    return tmp_path_factory.mktemp(f"{family}{next(_numbers)}")


def refused(command: str, argv, cwd: Path, out: Path, what: str, shared=(), message: str | None = None) -> str:
    """Run and judge a case that must be refused; the output must not exist afterwards.
    Returns the stderr line."""
    case = Case(command, list(argv), cwd, out, what, expect=REFUSE, shared=tuple(shared))
    assert_judged(case)
    assert case.outcome.code == 2, f"{what}: exit {case.outcome.code}, stdout {case.outcome.stdout[-300:]!r}"
    assert not out.exists(), f"{what}: the refused command created {out}"
    if message is not None:
        assert message in case.outcome.stderr, f"{what}: {case.outcome.stderr!r} does not say {message!r}"
    return case.outcome.stderr.strip()


def log_uniform(low_exp: float, high_exp: float):
    """Positive floats whose base-10 exponent is uniform in [low_exp, high_exp]."""
    return st.floats(low_exp, high_exp).map(lambda e: 10.0 ** e)


# --------------------------------------------------------------------------------------
# nesting depth and size of JSON and TOML


def nested_json(depth: int, opener: str) -> str:
    """A JSON value nesting `depth` levels: "[[[...]]]", '{"a":{"a":...}}' or both mixed."""
    if opener == "list":
        return "[" * depth + "]" * depth
    if opener == "object":
        return '{"a":' * depth + "1" + "}" * depth
    return '{"a":[' * (depth // 2) + "1" + "]}" * (depth // 2)


def nested_toml(depth: int, form: str) -> str:
    """A TOML document nesting `depth` levels by arrays, inline tables or dotted keys."""
    if form == "array":
        return "a = " + "[" * depth + "]" * depth + "\n"
    if form == "inline":
        return "a = " + "{b = " * depth + "1" + "}" * depth + "\n"
    return "a" + ".b" * depth + " = 1\n"


def metrics_and_thresholds(folder: Path) -> tuple[Path, Path]:
    metrics = folder / "metrics.json"
    metrics.write_text(json.dumps({"schema": 1, "scene": "primitives", "mean": {"psnr": 30.0}}))
    thresholds = folder / "thresholds.toml"
    thresholds.write_text('["*"]\npsnr = { min = 20.0 }\n')
    return metrics, thresholds


def test_check_passes_on_the_undamaged_pair(tmp_path):
    """The control of the check cases: the pair they damage passes (exit 0)."""
    metrics, thresholds = metrics_and_thresholds(tmp_path)
    outcome = run_cli(["check", metrics, "--thresholds", thresholds], tmp_path)
    assert outcome.code == 0, outcome


def test_deep_json_in_check_is_exit_2_not_a_failed_bound(tmp_path):
    """The issue's example: a metrics.json of 100,000 "[" ended in a RecursionError
    traceback with exit 1, which CI reads as "a bound failed"."""
    metrics, thresholds = metrics_and_thresholds(tmp_path)
    metrics.write_text(nested_json(100_000, "list"))
    line = refused("check", ["check", metrics, "--thresholds", thresholds, "--junit", tmp_path / "junit.xml"],
                   tmp_path, tmp_path / "junit.xml", "metrics.json 100,000 levels deep")
    assert f"at most {bounded.MAX_NESTING}" in line


def test_deep_toml_thresholds_is_exit_2(tmp_path):
    metrics, thresholds = metrics_and_thresholds(tmp_path)
    thresholds.write_text(nested_toml(50_000, "array"))
    refused("check", ["check", metrics, "--thresholds", thresholds], tmp_path, tmp_path / "out",
            "thresholds.toml 50,000 levels deep", message="TOML nests")


def test_the_depth_limit_is_where_it_says(tmp_path):
    """MAX_NESTING levels parse (JSON and TOML, brackets inside strings and comments do not
    count); one more is refused."""
    depth = bounded.MAX_NESTING
    assert bounded.loads_json(nested_json(depth, "list"), "x") is not None
    assert bounded.loads_json('{"s": "' + "[" * 10_000 + '"}', "x") == {"s": "[" * 10_000}
    assert bounded.loads_toml(nested_toml(depth - 1, "array") + "# " + "[" * 500 + "\ns = '" + "{" * 500 + "'\n", "x")
    assert bounded.loads_toml(nested_toml(depth - 1, "dotted"), "x")
    for text, load in ((nested_json(depth + 1, "list"), bounded.loads_json),
                       (nested_toml(depth, "array"), bounded.loads_toml),
                       (nested_toml(depth, "dotted"), bounded.loads_toml)):
        with pytest.raises(InputError, match="nests"):
            load(text, "x")


def test_oversized_json_and_toml_are_refused_before_reading(tmp_path):
    """Sparse files just above the limits: refused on their size, not parsed (a 64 MiB
    metrics.json of spaces would parse; the check must come first)."""
    metrics, thresholds = metrics_and_thresholds(tmp_path)
    with open(metrics, "r+b") as handle:
        handle.truncate(bounded.MAX_JSON_BYTES + 1)
    refused("check", ["check", metrics, "--thresholds", thresholds], tmp_path, tmp_path / "out",
            "metrics.json above MAX_JSON_BYTES", message="above the limit")
    metrics, thresholds = metrics_and_thresholds(tmp_path)
    with open(thresholds, "r+b") as handle:
        handle.truncate(bounded.MAX_TOML_BYTES + 1)
    refused("check", ["check", metrics, "--thresholds", thresholds], tmp_path, tmp_path / "out",
            "thresholds.toml above MAX_TOML_BYTES", message="above the limit")


DEEP_TARGETS = ("check-metrics", "check-thresholds", "scene-toml", "scene-json", "dataset-transforms", "suite-toml")


@pytest.mark.parametrize("target", DEEP_TARGETS)
@given(data=st.data())
@settings(max_examples=2, **FAST)
def test_deeply_nested_documents_are_refused(tmp_path_factory, tiny_dataset, renders, target, data):
    depth = data.draw(st.one_of(st.integers(bounded.MAX_NESTING + 1, 2_000), st.integers(2_000, 200_000)), label="depth")
    folder = _folder(tmp_path_factory, "deep")
    out = folder / "out"
    if target.startswith("check"):
        metrics, thresholds = metrics_and_thresholds(folder)
        if target == "check-metrics":
            metrics.write_text(nested_json(depth, data.draw(st.sampled_from(["list", "object", "mixed"]))))
        else:
            thresholds.write_text(nested_toml(depth, data.draw(st.sampled_from(["array", "inline", "dotted"]))))
        out = folder / "junit.xml"
        refused("check", ["check", metrics, "--thresholds", thresholds, "--junit", out], folder, out,
                f"{target} {depth} deep", message="nests")
    elif target.startswith("scene"):
        if target == "scene-toml":
            scene = folder / "scene.toml"
            scene.write_text("version = 1\n" + nested_toml(depth, data.draw(st.sampled_from(["array", "inline", "dotted"]))))
        else:
            scene = folder / "scene.json"
            scene.write_text('{"version": 1, "x": ' + nested_json(depth, "mixed") + "}")
        refused("generate", ["generate", scene, "--out", out, "--res", "8", "--views", "1", "--spp", "1"], folder,
                out, f"{target} {depth} deep", message="nests")
    elif target == "suite-toml":
        suite = folder / "deep.toml"
        suite.write_text(nested_toml(depth, data.draw(st.sampled_from(["array", "inline", "dotted"]))))
        refused("suite", ["suite", "generate", suite, "--out", out], folder, out, f"suite file {depth} deep",
                message="nests")
    else:
        ds = copy_tree(tiny_dataset, folder / "ds")
        write_raw(ds / "transforms_test.json", nested_json(depth, data.draw(st.sampled_from(["list", "object"]))).encode())
        rehash_manifest(ds)
        pred = copy_tree(renders, folder / "pred")
        refused("evaluate", ["evaluate", ds, "--pred", pred, "--out", out / "metrics.json"], folder, out,
                f"transforms_test.json {depth} deep", message="nests")


# --------------------------------------------------------------------------------------
# numeric flags: every one of every command, from the parser itself


def numeric_flags() -> list[tuple[tuple, str, object]]:
    """(subcommand words, option string, its Range) for every option whose type is a
    number (a Range, or a list or pair type carrying one as `.range`)."""
    from nerfgauge.cli import build_parser

    found = []

    def walk(parser, words):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, words + (name,))
            elif action.option_strings and action.type is not None:
                limits = getattr(action.type, "range", action.type)
                if isinstance(limits, arguments.Range):
                    found.append((words, action.option_strings[-1], limits))

    walk(build_parser(), ())
    return found


NUMERIC_FLAGS = numeric_flags()
_ID = [f"{' '.join(words)} {flag}" for words, flag, _ in NUMERIC_FLAGS]


def test_every_numeric_flag_is_range_checked_and_says_its_range_in_help():
    """Every option with a type is a path, a name list or a checked range (no bare int or
    float, no unbounded positive_int), and --help shows the range."""
    from nerfgauge.cli import build_parser

    known = {arguments.path, arguments.spp}
    unbounded = []

    def walk(parser, words):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, words + (name,))
            elif action.type is not None and action.type not in known:
                limits = getattr(action.type, "range", action.type)
                if not isinstance(limits, arguments.Range) and getattr(action.type, "__name__", "") != "names":
                    unbounded.append(f"{' '.join(words)} {action.option_strings or action.dest}")
                elif isinstance(limits, arguments.Range):
                    shown = " ".join(parser.format_help().split())
                    assert limits.text in shown, f"{' '.join(words)} {action.option_strings}: no range in --help"

    walk(build_parser(), ())
    assert not unbounded, f"numeric options without a range: {unbounded}"
    assert len(NUMERIC_FLAGS) >= 80  # the parser walk found them all (88 when written)


def outside(limits: arguments.Range, data) -> str:
    """A value outside `limits`, drawn across magnitudes: just past a bound, far past it
    (up to 1e300 and 1e-300), or negative, as text."""
    kind = data.draw(st.sampled_from(["far-above", "just-above", "far-below", "just-below", "tiny"]), label="where")
    if kind == "far-above" or kind == "just-above" and limits.kind is float:
        value = limits.high * (1 + 1e-9) + 1e-9 if kind == "just-above" else data.draw(log_uniform(math.log10(limits.high) + 0.01, 300))
    elif kind == "just-above":
        value = int(limits.high) + 1 if limits.kind is int else limits.high
    elif kind == "far-below":
        value = -data.draw(log_uniform(math.log10(max(abs(limits.low), 1e-300)) + 0.01, 300)) if limits.low >= 0 else \
            -data.draw(log_uniform(math.log10(abs(limits.low)) + 0.01, 300))
    elif kind == "just-below":
        value = (limits.low if limits.above else limits.low - (1 if limits.kind is int else abs(limits.low) * 1e-9 + 1e-9))
    else:  # a tiny positive number: outside unless the range holds it
        value = data.draw(log_uniform(-300, -12))
        if limits.contains(value):
            value = -value if not limits.contains(-value) else limits.high * 10 + 1
    if limits.kind is int:
        value = int(value) if abs(value) < 1e18 else int(math.copysign(10**18, value)) * 10**int(data.draw(st.integers(0, 5)))
        if limits.contains(value):
            value = int(limits.high) + 1
        return str(value)
    assert not limits.contains(value), (value, limits)
    return repr(value)


@pytest.mark.parametrize("words, flag, limits", NUMERIC_FLAGS, ids=_ID)
@given(data=st.data())
@settings(max_examples=3, **FAST)
def test_numeric_flags_out_of_range_are_refused(tmp_path_factory, words, flag, limits, data):
    """Each out-of-range value is an argument error naming the flag and its range, exit
    2, before anything is read or written (the command's positionals are not even given)."""
    text = outside(limits, data)
    if flag == "--elevation":  # a MIN,MAX pair
        text = f"{text},{text}"
    folder = _folder(tmp_path_factory, "flag")
    outcome = run_cli([*words, f"{flag}={text}"], folder)
    assert outcome.escaped is None and outcome.code == 2, (flag, text, outcome)
    lines = outcome.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"nerfgauge {words[0]}") and f"argument {flag}" in lines[0] \
        and limits.text in lines[0], (flag, text, lines)
    assert not any(folder.iterdir())


@pytest.mark.parametrize("words, flag, limits", NUMERIC_FLAGS, ids=_ID)
@given(data=st.data())
@settings(max_examples=2, **FAST)
def test_numeric_flags_in_range_are_accepted(words, flag, limits, data):
    """The control: a value inside the range parses to itself."""
    if limits.kind is int:
        value = data.draw(st.integers(int(limits.low) + limits.above, int(limits.high) - limits.below))
    else:
        value = data.draw(st.floats(limits.low, limits.high, exclude_min=limits.above, exclude_max=limits.below))
    assert limits(repr(value) if limits.kind is float else str(value)) == value


def test_the_issues_step_ratio_example_and_the_api_share_the_range(tmp_path, tiny_dataset):
    """`train --step-ratio 1e-9` was an OverflowError traceback; now one line, and the run
    folder is not created. TrainConfig and GenerateConfig check the same ranges."""
    from nerfgauge.generate.pipeline import GenerateConfig
    from nerfgauge.nerf.config import TrainConfig

    line = refused("train", ["train", tiny_dataset, "--out", tmp_path / "run", "--step-ratio", "1e-9", "--steps", "1"],
                   tmp_path, tmp_path / "run", "train --step-ratio 1e-9", shared=(tiny_dataset,))
    assert "from 0.05 to 2" in line
    with pytest.raises(InputError, match=r"--step-ratio must be a number from 0.05 to 2, got 1e-09"):
        TrainConfig(dataset=str(tiny_dataset), steps=1, step_ratio=1e-9).validate()
    with pytest.raises(InputError, match=r"--seed must be an integer from 0 to 2147483647"):
        TrainConfig(dataset=str(tiny_dataset), steps=1, seed=2**40).validate()
    with pytest.raises(InputError, match=r"--views must be an integer from 1 to 100000"):
        GenerateConfig(views=10**7).validate()
    with pytest.raises(InputError, match=r"--elevation must be a number from -90 to 90"):
        GenerateConfig(elevation=(-100.0, 10.0)).validate()


def test_a_resolution_of_thousands_of_digits_is_one_line(tmp_path):
    """int() refuses strings of more than 4300 digits with a ValueError of its own."""
    refused("generate", ["generate", "primitives", "--res", "9" * 5000, "--out", tmp_path / "out"], tmp_path,
            tmp_path / "out", "--res of 5000 digits")
    refused("generate", ["generate", "primitives", "--res", "100000x8", "--out", tmp_path / "out"], tmp_path,
            tmp_path / "out", "--res 100000x8", message="1 to 8192")


# --------------------------------------------------------------------------------------
# paths that are not UTF-8

NOT_UTF8 = [b"\xff", b"\xfe\xfe", b"\xc3(", b"\x80", b"\xed\xa0\x80", b"\xf8\x88\x80\x80\x80", b"a\xe9b"]
PATH_TARGETS = ("generate-out", "generate-mesh", "generate-envmap", "generate-scene-json", "train-out", "evaluate-dataset")


def _bytes_path(folder: Path, name: bytes) -> Path:
    return Path(os.fsdecode(os.fsencode(folder) + b"/" + name))


@pytest.mark.parametrize("target", PATH_TARGETS)
@given(data=st.data())
@settings(max_examples=2, **FAST)
def test_paths_that_are_not_utf8_are_refused(tmp_path_factory, tiny_dataset, target, data):
    """Each path exists where it names a file (so only its encoding is wrong); Mitsuba's
    path conversion crashed on it, now it is refused with one line where it enters."""
    bad = data.draw(st.sampled_from(NOT_UTF8), label="bytes")
    folder = _folder(tmp_path_factory, "path")
    out = folder / "out"
    if target == "generate-out":
        out = _bytes_path(folder, b"ds" + bad)
        argv = ["generate", "primitives", "--out", out, "--res", "8", "--views", "1", "--spp", "1"]
    elif target in ("generate-mesh", "generate-scene-json"):
        import trimesh

        mesh = _bytes_path(folder, b"tile" + bad + b".ply")
        write_raw(mesh, trimesh.creation.box().export(file_type="ply"))
        if target == "generate-mesh":
            argv = ["generate", f"mesh:{mesh}", "--out", out, "--res", "8", "--views", "1", "--spp", "1"]
        else:  # a JSON scene file can name it with a surrogate escape ("\udcff")
            scene = folder / "scene.json"
            scene.write_text(json.dumps({"version": 1, "asset": [{"path": mesh.name}]}))
            argv = ["generate", scene, "--out", out, "--res", "8", "--views", "1", "--spp", "1"]
    elif target == "generate-envmap":
        envmap = _bytes_path(folder, b"sky" + bad + b".exr")
        write_raw(envmap, exr_bytes({"RGB": np.ones((4, 8, 3), np.float32)}))
        argv = ["generate", "primitives", "--envmap", envmap, "--out", out, "--res", "8", "--views", "1", "--spp", "1"]
    elif target == "train-out":
        out = _bytes_path(folder, b"run" + bad)
        argv = ["train", tiny_dataset, "--out", out, "--steps", "1", "--quiet"]
    else:
        ds = copy_tree(tiny_dataset, _bytes_path(folder, b"ds" + bad))
        argv = ["evaluate", ds, "--pred", folder, "--out", out / "metrics.json"]
    refused(argv[0], argv, folder, out, f"{target} with {bad!r}", shared=(tiny_dataset,), message="not valid UTF-8")


# --------------------------------------------------------------------------------------
# files that inflate or declare more than a frame holds


def gzip_inflating_to(size: int) -> bytes:
    """A gzip member of `size` zero bytes after a valid .npy header declaring them
    (compressed about 1000:1: 256 MiB makes a 256 kB file)."""
    buffer, header = io.BytesIO(), io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (size // 8,)})
    with gzip.GzipFile(fileobj=buffer, mode="wb", compresslevel=9) as handle:
        handle.write(header.getvalue())  # magic, version and header
        block = bytes(1 << 20)
        for _ in range(size // len(block)):
            handle.write(block)
    return buffer.getvalue()


def nerfstudio_prediction(folder: Path, tiny_dataset: Path, pred_run: Path) -> Path:
    """An ns-render layout of the tiny dataset's test views: test/rgba/r_00k.png and
    test/raw-depth/r_00k.npy.gz (valid ones)."""
    pred = folder / "ns"
    (pred / "test" / "rgba").mkdir(parents=True)
    (pred / "test" / "raw-depth").mkdir()
    from nerfgauge.core.images import read_exr_single

    for png in sorted(pred_run.rglob("r_*[0-9].png")):
        shutil.copyfile(png, pred / "test" / "rgba" / png.name)
        depth = read_exr_single(png.with_name(png.stem + "_depth.exr"))[..., None]  # [H, W, 1]
        buffer = io.BytesIO()
        np.save(buffer, depth)
        (pred / "test" / "raw-depth" / (png.stem + ".npy.gz")).write_bytes(gzip.compress(buffer.getvalue()))
    return pred


@pytest.fixture(scope="module")
def renders(tmp_path_factory, tiny_dataset):
    """A 2-step run's test renders of the tiny dataset (valid predictions to corrupt)."""
    folder = tmp_path_factory.mktemp("renders")
    for argv in (["train", tiny_dataset, "--out", folder / "run", "--steps", "2", "--quiet"],
                 ["render", folder / "run", "--out", folder / "pred", "--quiet"]):
        assert run_cli(argv, folder).code == 0
    return folder / "pred"


@pytest.mark.slow
def test_a_small_gzip_depth_that_inflates_to_gigabytes_is_refused_while_inflating(tmp_path, tiny_dataset, renders):
    """The issue's example: a nerfstudio raw-depth .npy.gz of 1 MB inflating to 1 GiB was
    read whole. It is refused as soon as the inflated bytes pass what a 32x32 depth holds."""
    pred = nerfstudio_prediction(tmp_path, tiny_dataset, renders)
    target = pred / "test" / "raw-depth" / "r_000.npy.gz"
    target.write_bytes(gzip_inflating_to(1 << 30))
    assert target.stat().st_size < 2 << 20
    line = refused("evaluate", ["evaluate", tiny_dataset, "--pred", pred, "--out", tmp_path / "out" / "m.json"],
                   tmp_path, tmp_path / "out", "1 GiB .npy.gz", shared=(tiny_dataset,), message="inflates to more than")
    assert "while inflating" in line


def test_valid_foreign_depth_is_still_read(tmp_path, tiny_dataset, renders):
    """The control: the same layout with honest .npy.gz files scores (exit 0)."""
    pred = nerfstudio_prediction(tmp_path, tiny_dataset, renders)
    outcome = run_cli(["evaluate", tiny_dataset, "--pred", pred, "--out", tmp_path / "m.json"], tmp_path)
    assert outcome.code == 0, outcome


DECLARING = ("npy-shape", "npy-gz-shape", "npy-dtype", "exr-channels", "png-size")


@pytest.mark.parametrize("kind", DECLARING)
@given(data=st.data())
@settings(max_examples=2, **FAST)
def test_prediction_files_declaring_more_than_a_frame_are_refused(tmp_path_factory, tiny_dataset, renders, kind, data):
    """A small prediction file whose header declares a huge array: refused from the header,
    before anything that size is allocated or inflated."""
    folder = _folder(tmp_path_factory, "declare")
    pred = copy_tree(renders, folder / "pred")
    frames = pred / "test"  # r_000.png, r_000_depth.exr, ...
    assert (frames / "r_000_depth.exr").is_file()
    out = folder / "out"
    if kind.startswith("npy"):
        side = data.draw(st.sampled_from([33, 1000, 100_000, 2**31 - 1]), label="side")
        dtype = data.draw(st.sampled_from(["|O", "<c16", "V8", "<U4"]), label="dtype") if kind == "npy-dtype" else "<f8"
        header = io.BytesIO()
        np.lib.format.write_array_header_1_0(header, {"descr": dtype, "fortran_order": False, "shape": (side, side)})
        body = header.getvalue() + bytes(data.draw(st.integers(0, 4096), label="payload"))
        for exr in frames.glob("r_*_depth.exr"):
            exr.unlink()
        if kind == "npy-gz-shape":
            shutil.rmtree(pred)
            pred = nerfstudio_prediction(folder, tiny_dataset, renders)
            target = pred / "test" / "raw-depth" / "r_000.npy.gz"
            assert target.is_file()
            target.write_bytes(gzip.compress(body))
        else:
            (frames / "r_000_depth.npy").write_bytes(body)
            for other in sorted(frames.glob("r_*[0-9].png"))[1:]:
                np.save(frames / f"{other.stem}_depth.npy", np.zeros((32, 32)))
    elif kind == "exr-channels":
        channels = data.draw(st.integers(5, 40), label="channels")
        exr = exr_bytes({f"c{i:02d}": np.zeros((8, 8), np.float32) for i in range(channels)})
        write_raw(frames / "r_000_depth.exr", exr_with_data_window(exr, 8192, 8192))
    else:
        side = data.draw(st.sampled_from([8192, 9000, 65535, 2**31 - 1]), label="side")
        write_raw(frames / "r_000.png", png_declaring(side, side, bytes(data.draw(st.integers(0, 10_000), label="payload"))))
    line = refused("evaluate", ["evaluate", tiny_dataset, "--pred", pred, "--out", out / "m.json"], folder, out, kind,
                   shared=(tiny_dataset,))
    expected = {"npy-shape": ("header declares",), "npy-gz-shape": ("header declares",),
                "npy-dtype": ("not a plain number type",), "exr-channels": ("channels of 8192x8192",),
                "png-size": ("header says", "cannot read image", "the ground truth is")}[kind]  # size checked first
    assert "r_000" in line and any(text in line for text in expected), line


def test_read_npy_checks_the_header_before_reading():
    """Unit view of the same: the shape's value count, the dtype and the payload's size."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (10**6, 10**6)})
    with pytest.raises(InputError, match="header declares shape"):
        bounded.read_npy("x.npy", header.getvalue(), max_elements=1024)
    buffer = io.BytesIO()
    np.save(buffer, np.arange(6.0).reshape(2, 3))
    assert bounded.read_npy("x.npy", buffer.getvalue(), max_elements=6).tolist() == [[0, 1, 2], [3, 4, 5]]
    with pytest.raises(InputError, match="holds"):
        bounded.read_npy("x.npy", buffer.getvalue()[:-8], max_elements=6)
    buffer = io.BytesIO()
    np.save(buffer, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match="not a plain number type"):
        bounded.read_npy("x.npy", buffer.getvalue())


# --------------------------------------------------------------------------------------
# radiance that overflows float32 while rendering


def envmap_with(path: Path, peak: float, everywhere: bool = False) -> Path:
    pixels = np.full((8, 16, 3), peak if everywhere else 1.0, np.float32)
    pixels[3, 5] = peak
    write_raw(path, exr_bytes({"RGB": pixels}))
    return path


def test_the_issues_envmap_example_is_refused_before_rendering(tmp_path):
    """An environment map holding 1e30 (finite) overflowed to NaN and left a partial view."""
    envmap = envmap_with(tmp_path / "sky.exr", 1e30)
    line = refused("generate", ["generate", "primitives", "--envmap", envmap, "--out", tmp_path / "out", "--res", "8",
                                "--views", "1", "--spp", "2"], tmp_path, tmp_path / "out", "envmap pixel 1e30")
    assert "radiance 1e+30" in line and f"{validate.MAX_RADIANCE:.3g}" in line


def test_radiance_below_the_bound_renders_finite(tmp_path):
    """The control: a map at the bound everywhere renders, and every output is finite (so
    the bound leaves the headroom it claims)."""
    envmap = envmap_with(tmp_path / "sky.exr", validate.MAX_RADIANCE * 0.99, everywhere=True)
    outcome = run_cli(["generate", "primitives", "--envmap", envmap, "--out", tmp_path / "out", "--res", "16",
                       "--views", "2", "--val-views", "0", "--test-views", "1", "--spp", "4", "--quiet"], tmp_path)
    assert outcome.code == 0, outcome
    from fuzzing import nonfinite_outputs

    assert not nonfinite_outputs(tmp_path / "out")


LIGHTS = {
    "constant": '[[light]]\ntype = "constant"\nradiance = [{v}, 1.0, 1.0]\n',
    "sky": '[[light]]\ntype = "sky"\nzenith = [1.0, 1.0, 1.0]\nhorizon = [1.0, 1.0, 1.0]\nnadir = [1.0, 1.0, 1.0]\n'
           'sun_direction = [0.0, 0.0, 1.0]\nsun_radiance = [{v}, {v}, {v}]\n',
    "point": '[[light]]\ntype = "point"\nposition = [0.0, 0.0, 3.0]\nintensity = [{v}, {v}, {v}]\n',
    "rectangle": '[[light]]\ntype = "rectangle"\ncenter = [0.0, 0.0, 2.5]\nsize = [1.0, 1.0]\nnormal = [0.0, 0.0, -1.0]\n'
                 'radiance = [1.0, {v}, 1.0]\n',
    "envmap": '[envmap]\npath = "sky.exr"\n',
}


@pytest.mark.parametrize("light", sorted(LIGHTS))
@given(data=st.data())
@settings(max_examples=2, **FAST)
def test_radiance_above_the_bound_is_refused(tmp_path_factory, light, data):
    """Scene-file lights and envmaps with a radiance between the bound and float32's
    largest value, drawn across magnitudes: one line, nothing written."""
    import trimesh

    peak = data.draw(log_uniform(math.log10(validate.MAX_RADIANCE) + 0.01, math.log10(3.4e38)), label="radiance")
    folder = _folder(tmp_path_factory, "radiance")
    trimesh.creation.box().export(folder / "box.ply")
    if light == "envmap":
        envmap_with(folder / "sky.exr", peak, everywhere=data.draw(st.booleans(), label="everywhere"))
    scene = folder / "scene.toml"
    scene.write_text('version = 1\n\n[[asset]]\npath = "box.ply"\n\n' + LIGHTS[light].format(v=f"{peak:.6g}"))
    refused("generate", ["generate", scene, "--out", folder / "out", "--res", "8", "--views", "1", "--spp", "1"],
            folder, folder / "out", f"{light} radiance {peak:.3g}", message="radiance")


# --------------------------------------------------------------------------------------
# fresh cases of every drawn family above, from the run's fuzz seed (printed)

test_deeply_nested_documents_are_refused_fresh = fresh_twin(test_deeply_nested_documents_are_refused)
test_numeric_flags_out_of_range_are_refused_fresh = fresh_twin(test_numeric_flags_out_of_range_are_refused, 1)
test_numeric_flags_in_range_are_accepted_fresh = fresh_twin(test_numeric_flags_in_range_are_accepted, 1)
test_paths_that_are_not_utf8_are_refused_fresh = fresh_twin(test_paths_that_are_not_utf8_are_refused, 1)
test_prediction_files_declaring_more_than_a_frame_are_refused_fresh = fresh_twin(
    test_prediction_files_declaring_more_than_a_frame_are_refused, 1)
test_radiance_above_the_bound_is_refused_fresh = fresh_twin(test_radiance_above_the_bound_is_refused, 1)


def test_fresh_cases_come_from_the_printed_seed(monkeypatch):
    """The same seed draws the same cases, another seed others, and the fixed twin keeps
    its derandomized ones: a failure of a fresh case reproduces from the seed."""
    drawn = []

    @given(data=st.data())
    @settings(max_examples=5, **FAST)
    def sample(data):
        drawn.append(data.draw(st.integers(0, 2**62)))

    def run(test):
        drawn.clear()
        test()
        return list(drawn)

    def fresh(seed):
        monkeypatch.setenv("NERFGAUGE_FUZZ_SEED", str(seed))
        return run(fresh_twin(sample))

    assert fresh(1) == fresh(1) != fresh(2)
    assert run(sample) == run(sample) != fresh(1)


def test_found_by_a_fresh_seed_a_three_channel_ground_truth_depth_is_one_line(tmp_path):
    """Seed 3169015096 of the fresh image family replaced a dataset's r_000_distance.exr
    with an RGB EXR: OpenEXR groups R, G, B as one "RGB" entry, so the one-channel check
    passed and covisibility broadcast [32, 32] against [32, 32, 3] (a ValueError traceback)."""
    from nerfgauge.core.images import read_exr_single

    path = tmp_path / "r_000_distance.exr"
    write_raw(path, exr_bytes({"RGB": np.ones((4, 4, 3), np.float32)}))
    with pytest.raises(InputError, match="should hold one channel, has 3"):
        read_exr_single(path)
    write_raw(path, exr_bytes({"Z": np.ones((4, 4), np.float32)}))
    assert read_exr_single(path).shape == (4, 4)


def test_found_by_a_fresh_seed_a_png_cut_inside_its_end_chunk_is_refused(tmp_path):
    """Seed 248928585 of the fresh image family cut a mask PNG to 124 of its 134 bytes
    (inside IEND): Pillow decoded it and evaluate accepted it (exit 0)."""
    from nerfgauge.core.images import read_png
    from fuzzing import image_bytes

    data = image_bytes(np.zeros((4, 4), np.uint8), "PNG")
    assert read_png(tmp_path / "m.png", data).shape == (4, 4)
    for cut in (1, 4, 11):
        with pytest.raises(InputError, match="truncated"):
            read_png(tmp_path / "m.png", data[:-cut])


@pytest.mark.parametrize("compression", ["NO_COMPRESSION", "ZIP_COMPRESSION", "ZIPS_COMPRESSION", "PIZ_COMPRESSION",
                                         "PXR24_COMPRESSION", "DWAB_COMPRESSION"])
def test_found_by_a_fresh_seed_an_exr_cut_anywhere_is_one_line(tmp_path, compression):
    """Seed 383943042 cut a dataset's r_000_distance.exr to 679 of 1117 bytes: OpenEXR's C
    library wrote a second stderr line of its own. The offset table is now checked against
    the file's size first: every cut, in every compression, is one InputError."""
    import OpenEXR

    from nerfgauge.core.images import read_exr

    data = exr_bytes({"Z": np.random.default_rng(0).random((37, 19), np.float32)},
                     {"compression": getattr(OpenEXR, compression)})
    assert read_exr(tmp_path / "d.exr", data)[0]["Z"].shape == (37, 19)
    for cut in range(9, len(data), max(1, len(data) // 97)):
        with pytest.raises(InputError, match="truncated|cannot read EXR"):
            read_exr(tmp_path / "d.exr", data[:cut])


def test_found_by_a_fresh_seed_a_saved_count_of_none_is_one_line():
    """CI's fresh checkpoint draw (hypothesis b'AABBBEEB') wrote `"threads": null` into a
    model.pt's config: check_fields skipped every None, so `nerfgauge render` reached
    `threads > 1` (a TypeError traceback). A None is now refused where the field's
    annotation does not admit one, and still skipped where it does ("auto", "not given")."""
    from dataclasses import dataclass
    from typing import Optional

    from nerfgauge.nerf.config import TrainConfig

    @dataclass
    class Counts:
        workers: int = 2
        limit: Optional[int] = None
        cap: float | None = None

    ranges = {"workers": arguments.THREADS, "limit": arguments.THREADS, "cap": arguments.THREADS}
    arguments.check_fields(Counts(), ranges)  # the optional fields' None passes
    with pytest.raises(InputError, match="--workers needs a value, got None"):
        arguments.check_fields(Counts(workers=None), ranges)
    with pytest.raises(InputError, match="--threads needs a value"):
        TrainConfig(dataset="d", threads=None).validate()
    TrainConfig(dataset="d", steps=10).validate()  # budget_seconds None beside steps: its annotation admits it


class NoneCount(int):
    """An int type whose name holds "None": the annotation's text once said it admitted None."""


def test_whether_a_field_admits_none_is_read_from_its_type_not_its_text():
    """`admits_none` reads the resolved annotation: a union with None admits it, a type whose
    name or arguments merely contain "None" does not, and string annotations (`from
    __future__ import annotations`, as every config module has) resolve to the same types."""
    from typing import Any, Optional, Union

    assert all(arguments.admits_none(a) for a in (Optional[int], int | None, Union[None, float], type(None), Any, None))
    assert not any(arguments.admits_none(a) for a in (int, float, NoneCount, dict[str, None], tuple[None, int]))
    namespace = {}
    exec("from __future__ import annotations\nfrom dataclasses import dataclass\nfrom typing import Optional\n"
         "@dataclass\nclass Later:\n    count: NoneCount = 1\n    limit: Optional[int] = None\n",
         {"NoneCount": NoneCount, "__name__": __name__}, namespace)
    ranges = {"count": arguments.THREADS, "limit": arguments.THREADS}
    arguments.check_fields(namespace["Later"](), ranges)
    with pytest.raises(InputError, match="--count needs a value, got None"):
        arguments.check_fields(namespace["Later"](count=None), ranges)
