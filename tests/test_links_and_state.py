"""Issue 47: nothing is written through a link inside our folders, and no state file is
trusted. Grouped by fault class:

- TestTheLinkRule: core.owned's walk, helper by helper: a symbolic link anywhere below a
  folder holding our marker is refused (one line naming it) by every write, delete, rename
  and folder creation, and the link's target is unchanged; a link above our folder, or a
  path in no folder of ours, is followed as before.
- TestNoRawWrites: a lint over the source: every delete, rename and write goes through
  core.owned or core.files (an explicit, commented allow-list for the few that write the
  temporary `atomic_path` hands out, or memory).
- TestLinksInsideOurFolders: the issue's examples through the command line: `export colmap`
  with images/ or sparse/0 a link, `generate` resuming with images/ or train/ a link,
  `train --resume` with a link in the run, `suite evaluate` and `suite generate` with a link
  in the suite: exit 2, one line, nothing outside changed (paths, sizes, mtimes, contents).
- TestExportJournal: the export's rollback journal is data: absolute and `..` names, other
  files, malformed documents, a manifest that does not match the files, are one line and
  exit 2 with nothing written; a journal an export wrote is still restored.
- TestResumeRecords: a view's noise record and a run's log.jsonl are re-validated on resume.
- TestUnresolvedGeometry: `generate tiny` at 24 px: every view rendered, exit 0, the COLMAP
  model without points and the reason, as a scene with no geometry gets.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest
from cli_errors import one_line_exit_2

from nerfgauge.cli import main
from nerfgauge.core import owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import link_or_copy_atomic, read_json, write_bytes_atomic, write_json
from nerfgauge.core.folders import MARKER, claim_folder, folder_lock, remove_owned

REPOSITORY = Path(__file__).resolve().parent.parent


def snapshot(folder: Path) -> dict:
    """{relative path: (kind, size, mtime_ns, sha256 or link text)} of everything under
    `folder` (links not followed), the folder itself included."""
    found = {}
    for path in [folder, *sorted(folder.rglob("*"))]:
        info = path.lstat()
        rel = path.relative_to(folder).as_posix()
        if path.is_symlink():
            found[rel] = ("link", os.readlink(path))
        elif path.is_dir():
            found[rel] = ("folder", info.st_mtime_ns)
        else:
            found[rel] = ("file", info.st_size, info.st_mtime_ns, hashlib.sha256(path.read_bytes()).hexdigest())
    return found


def user_folder(tmp_path: Path, name: str = "user") -> Path:
    """A user's folder a link will point at, with files whose names our writers use."""
    folder = tmp_path / name
    folder.mkdir(parents=True)
    (folder / "my_notes.txt").write_text("notes\n")
    (folder / "r_000.png").write_bytes(b"not ours")
    (folder / "result.json").write_text('{"mine": true}\n')
    (folder / "metrics.json").write_text('{"mine": true}\n')
    return folder


def ours(folder: Path, kind: str = "dataset") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / MARKER, {"kind": kind, "recipe": None, "tool": "nerfgauge"})
    return folder


