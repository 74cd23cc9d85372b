"""Single-file outputs (issue 31, class "outputs replace anything"): a file nerfgauge writes
at a path the user gives goes only to a new path or onto a file of its own kind that
nerfgauge wrote (core.outputs); never into a dataset folder, never over a user's file or a
run's own files; `--overwrite` replaces only nerfgauge's own files of another kind.

Each refusal is judged on the whole promise: exit 2, exactly one stderr line naming what was
found, and nothing changed in the whole test folder (snapshot before and after, the shared
dataset and prediction fixtures included).
"""

from __future__ import annotations

import json
import shutil

import pytest

from cli_errors import one_line_exit_2
from fuzzing import snapshot, snapshot_changes
from nerfgauge.cli import main
from nerfgauge.core.folders import MARKER
from nerfgauge.core.outputs import check_output_file, identify, ply_mark, stamp, xml_mark

def cli(argv) -> int:
    return main([str(arg) for arg in argv])


THRESHOLDS = '["*"]\npsnr = { min = 1.0 }\n'


@pytest.fixture(scope="module")
def predictions(tmp_path_factory, tiny_dataset):
    """The tiny dataset's test split by the nearest-view baseline (a nerfgauge baseline folder)."""
    out = tmp_path_factory.mktemp("ownership") / "nearest"
    assert cli(["baseline", str(tiny_dataset), "--method", "nearest", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory, tiny_dataset):
    """A 5-step training run (a nerfgauge run folder; too short to hold a surface)."""
    out = tmp_path_factory.mktemp("ownership-run") / "run"
    assert cli(["train", str(tiny_dataset), "--out", str(out), "--steps", "5", "--quiet"]) == 0
    return out


@pytest.fixture
def unchanged(tiny_dataset, predictions, tmp_path):
    """unchanged(argv, *expected): the command exits 2 with one line holding every expected
    text, and nothing under tmp_path, the dataset or the predictions changed."""
    def check(capsys, argv, *expected) -> str:
        roots = [tmp_path, tiny_dataset, predictions]
        before = snapshot(roots)
        line = one_line_exit_2(capsys, argv, *expected)
        changes = snapshot_changes(before, snapshot(roots))
        assert not changes, changes
        return line
    return check


def evaluate_argv(dataset, predictions, *extra):
    return ["evaluate", dataset, "--pred", predictions, "--no-held-out", *extra]


class TestEvaluateOut:
    def test_another_datasets_manifest_is_refused_and_that_dataset_stays_usable(self, tiny_dataset, predictions,
                                                                                 tmp_path, unchanged, capsys):
        other = shutil.copytree(tiny_dataset, tmp_path / "DS2")
        line = unchanged(capsys, evaluate_argv(tiny_dataset, predictions, "--out", other / "manifest.json"),
                         f"refusing to write {other / 'manifest.json'}", "another dataset's manifest.json",
                         f"dataset folder {other}")
        assert "--overwrite" not in line  # no flag makes this allowed
        unchanged(capsys, evaluate_argv(tiny_dataset, predictions, "--out", other / "manifest.json", "--overwrite"),
                  "another dataset's manifest.json")
        from nerfgauge.core.dataset import Dataset

        Dataset(other).cameras("test")  # still a complete dataset

    def test_a_new_file_inside_a_dataset_folder_is_refused(self, tiny_dataset, predictions, tmp_path, unchanged,
                                                            capsys):
        other = shutil.copytree(tiny_dataset, tmp_path / "DS2")
        for target in (other / "scores.json", other / "test" / "scores.json", other / "sub" / "scores.json"):
            unchanged(capsys, evaluate_argv(tiny_dataset, predictions, "--out", target),
                      f"refusing to write {target}", f"inside the nerfgauge dataset folder {other}")

    def test_dot_dot_and_symlinked_folders_are_judged_where_they_lead(self, tiny_dataset, predictions, tmp_path,
                                                                       unchanged, capsys):
        other = shutil.copytree(tiny_dataset, tmp_path / "DS2")
        (tmp_path / "link").symlink_to(other)
        unchanged(capsys, evaluate_argv(tiny_dataset, predictions, "--out", tmp_path / "link" / "manifest.json"),
                  "another dataset's manifest.json", f"dataset folder {other}")
        beside = other / ".." / "beside.json"  # outside the dataset, though the path names it
        assert cli(evaluate_argv(tiny_dataset, predictions, "--out", beside)) == 0
        assert identify(tmp_path / "beside.json") == "metrics"

    def test_a_users_file_is_refused_even_with_overwrite(self, tiny_dataset, predictions, tmp_path, unchanged,
                                                         capsys):
        notes = tmp_path / "notes.txt"
        notes.write_text("my notes\n")
        mine = tmp_path / "mine.json"
        mine.write_text(json.dumps({"kind": "metrics", "psnr": 30}))  # our kind, but not our tool
        for target in (notes, mine):
            for extra in ([], ["--overwrite"]):
                unchanged(capsys, evaluate_argv(tiny_dataset, predictions, "--out", target, *extra),
                          f"refusing to replace {target}: it is a file nerfgauge did not write")
        assert notes.read_text() == "my notes\n"

    def test_a_rerun_replaces_its_own_metrics_without_a_flag(self, tiny_dataset, predictions, tmp_path, capsys):
        out = tmp_path / "scores" / "m.json"
        for _ in range(2):
            assert cli(evaluate_argv(tiny_dataset, predictions, "--out", out)) == 0
        document = json.loads(out.read_text())
        assert document["tool"] == "nerfgauge" and document["kind"] == "metrics" and identify(out) == "metrics"
        assert cli(evaluate_argv(tiny_dataset, predictions)) == 0  # the default, PRED/metrics.json, twice
        assert cli(evaluate_argv(tiny_dataset, predictions)) == 0
        assert identify(predictions / "metrics.json") == "metrics"

    def test_the_readme_flow_writes_beside_a_run_and_reruns(self, tiny_dataset, predictions, run_folder, capsys):
        out = run_folder / "metrics.json"  # README: evaluate ... --out runs/prim/metrics.json
        try:
            for _ in range(2):
                assert cli(evaluate_argv(tiny_dataset, predictions, "--out", out)) == 0
        finally:
            out.unlink(missing_ok=True)
            shutil.rmtree(run_folder / "error_maps", ignore_errors=True)

    def test_a_runs_own_files_are_never_replaced(self, tiny_dataset, predictions, run_folder, tmp_path, unchanged,
                                                 capsys):
        before = snapshot([run_folder])
        for name in ("config.json", "model.pt", "log.jsonl"):
            for extra in ([], ["--overwrite"]):
                unchanged(capsys, evaluate_argv(tiny_dataset, predictions, "--out", run_folder / name, *extra),
                          f"refusing to replace {run_folder / name}: it is one of its own files in the run folder")
        assert snapshot([run_folder]) == before
        scores = run_folder / "geometry.json"  # an output beside the run, not the run's own: --overwrite may
        scores.write_bytes(json.dumps(stamp({"schema": 1}, "geometry")).encode())
        try:
            line = one_line_exit_2(capsys, evaluate_argv(tiny_dataset, predictions, "--out", scores),
                                   "it is a nerfgauge geometry file, not a metrics file", "pass --overwrite")
            assert cli(evaluate_argv(tiny_dataset, predictions, "--out", scores, "--overwrite")) == 0, line
            assert identify(scores) == "metrics"
        finally:
            scores.unlink()
            shutil.rmtree(run_folder / "error_maps", ignore_errors=True)

    def test_another_nerfgauge_kind_needs_overwrite(self, tiny_dataset, predictions, tmp_path, unchanged, capsys):
        geometry = tmp_path / "geometry.json"
        geometry.write_bytes(json.dumps(stamp({"schema": 1}, "geometry")).encode())
        unchanged(capsys, evaluate_argv(tiny_dataset, predictions, "--out", geometry),
                  f"refusing to replace {geometry}: it is a nerfgauge geometry file, not a metrics file",
                  "pass --overwrite")
        assert cli(evaluate_argv(tiny_dataset, predictions, "--out", geometry, "--overwrite")) == 0
        assert identify(geometry) == "metrics"

    def test_the_python_api_keeps_the_same_rule(self, tiny_dataset, predictions, tmp_path):
        import nerfgauge

        notes = tmp_path / "notes.txt"
        notes.write_text("mine")
        other = shutil.copytree(tiny_dataset, tmp_path / "DS2")
        for target, expected in ((notes, "a file nerfgauge did not write"), (other / "manifest.json", "dataset")):
            before = snapshot([tmp_path])
            with pytest.raises(nerfgauge.InputError, match=expected):
                nerfgauge.evaluate(tiny_dataset, predictions, out=target, held_out=False)
            assert not snapshot_changes(before, snapshot([tmp_path]))

    def test_a_folders_marker_is_never_a_target(self, tiny_dataset, predictions, unchanged, capsys):
        for extra in ([], ["--overwrite"]):
            unchanged(capsys, evaluate_argv(tiny_dataset, predictions, "--out", predictions / MARKER, *extra),
                      "ownership marker")

    def test_foreign_result_files_are_checked_before_anything_is_written(self, tiny_dataset, predictions, tmp_path,
                                                                         unchanged, capsys):
        user = tmp_path / "results.json"
        user.write_text("{}")
        out = tmp_path / "new" / "m.json"
        for flag in ("--ns-eval", "--nerfbaselines"):
            unchanged(capsys, evaluate_argv(tiny_dataset, predictions, "--out", out, flag, user),
                      f"refusing to replace {user}: it is a file nerfgauge did not write")
        assert not out.parent.exists()  # the metrics were not written either
        ns, nb = tmp_path / "ns.json", tmp_path / "nb.json"
        for _ in range(2):  # our own: a rerun replaces them
            assert cli(evaluate_argv(tiny_dataset, predictions, "--out", out, "--ns-eval", ns,
                                      "--nerfbaselines", nb)) == 0
        assert (identify(ns), identify(nb)) == ("ns-eval", "nerfbaselines-results")
        assert "results" in json.loads(ns.read_text())  # still ns-eval's format


class TestCheckJunit:
    @pytest.fixture
    def metrics(self, tiny_dataset, predictions, tmp_path):
        out = tmp_path / "scores" / "metrics.json"
        assert cli(evaluate_argv(tiny_dataset, predictions, "--out", out)) == 0
        thresholds = tmp_path / "t.toml"
        thresholds.write_text(THRESHOLDS)
        return out, thresholds

    def test_a_users_file_and_a_dataset_are_refused(self, metrics, tiny_dataset, tmp_path, unchanged, capsys):
        out, thresholds = metrics
        report = tmp_path / "report.xml"
        report.write_text("<testsuite name='theirs'/>")
        for extra in ([], ["--overwrite"]):
            unchanged(capsys, ["check", out, "--thresholds", thresholds, "--junit", report, *extra],
                      f"refusing to replace {report}: it is a file nerfgauge did not write")
        other = shutil.copytree(tiny_dataset, tmp_path / "DS2")
        unchanged(capsys, ["check", out, "--thresholds", thresholds, "--junit", other / "junit.xml"],
                  "inside the nerfgauge dataset folder")

    def test_a_rerun_replaces_its_own_junit_and_not_the_metrics(self, metrics, tmp_path, unchanged, capsys):
        out, thresholds = metrics
        junit = tmp_path / "junit.xml"
        for _ in range(2):
            assert cli(["check", out, "--thresholds", thresholds, "--junit", junit]) == 0
        assert identify(junit) == "junit"
        import xml.etree.ElementTree as ET

        assert ET.parse(junit).getroot().get("name") == "nerfgauge check"  # the comment keeps it valid XML
        unchanged(capsys, ["check", out, "--thresholds", thresholds, "--junit", out],
                  "it is a nerfgauge metrics file, not a junit file", "pass --overwrite")


class TestMeshGeometryToyPe:
    def test_mesh_and_geometry_refuse_a_users_file_before_any_work(self, tiny_dataset, run_folder, tmp_path,
                                                                    unchanged, capsys):
        mine = tmp_path / "scan.ply"
        mine.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
        for extra in ([], ["--overwrite"]):
            unchanged(capsys, ["mesh", run_folder, "-o", mine, *extra],
                      f"refusing to replace {mine}: it is a file nerfgauge did not write")
        other = shutil.copytree(tiny_dataset, tmp_path / "DS2")
        unchanged(capsys, ["mesh", run_folder, "-o", other / "meshes" / "mesh.ply"], "dataset")
        notes = tmp_path / "geometry.json"
        notes.write_text('{"mine": true}')
        unchanged(capsys, ["geometry", tiny_dataset, "--pred-mesh", mine, "-o", notes],
                  f"refusing to replace {notes}: it is a file nerfgauge did not write")

    def test_our_mesh_is_marked_readable_and_replaceable(self, tmp_path):
        import numpy as np
        import trimesh

        from nerfgauge.nerf.mesh import ply_bytes

        data = ply_bytes(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]))
        path = tmp_path / "m.ply"
        path.write_bytes(data)
        assert identify(path) == "mesh"
        assert len(trimesh.load(path, process=False).faces) == 1  # the comment line keeps it a valid PLY
        assert check_output_file(path, "mesh") == path  # a rerun of `mesh -o m.ply` may replace it
        path.write_bytes(data.replace(b"comment nerfgauge-kind: mesh\n", b""))
        with pytest.raises(Exception, match="nerfgauge did not write"):
            check_output_file(path, "mesh", overwrite=True)

    def test_toy_pe_refuses_a_dataset_and_a_users_image_and_reruns(self, tiny_dataset, tmp_path, unchanged, capsys):
        other = shutil.copytree(tiny_dataset, tmp_path / "DS2")
        unchanged(capsys, ["toy-pe", "--steps", "1", "--out", other], "inside the nerfgauge dataset folder")
        user = tmp_path / "pictures"
        user.mkdir()
        (user / "toy_pe.png").write_bytes(b"\x89PNG\r\n\x1a\n mine")
        unchanged(capsys, ["toy-pe", "--steps", "1", "--out", user],
                  f"refusing to replace {user / 'toy_pe.png'}: it is a file nerfgauge did not write")
        out = tmp_path / "toy"
        for _ in range(2):
            assert cli(["toy-pe", "--steps", "1", "--out", out]) == 0
        assert (identify(out / "toy_pe.png"), identify(out / "toy_pe.json")) == ("toy-pe", "toy-pe")


