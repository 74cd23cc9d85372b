"""Issue 47 item 11: the fuzz families draw links, journals and suite folders too.

Three families, each judged by tests/fuzzing.py's verdict (exit 0 with finite outputs, or
exit 2 with one `nerfgauge <cmd>: error:` line; never a traceback; nothing changed outside
the command's own folder):

- links: any file or folder of a dataset (or of a suite folder) replaced by a symbolic link
  to a user's folder or file holding the same names, then a command that writes there
  (`export colmap`, `generate` resuming, `suite evaluate`, `suite report`). The user's
  folder lies outside the target, so a write, delete or rename through the link is caught
  by the snapshot.
- journals: the export's rollback journal (`.nerfgauge-export.json`) drawn as a document:
  its manifest text and its {name: text} table with absolute, `..`, NUL, empty and
  non-string names and values, or not JSON at all. Any name that resolved outside the
  dataset would create a file in the case folder, which the snapshot sees.
- suite folders: one value anywhere in suite.json, suite-manifest.json or a result.json
  replaced by a hostile one (path-like and mathtext strings, NUL, wrong types, huge
  numbers), then `suite report`, which draws and writes from those files.

Each family has a fixed derandomized test (the same cases every run) and a `_fresh` twin
that draws new cases from the run's printed fuzz seed (tests/conftest.py).
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
from pathlib import Path

import pytest
from fuzzing import ANY, Case, assert_judged, copy_tree, fresh_twin, run_cli
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

FAST = dict(deadline=None, derandomize=True, database=None, phases=(Phase.explicit, Phase.generate),
            suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
_case_numbers = itertools.count()

# generate_small's recipe (tests/conftest.py), so that `generate` resumes the dataset
GENERATE_ARGS = ["primitives", "--views", "4", "--val-views", "1", "--test-views", "2", "--res", "32", "--spp", "4",
                 "--quiet"]

HOSTILE_STRINGS = ["../x", "../../outside.txt", "/tmp/nerfgauge-fuzz-abs", "a\x00b", "m$\\frac$x", "", "x" * 300,
                   "results/../../u", "C:\\x", "\u202eevil", ".", "..", "~/x"]
HOSTILE_VALUES = [None, 0, -1, 2**70, 1e308, -1e308, True, [], {}, [1, 2], {"a": 1}]


@pytest.fixture(scope="module")
def base(tmp_path_factory, tiny_dataset):
    """The read-only inputs: the tiny dataset (with its COLMAP export) and a one-scene
    suite folder with the nearest baseline's results, and the folder all cases live in."""
    from suite_toml import one_scene_suite

    from nerfgauge.cli import main

    root = tmp_path_factory.mktemp("fuzz-state")
    toml, suite, pred = one_scene_suite(root)
    assert main(["suite", "evaluate", str(toml), str(suite), "--method", "nearest", "--pred", str(pred)]) == 0
    cases = root / "cases"
    cases.mkdir()
    return {"dataset": Path(tiny_dataset), "suite": suite, "toml": toml, "pred": pred, "cases": cases,
            "shared": (Path(tiny_dataset), toml, pred)}


def new_case(base, family: str) -> Path:
    folder = base["cases"] / f"{family}-{next(_case_numbers)}"
    folder.mkdir()
    return folder


def entries(root: Path) -> list[str]:
    """Every file and folder below `root` (relative POSIX paths), sorted: what a link may replace."""
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if ".nerfgauge.lock" not in p.name)


def plant_link(data, root: Path, user_root: Path) -> str:
    """Replace one drawn entry below `root` with a link to a user's copy of it (the same
    names inside, plus a file of the user's own); returns what was done, in words."""
    found = entries(root)
    folders = [rel for rel in found if (root / rel).is_dir()]
    # folders mostly: a linked folder is where writers create, prune and replace names
    rel = data.draw(st.one_of(st.sampled_from(folders), st.sampled_from(folders), st.sampled_from(found)),
                    label="linked entry")
    path = root / rel
    user = user_root / "user" / rel
    user.parent.mkdir(parents=True, exist_ok=True)
    if path.is_dir() and not path.is_symlink():
        shutil.copytree(path, user, symlinks=True)
        (user / "my_notes.txt").write_text("notes\n")
        shutil.rmtree(path)
    else:
        shutil.copy2(path, user, follow_symlinks=False)
        path.unlink()
    os.symlink(user, path, target_is_directory=user.is_dir())
    return f"{rel} a link to the user's copy"


# --------------------------------------------------------------------------------------
# links


@given(data=st.data())
@settings(max_examples=10, **FAST)
def test_a_link_anywhere_in_a_dataset(base, data):
    folder = new_case(base, "link-ds")
    ds = copy_tree(base["dataset"], folder / "ds")
    command = data.draw(st.sampled_from(["export", "generate"]), label="command")
    if command == "generate":
        (ds / "manifest.json").unlink()  # incomplete: the rerun resumes into it
    what = plant_link(data, ds, folder)
    argv = (["export", "colmap", ds, "--points", "none"] if command == "export"
            else ["generate", *GENERATE_ARGS, "--out", ds])
    assert_judged(Case(command, argv, folder, ds, what, ANY, base["shared"]))