def replace_with_link(path: Path, target: Path) -> None:
    """`path` (a folder or file of ours) becomes a symbolic link to `target`."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()
    path.symlink_to(target, target_is_directory=target.is_dir())


# --------------------------------------------------------------------------------------


class TestTheLinkRule:
    @pytest.fixture
    def linked(self, tmp_path):
        """(our folder, its subfolder `sub` that is a link to a user's folder, the user's folder)."""
        user = user_folder(tmp_path)
        folder = ours(tmp_path / "ds")
        (folder / "sub").symlink_to(user, target_is_directory=True)
        return folder, folder / "sub", user

    @pytest.mark.parametrize("operation", [
        "write_json", "write_bytes_atomic", "link_or_copy", "remove_file", "remove_tree", "remove_empty_folder",
        "make_folder", "rename_into", "rename_out_of", "open_append", "remove_owned", "folder_lock",
        "claim_folder_inside"])
    def test_every_helper_refuses_a_link_below_our_folder(self, linked, tmp_path, operation):
        folder, sub, user = linked
        (folder / "mine.txt").write_text("ours")
        before = snapshot(user)
        do = {
            "write_json": lambda: write_json(sub / "result.json", {"x": 1}),
            "write_bytes_atomic": lambda: write_bytes_atomic(sub / "new.bin", b"x"),
            "link_or_copy": lambda: link_or_copy_atomic(folder / "mine.txt", sub / "r_000.png"),
            "remove_file": lambda: owned.remove_file(sub / "my_notes.txt"),
            "remove_tree": lambda: owned.remove_tree(sub / "nested"),
            "remove_empty_folder": lambda: owned.remove_empty_folder(sub / "empty"),
            "make_folder": lambda: owned.make_folder(sub / "a" / "b"),
            "rename_into": lambda: owned.rename(folder / "mine.txt", sub / "result.json"),
            "rename_out_of": lambda: owned.rename(sub / "result.json", folder / "taken.json"),
            "open_append": lambda: owned.open_append(sub / "my_notes.txt"),
            "remove_owned": lambda: remove_owned(sub / "nested", "run"),
            "folder_lock": lambda: folder_lock(sub / "nested").__enter__(),
            "claim_folder_inside": lambda: claim_folder(sub / "run", "run", None).__enter__(),
        }[operation]
        if operation in ("remove_tree", "remove_owned", "folder_lock"):
            ours(user / "nested", "run")
            before = snapshot(user)
        if operation == "remove_empty_folder":
            (user / "empty").mkdir()
            before = snapshot(user)
        with pytest.raises(InputError, match=f"{sub} is a symbolic link inside the nerfgauge folder {folder}"):
            do()
        assert snapshot(user) == before
        assert (folder / "mine.txt").read_text() == "ours"

    def test_the_refusal_is_one_line_naming_the_link(self, linked):
        _, sub, _ = linked
        with pytest.raises(InputError) as refused:
            write_json(sub / "deeper" / "x.json", {})
        assert len(str(refused.value).splitlines()) == 1 and str(sub) in str(refused.value)

    def test_a_link_deeper_down_and_a_linked_file_are_refused(self, tmp_path):
        user = user_folder(tmp_path)
        folder = ours(tmp_path / "ds")
        (folder / "train").mkdir()
        (folder / "train" / "deep").symlink_to(user, target_is_directory=True)
        (folder / "train" / "r_000.png").symlink_to(user / "r_000.png")
        before = snapshot(user)
        for path in (folder / "train" / "deep" / "r_000.png", folder / "train" / "r_000.png"):
            with pytest.raises(InputError, match="symbolic link"):
                write_bytes_atomic(path, b"ours")
        with pytest.raises(InputError, match="symbolic link"):
            owned.rename(folder / MARKER, folder / "train" / "r_000.png")
        assert snapshot(user) == before

    def test_deleting_a_link_removes_the_link_not_its_target(self, tmp_path):
        user = user_folder(tmp_path)
        folder = ours(tmp_path / "ds")
        (folder / "r_000.png").symlink_to(user / "r_000.png")
        before = snapshot(user)
        assert owned.remove_file(folder / "r_000.png")
        assert not (folder / "r_000.png").is_symlink() and snapshot(user) == before

    def test_a_link_inside_a_nested_folder_of_ours_is_refused_too(self, tmp_path):
        """A suite holds datasets, a run holds renders: the outermost folder of ours counts."""
        user = user_folder(tmp_path)
        suite = ours(tmp_path / "suite", "suite")
        (suite / "datasets").symlink_to(user, target_is_directory=True)
        ours(user / "a", "dataset")  # the link leads to a folder that holds a marker of its own
        before = snapshot(user)
        with pytest.raises(InputError, match=f"{suite / 'datasets'} is a symbolic link"):
            write_json(suite / "datasets" / "a" / "scene.json", {})
        assert snapshot(user) == before

    def test_a_link_above_our_folder_is_the_users_layout_and_followed(self, tmp_path):
        real = tmp_path / "real-home"
        real.mkdir()
        (tmp_path / "home").symlink_to(real, target_is_directory=True)
        folder = ours(tmp_path / "home" / "ds")
        owned.make_folder(folder / "train")
        write_json(folder / "train" / "x.json", {"a": 1})
        owned.rename(folder / "train" / "x.json", folder / "train" / "y.json")
        with owned.open_append(folder / "log.jsonl") as log:
            log.write("{}\n")
        assert read_json(real / "ds" / "train" / "y.json") == {"a": 1} and (real / "ds" / "log.jsonl").is_file()
        assert owned.remove_file(folder / "log.jsonl") and owned.remove_tree(folder / "train")
        with folder_lock(folder):
            pass

    def test_paths_in_no_folder_of_ours_are_not_judged_here(self, tmp_path):
        """Single-file outputs the user names are core.outputs' business: a link in the
        user's own tree is their layout."""
        user = user_folder(tmp_path)
        (tmp_path / "mine").symlink_to(user, target_is_directory=True)
        write_json(tmp_path / "mine" / "out.json", {"a": 1})
        assert read_json(user / "out.json") == {"a": 1}

    def test_dot_dot_is_walked_where_the_kernel_walks_it(self, tmp_path):
        """`ds/sub/../x` with sub a link leads to the link target's parent: the link is on the way."""
        user = user_folder(tmp_path / "elsewhere")
        folder = ours(tmp_path / "ds")
        (folder / "sub").symlink_to(user, target_is_directory=True)
        with pytest.raises(InputError, match="symbolic link"):
            write_json(folder / "sub" / ".." / "x.json", {})
        assert not (tmp_path / "elsewhere" / "x.json").exists()

    def test_taking_a_folder_refuses_a_link_anywhere_inside_before_any_work(self, tmp_path):
        user = user_folder(tmp_path)
        folder = tmp_path / "ds"
        with claim_folder(folder, "dataset", "r1"):
            pass
        (folder / "train" / "deep").mkdir(parents=True)
        (folder / "train" / "deep" / "x").symlink_to(user, target_is_directory=True)
        before_user, before_ours = snapshot(user), snapshot(folder)
        with pytest.raises(InputError, match=f"{folder / 'train' / 'deep' / 'x'} is a symbolic link"):
            with claim_folder(folder, "dataset", "r1"):
                raise AssertionError("claimed a folder holding a link")
        with pytest.raises(InputError, match="symbolic link"):
            with folder_lock(folder):
                raise AssertionError("locked a folder holding a link")
        assert snapshot(user) == before_user
        assert {k: v for k, v in snapshot(folder).items() if k != ".nerfgauge.lock"} == \
            {k: v for k, v in before_ours.items() if k != ".nerfgauge.lock"}

    def test_overwrite_removes_a_planted_link_as_a_link(self, tmp_path):
        user = user_folder(tmp_path)
        folder = tmp_path / "ds"
        with claim_folder(folder, "dataset", "r1"):
            pass
        (folder / "images").symlink_to(user, target_is_directory=True)
        before = snapshot(user)
        with claim_folder(folder, "dataset", "r2", overwrite=True) as state:
            assert state == "replaced"
        assert not (folder / "images").exists() and snapshot(user) == before