class TestFoldersInsideADataset:
    def test_no_command_makes_a_folder_inside_a_dataset(self, tiny_dataset, run_folder, tmp_path, unchanged, capsys):
        other = shutil.copytree(tiny_dataset, tmp_path / "DS2")
        for argv in (["render", run_folder, "--quiet", "--out", other / "renders"],
                     ["baseline", tiny_dataset, "--method", "nearest", "--out", other / "nearest"],
                     ["train", tiny_dataset, "--steps", "2", "--quiet", "--out", other / "test" / "run"],
                     ["generate", "primitives", "--res", "16", "--views", "2", "--quiet", "--out", other / "inner"]):
            unchanged(capsys, argv, f"refusing to write into {argv[-1]}",
                      f"inside the nerfgauge dataset folder {other}")


class TestRecognition:
    def test_each_mark_is_recognised_and_nothing_else_is(self, tmp_path):
        cases = {
            "stamped.json": (json.dumps(stamp({"a": 1}, "metrics")).encode(), "metrics"),
            "untooled.json": (json.dumps({"kind": "metrics"}).encode(), None),
            "kindless.json": (json.dumps({"tool": "nerfgauge"}).encode(), None),
            "list.json": (b"[1, 2]", None),
            "deep.json": (b'{"a":' * 100_000, None),
            "junit.xml": (xml_mark(b"<?xml version='1.0'?>\n<testsuite/>", "junit"), "junit"),
            "plain.xml": (b"<?xml version='1.0'?>\n<testsuite name='nerfgauge-kind: junit'/>", None),
            "mesh.ply": (ply_mark(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n"), "mesh"),
            "plain.ply": (b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\ncomment nerfgauge-kind: mesh\n", None),
            "empty": (b"", None),
        }
        for name, (data, kind) in cases.items():
            (tmp_path / name).write_bytes(data)
            assert identify(tmp_path / name) == kind, name

    def test_a_png_is_recognised_by_its_text_chunk(self, tmp_path):
        import numpy as np

        from nerfgauge.core.images import read_png, write_png

        image = np.zeros((3, 5, 3), np.uint8)
        write_png(tmp_path / "ours.png", image, kind="error-map")
        write_png(tmp_path / "plain.png", image)
        assert identify(tmp_path / "ours.png") == "error-map" and identify(tmp_path / "plain.png") is None
        assert read_png(tmp_path / "ours.png").shape == (3, 5, 3)