@given(data=st.data())
@settings(max_examples=8, **FAST)
def test_a_link_anywhere_in_a_suite_folder(base, data):
    folder = new_case(base, "link-suite")
    suite = copy_tree(base["suite"], folder / "S")
    what = plant_link(data, suite, folder)
    command = data.draw(st.sampled_from(["evaluate", "report"]), label="command")
    argv = (["suite", "evaluate", base["toml"], suite, "--method", "nearest", "--pred", base["pred"]]
            if command == "evaluate" else ["suite", "report", suite])
    assert_judged(Case("suite", argv, folder, suite, f"{what}, then suite {command}", ANY, base["shared"]))


# --------------------------------------------------------------------------------------
# the export's journal

JOURNAL = ".nerfgauge-export.json"


def journal_names(data, folder: Path) -> str:
    return data.draw(st.one_of(
        st.sampled_from(["scene.json", "transforms.json", "sparse/0/images.txt", "images/r_000.png", "manifest.json",
                         JOURNAL, "../escape.txt", "../../escape.txt", str(folder / "absolute.txt"), "a\x00b", "",
                         ".", "images/../../escape.txt", "sparse/0/../../../escape.txt", "x" * 300]),
        st.text(min_size=0, max_size=12)), label="name")


@given(data=st.data())
@settings(max_examples=10, **FAST)
def test_a_drawn_export_journal(base, data):
    folder = new_case(base, "journal")
    ds = copy_tree(base["dataset"], folder / "ds")
    manifest = (ds / "manifest.json").read_text()
    shape = data.draw(st.sampled_from(["document", "document", "document", "not-json", "not-an-object"]), label="shape")
    if shape == "not-json":
        raw = data.draw(st.binary(max_size=40), label="bytes")
    elif shape == "not-an-object":
        raw = json.dumps(data.draw(st.sampled_from(HOSTILE_VALUES), label="document")).encode()
    else:
        document = {"manifest": data.draw(st.one_of(st.just(manifest), st.text(max_size=20),
                                                    st.sampled_from(HOSTILE_VALUES)), label="manifest"),
                    "files": {journal_names(data, folder): data.draw(st.one_of(st.text(max_size=20),
                                                                               st.sampled_from(HOSTILE_VALUES)),
                                                                     label="text")
                              for _ in range(data.draw(st.integers(0, 3), label="count"))}}
        if data.draw(st.booleans(), label="drop a key"):
            document.pop(data.draw(st.sampled_from(sorted(document)), label="dropped"))
        raw = json.dumps(document).encode()
    (ds / JOURNAL).write_bytes(raw)
    (ds / "manifest.json").unlink()  # as a killed export leaves it
    assert_judged(Case("export", ["export", "colmap", ds, "--points", "none"], folder, ds, f"journal {shape}", ANY,
                       base["shared"]))


# --------------------------------------------------------------------------------------
# suite folders' state files


def json_locations(value, where=()):
    """Every (key path) inside a JSON document, containers included."""
    yield where
    if isinstance(value, dict):
        for key, item in value.items():
            yield from json_locations(item, (*where, key))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            yield from json_locations(item, (*where, index))


def replace_at(document, where, value):
    if not where:
        return value
    parent = document
    for key in where[:-1]:
        parent = parent[key]
    parent[where[-1]] = value
    return document


@given(data=st.data())
@settings(max_examples=10, **FAST)
def test_a_drawn_value_in_a_suite_state_file(base, data):
    folder = new_case(base, "suite-state")
    suite = copy_tree(base["suite"], folder / "S")
    state_files = sorted(p.relative_to(suite).as_posix() for p in suite.rglob("*.json")
                         if p.name in ("suite.json", "suite-manifest.json", "result.json"))
    rel = data.draw(st.sampled_from(state_files), label="file")
    document = json.loads((suite / rel).read_text())
    where = data.draw(st.sampled_from(list(json_locations(document))), label="where")
    value = data.draw(st.sampled_from(HOSTILE_STRINGS + HOSTILE_VALUES), label="value")
    (suite / rel).write_text(json.dumps(replace_at(document, where, value)))
    assert_judged(Case("suite", ["suite", "report", suite], folder, suite, f"{rel} {list(where)} = {value!r}", ANY,
                       base["shared"]))


def test_the_suite_fixture_reports_before_any_mutation(base):
    """The families start from a folder `suite report` accepts, so a refusal is the mutation's."""
    folder = new_case(base, "suite-plain")
    suite = copy_tree(base["suite"], folder / "S")
    outcome = run_cli(["suite", "report", suite], folder)
    assert outcome.code == 0, outcome


test_a_link_anywhere_in_a_dataset_fresh = fresh_twin(test_a_link_anywhere_in_a_dataset)
test_a_link_anywhere_in_a_suite_folder_fresh = fresh_twin(test_a_link_anywhere_in_a_suite_folder)
test_a_drawn_export_journal_fresh = fresh_twin(test_a_drawn_export_journal)
test_a_drawn_value_in_a_suite_state_file_fresh = fresh_twin(test_a_drawn_value_in_a_suite_state_file)