# --------------------------------------------------------------------------------------

SOURCES = ("nerfgauge", "generate", "nerf", "eval", "scenes")
HELPERS = {"nerfgauge/core/owned.py", "nerfgauge/core/files.py"}  # the helpers' home: raw calls live here only
# Calls that write, delete, rename or make, named by the attribute called ...
RAW_METHODS = {"unlink", "rmdir", "mkdir", "rename", "write_bytes", "write_text", "touch", "symlink_to",
               "hardlink_to", "save", "savefig", "savez", "savez_compressed", "imwrite", "print_png", "write_binary",
               "rmtree", "makedirs", "removedirs", "mkfifo", "mknod"}
# ... or by module.function (names too common to flag on their own: list.remove, str.replace, dict.copy)
RAW_FUNCTIONS = {("os", "remove"), ("os", "unlink"), ("os", "replace"), ("os", "rename"), ("os", "link"),
                 ("os", "symlink"), ("os", "open"), ("os", "rmdir"), ("shutil", "move"), ("shutil", "copy"),
                 ("shutil", "copy2"), ("shutil", "copyfile"), ("shutil", "copytree"), ("np", "save"),
                 ("torch", "save")}
# The few raw writes that stay, each a write to the temporary `files.atomic_path` hands out
# (checked, fsynced and renamed by it), to memory, or to no file at all:
ALLOWED = {
    ("nerfgauge/cli.py", "os.open(os.devnull"): "opens /dev/null to silence a C library's stderr; writes no file",
    ("nerfgauge/core/dataset.py", ".save(tmp"): "Pillow writes atomic_path's temporary (16-bit instance PNG)",
    ("nerfgauge/core/images.py", ".save(tmp"): "Pillow writes atomic_path's temporary (PNG)",
    ("nerf/toy_pe.py", ".save(temporary"): "Pillow writes atomic_path's temporary (the comparison PNG)",
    ("nerf/checkpoint.py", "torch.save(obj, buffer)"): "into memory; the bytes go to write_bytes_atomic",
    ("eval/lpips.py", "torch.save({key"): "torch writes atomic_path's temporary (the converted weights)",
    ("eval/lpips.py", "Path(tmp).write_text"): "the checksum into atomic_path's temporary",
    ("eval/lpips_cache.py", 'open(tmp, "wb")'): "a feature entry streamed into atomic_path's temporary",
    ("eval/lpips.py", "torch.save(state, tmp)"): "torch writes atomic_path's temporary (torchvision's AlexNet file)",
    ("nerfgauge/methods/specs/gsplat_render.py", "folder.mkdir("):
        "runs in gsplat's own environment (no nerfgauge there): the render folder the harness named",
    ("nerfgauge/methods/specs/gsplat_render.py", ".save(folder /"):
        "runs in gsplat's own environment (no nerfgauge there): a PNG into the render folder the harness named",
    ("eval/report.py", ".print_png(str(tmp))"): "matplotlib writes atomic_path's temporary (a figure)",
    ("nerfgauge/core/scratch.py", "owned.rename(new, folder)"):
        "core.owned's own rename (the lint knows calls by their name only)",
    ("nerfgauge/methods/sfm.py", "best.write_binary(str(owned.make_folder("):
        "pycolmap writes its model into a folder core.owned just made (checked for links)",
}


def raw_calls(path: Path) -> list:
    """(line number, source text of the call) of every raw write/delete/rename in the file."""
    source = path.read_text()
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        raw = False
        if isinstance(func, ast.Attribute):
            owner = func.value.id if isinstance(func.value, ast.Name) else None
            raw = func.attr in RAW_METHODS or (owner, func.attr) in RAW_FUNCTIONS
            if func.attr == "replace" and len(node.args) == 1 and not node.keywords and owner != "dataclasses":
                # Path.replace(target); str.replace takes two arguments
                raw = True
            if func.attr == "open" and owner != "os":  # Path.open(mode) writing
                raw = _writing_mode(node, 0)
            if (owner, func.attr) == ("os", "open"):  # os.open(path, flags): raw when the flags write
                flags = ast.get_source_segment(source, node.args[1]) if len(node.args) > 1 else ""
                raw = any(flag in flags for flag in ("O_WRONLY", "O_RDWR", "O_CREAT", "O_TRUNC", "O_APPEND"))
        elif isinstance(func, ast.Name) and func.id == "open":  # open(path, mode) writing
            raw = _writing_mode(node, 1)
        if raw:
            found.append((node.lineno, ast.get_source_segment(source, node)))
    return found


def _writing_mode(call: ast.Call, position: int) -> bool:
    mode = call.args[position] if len(call.args) > position else next(
        (k.value for k in call.keywords if k.arg == "mode"), None)
    return isinstance(mode, ast.Constant) and isinstance(mode.value, str) and any(c in mode.value for c in "wax+")


class TestNoRawWrites:
    def test_every_delete_rename_and_write_goes_through_the_core_helpers(self):
        offending, used = [], set()
        for folder in SOURCES:
            for path in sorted((REPOSITORY / folder).rglob("*.py")):
                rel = path.relative_to(REPOSITORY).as_posix()
                if rel in HELPERS:
                    continue
                for line, text in raw_calls(path):
                    allowed = [key for key in ALLOWED if key[0] == rel and key[1] in text]
                    used.update(allowed)
                    if not allowed:
                        offending.append(f"{rel}:{line}: {text.splitlines()[0]}")
        assert not offending, ("raw writes, deletes or renames outside nerfgauge/core/owned.py and files.py "
                               "(use core.owned / core.files, or add a commented entry to ALLOWED):\n  "
                               + "\n  ".join(offending))
        assert used == set(ALLOWED), f"ALLOWED entries that match nothing any more: {sorted(set(ALLOWED) - used)}"

    def test_the_lint_sees_each_kind_of_raw_call(self, tmp_path):
        """The lint is not blind: each form it must catch, caught."""
        sample = tmp_path / "sample.py"
        sample.write_text("import os, shutil, torch\n"
                          "p.unlink()\nshutil.rmtree(p)\nos.replace(a, b)\np.replace(q)\np.mkdir()\n"
                          "open(p, 'w')\np.open('a')\np.write_bytes(b'')\nimage.save(p)\ntorch.save(x, p)\n"
                          "fig.savefig(p)\nos.remove(p)\nos.link(a, b)\n"
                          "os.open(p, os.O_WRONLY | os.O_CREAT)\n"
                          "s.replace('a', 'b')\nopen(p)\np.open()\nitems.remove(3)\nos.open(p, os.O_RDONLY)\n")
        assert [line for line, _ in raw_calls(sample)] == list(range(2, 16))


# --------------------------------------------------------------------------------------


def dataset_copy(source: Path, where: Path) -> Path:
    shutil.copytree(source, where, symlinks=True)
    return where


@pytest.fixture(scope="module")
def exported_dataset(tmp_path_factory):
    """primitives, 4/1/2 views at 24 px, 4 spp, with the default COLMAP export (images/, sparse/0)."""
    from conftest import generate_small

    return generate_small(tmp_path_factory.mktemp("links") / "ds", width=24, height=24)


GENERATE_ARGS = ["primitives", "--views", "4", "--val-views", "1", "--test-views", "2", "--res", "24", "--spp", "4",
                 "--quiet"]


@pytest.fixture(scope="module")
def suite(tmp_path_factory):
    """(suite TOML, a one-dataset 16 px suite folder, predictions: the dataset's own test PNGs)."""
    from suite_toml import one_scene_suite

    return one_scene_suite(tmp_path_factory.mktemp("suite-links"))


class TestLinksInsideOurFolders:
    @pytest.mark.parametrize("linked", ["images", "sparse/0"])
    def test_export_colmap_through_a_linked_folder_is_refused(self, exported_dataset, tmp_path, capsys, linked):
        ds = dataset_copy(exported_dataset, tmp_path / "e01")
        user = user_folder(tmp_path)
        replace_with_link(ds / linked, user)
        before, ours_before = snapshot(user), snapshot(ds)
        one_line_exit_2(capsys, ["export", "colmap", ds, "--points", "none"], f"{ds / linked} is a symbolic link")
        assert snapshot(user) == before
        assert {k: v for k, v in snapshot(ds).items() if ".nerfgauge.lock" not in k} == \
            {k: v for k, v in ours_before.items() if ".nerfgauge.lock" not in k}

    @pytest.mark.parametrize("linked", ["images", "train"])
    def test_generate_resuming_through_a_linked_folder_is_refused(self, exported_dataset, tmp_path, capsys, linked):
        """The issue's example: a view missing, `train/` (where it renders) or `images/` (which
        the export prunes) a link to the user's folder."""
        ds = dataset_copy(exported_dataset, tmp_path / "g01")
        user = tmp_path / "user"
        shutil.copytree(ds / linked, user)  # the user's folder: the same names, a view missing
        (user / "my_notes.txt").write_text("notes\n")
        for name in ("r_000.png", "r_000_noise.json"):
            (user / name).unlink(missing_ok=True)
        replace_with_link(ds / linked, user)
        (ds / "manifest.json").unlink()
        before = snapshot(user)
        one_line_exit_2(capsys, ["generate", *GENERATE_ARGS, "--out", ds], f"{ds / linked} is a symbolic link")
        assert snapshot(user) == before

    def test_train_resume_with_a_linked_file_in_the_run_is_refused(self, exported_dataset, tmp_path, capsys):
        run = tmp_path / "run"
        argv = ["train", exported_dataset, "--out", run, "--steps", "4", "--checkpoint-every", "2", "--threads", "1",
                "--quiet"]
        assert main([str(a) for a in argv]) == 0
        capsys.readouterr()
        user = user_folder(tmp_path)
        (user / "log.jsonl").write_bytes((run / "log.jsonl").read_bytes())
        replace_with_link(run / "log.jsonl", user / "log.jsonl")
        before = snapshot(user)
        one_line_exit_2(capsys, argv + ["--resume"], f"{run / 'log.jsonl'} is a symbolic link")
        assert snapshot(user) == before

    def test_suite_evaluate_through_a_linked_results_folder_is_refused(self, suite, tmp_path, capsys):
        toml, out, pred = suite
        suite_copy = dataset_copy(out, tmp_path / "S")
        user = user_folder(tmp_path)
        (suite_copy / "results").mkdir(exist_ok=True)
        replace_with_link(suite_copy / "results" / "nearest", user)
        before = snapshot(user)
        one_line_exit_2(capsys, ["suite", "evaluate", toml, suite_copy, "--method", "nearest", "--pred", pred],
                        f"{suite_copy / 'results' / 'nearest'} is a symbolic link")
        assert snapshot(user) == before

    def test_suite_generate_resuming_with_a_link_in_a_dataset_is_refused(self, suite, tmp_path, capsys):
        toml, out, _ = suite
        suite_copy = dataset_copy(out, tmp_path / "S")
        user = user_folder(tmp_path)
        dataset = suite_copy / "datasets" / "primitives"
        (dataset / "manifest.json").unlink()  # incomplete: the rerun must resume into it
        replace_with_link(dataset / "meshes", user)
        before = snapshot(user)
        one_line_exit_2(capsys, ["suite", "generate", toml, "--out", suite_copy], f"{dataset / 'meshes'} is a symbolic link")
        assert snapshot(user) == before


# --------------------------------------------------------------------------------------


def journal_case(exported_dataset, tmp_path, journal) -> Path:
    """A copy of the dataset as a killed export leaves it: the journal written, manifest.json gone."""
    ds = dataset_copy(exported_dataset, tmp_path / "e03")
    (ds / ".nerfgauge-export.json").write_text(journal if isinstance(journal, str) else json.dumps(journal))
    (ds / "manifest.json").unlink()
    return ds


def valid_journal(ds: Path) -> dict:
    return {"manifest": (ds / "manifest.json").read_text(),
            "files": {name: (ds / name).read_text() for name in ("scene.json", "transforms.json")}}


class TestExportJournal:
    def test_the_issues_example_absolute_and_dot_dot_names_write_nothing(self, exported_dataset, tmp_path, capsys,
                                                                          monkeypatch):
        work = tmp_path / "work"
        work.mkdir()
        monkeypatch.chdir(work)
        journal = {"manifest": (exported_dataset / "manifest.json").read_text(),
                   "files": {str(work / "ABS.txt"): "x", "../REL.txt": "y"}}
        ds = journal_case(exported_dataset, work, journal)
        outside = snapshot(tmp_path)
        one_line_exit_2(capsys, ["export", "colmap", ds, "--points", "none"], "ABS.txt", "export journal")
        assert not (work / "ABS.txt").exists() and not (ds.parent / "REL.txt").exists()
        assert {k: v for k, v in snapshot(tmp_path).items() if ".nerfgauge.lock" not in k} == \
            {k: v for k, v in outside.items() if ".nerfgauge.lock" not in k}

    @pytest.mark.parametrize("case", [
        "not json", "a list", "files a list", "manifest a number", "an extra key", "a file's text a number",
        "another file named", "scene.json not json", "manifest not json", "manifest entry climbs out",
        "manifest entry absolute", "manifest hash of a view altered", "manifest lacks scene.json",
        "scene.json text differs from the manifest", "deeply nested"])
    def test_a_journal_that_is_not_one_an_export_wrote_is_one_line(self, exported_dataset, tmp_path, capsys, case):
        good = valid_journal(exported_dataset)
        manifest = json.loads(good["manifest"])

        def with_manifest(change):
            edited = json.loads(good["manifest"])
            change(edited["files"])
            return {**good, "manifest": json.dumps(edited)}

        view = next(rel for rel in manifest["files"] if rel.startswith("train/"))
        journal = {
            "not json": "{not json",
            "a list": [good],
            "files a list": {**good, "files": list(good["files"].items())},
            "manifest a number": {**good, "manifest": 3},
            "an extra key": {**good, "run": "rm -rf"},
            "a file's text a number": {**good, "files": {"scene.json": 7}},
            "another file named": {**good, "files": {**good["files"], "train/r_000.png": "x"}},
            "scene.json not json": {**good, "files": {**good["files"], "scene.json": "{"}},
            "manifest not json": {**good, "manifest": "{"},
            "manifest entry climbs out": with_manifest(lambda f: f.update({"../x": f[view]})),
            "manifest entry absolute": with_manifest(lambda f: f.update({"/etc/passwd": f[view]})),
            "manifest hash of a view altered": with_manifest(lambda f: f[view].update(sha256="0" * 64)),
            "manifest lacks scene.json": with_manifest(lambda f: f.pop("scene.json")),
            "scene.json text differs from the manifest": {**good, "files": {**good["files"], "scene.json": "{}"}},
            "deeply nested": "[" * 100_000 + "]" * 100_000,
        }[case]
        ds = journal_case(exported_dataset, tmp_path, journal)
        before = snapshot(tmp_path)
        one_line_exit_2(capsys, ["export", "colmap", ds, "--points", "none"], str(ds / ".nerfgauge-export.json"))
        assert {k: v for k, v in snapshot(tmp_path).items() if ".nerfgauge.lock" not in k} == \
            {k: v for k, v in before.items() if ".nerfgauge.lock" not in k}

    def test_a_journal_an_export_wrote_is_restored_and_the_export_redone(self, exported_dataset, tmp_path, capsys):
        """The kill the journal is for: after an export to `none` replaced scene.json and
        transforms.json and removed the manifest, `export colmap` rolls back and redoes it,
        ending with the bytes an uninterrupted export makes."""
        from nerfgauge.core.dataset import verify_manifest

        reference = dataset_copy(exported_dataset, tmp_path / "reference")
        assert main(["export", "colmap", str(reference), "--points", "random:50"]) == 0
        ds = dataset_copy(exported_dataset, tmp_path / "killed")
        journal = valid_journal(ds)
        (ds / ".nerfgauge-export.json").write_text(json.dumps(journal))
        (ds / "manifest.json").unlink()
        (ds / "scene.json").write_text('{"half": "written by the export being undone"}')
        (ds / "sparse" / "0" / "points3D.ply").unlink()  # pruned before the kill
        assert main(["export", "colmap", str(ds), "--points", "random:50"]) == 0
        capsys.readouterr()
        assert not (ds / ".nerfgauge-export.json").exists() and not verify_manifest(ds)
        got = {k: v[3] for k, v in snapshot(ds).items() if v[0] == "file" and ".nerfgauge.lock" not in k}
        want = {k: v[3] for k, v in snapshot(reference).items() if v[0] == "file" and ".nerfgauge.lock" not in k}
        assert got == want


# --------------------------------------------------------------------------------------


class TestResumeRecords:
    @pytest.mark.parametrize("record", [
        {"spp": "x"}, [], {"spp": 4, "passes": [2, 2]}, "garbage",
        {"noise_psnr": None, "psnr_ceiling": None, "reason": 3, "spp": 1, "passes": [1],
         "png_quantisation_mse": {"black": 0.0, "white": 0.0}},
        {"noise_psnr": {"linear": 30.0, "srgb_black": 30.0, "srgb_white": 30.0}, "spp": 4, "passes": [2, 3],
         "psnr_ceiling": {"black": 1.0, "white": 1.0}, "png_quantisation_mse": {"black": 0.0, "white": 0.0}}])
    def test_a_noise_record_that_is_not_ours_renders_its_view_again(self, exported_dataset, tmp_path, capsys, record):
        """A view whose noise record is not what the renderer writes is not complete: the rerun
        renders it again (the same bytes), instead of carrying the record into scene.json."""
        ds = dataset_copy(exported_dataset, tmp_path / "ds")
        noise = ds / "train" / "r_001_noise.json"
        kept = noise.read_bytes()
        noise.write_text(record if isinstance(record, str) else json.dumps(record))
        (ds / "manifest.json").unlink()
        assert main(["generate", *GENERATE_ARGS, "--out", str(ds)]) == 0
        assert "1 views rendered" in capsys.readouterr().out
        assert noise.read_bytes() == kept and (ds / "scene.json").read_bytes() == \
            (exported_dataset / "scene.json").read_bytes()

    @pytest.mark.parametrize("line", ['{"step": true}', '{"step": -1}', '{"step": "3"}', "[1]"])
    def test_a_log_line_without_a_real_step_is_refused_on_resume(self, exported_dataset, tmp_path, capsys, line):
        run = tmp_path / "run"
        argv = ["train", exported_dataset, "--out", run, "--steps", "4", "--checkpoint-every", "2", "--threads", "1",
                "--quiet"]
        assert main([str(a) for a in argv]) == 0
        capsys.readouterr()
        log = run / "log.jsonl"
        log.write_text(line + "\n" + log.read_text())
        one_line_exit_2(capsys, argv + ["--resume"], f"{log} line 1")


# --------------------------------------------------------------------------------------


class TestUnresolvedGeometry:
    def test_the_issues_tiny_example_exports_without_points_and_says_why(self, tmp_path, capsys):
        from nerfgauge.core.dataset import Dataset
        from nerfgauge.generate.export import NO_VISIBLE_SURFACE

        out = tmp_path / "tiny"
        code = main(["generate", "tiny", "--res", "24", "--views", "4", "--val-views", "1", "--test-views", "2",
                     "--spp", "4", "--quiet", "--out", str(out)])
        printed = capsys.readouterr()
        assert code == 0, printed.err
        assert "7 views rendered" in printed.out and "without points (no train view resolves" in printed.out
        ds = Dataset(out)  # complete, every file verifying against its manifest
        points = ds.scene["points"]
        assert points["kind"] == "none" and points["count"] == 0 and points["note"] == NO_VISIBLE_SURFACE
        assert (out / "sparse" / "0" / "points3D.bin").is_file() and not (out / "sparse" / "0" / "points3D.ply").exists()
        assert "ply_file_path" not in read_json(out / "transforms.json")
        # the meshes are there: the reason is the views' resolution, not a scene without geometry
        assert any(rel.startswith("meshes/") for rel in ds.manifest_files)
