"""nerfgauge.core.folders and files: ownership before deletion, one writer per folder,
writes only to new paths or regular files (RELIABILITY.md: nothing lost)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from nerfgauge.core import folders
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_bytes_atomic, write_json


def claim(folder, recipe="r1", overwrite=False, kind="dataset"):
    with folders.claim_folder(folder, kind, recipe, overwrite=overwrite) as state:
        return state


def test_claim_states_new_resume_replaced(tmp_path):
    out = tmp_path / "ds"
    assert claim(out) == "new"
    assert folders.read_marker(out)["kind"] == "dataset"
    assert claim(out) == "resume"
    (out / "view.png").write_bytes(b"old")
    with pytest.raises(InputError, match="another recipe; pass --overwrite"):
        claim(out, "r2")
    assert (out / "view.png").exists()
    assert claim(out, "r2", overwrite=True) == "replaced"
    assert not (out / "view.png").exists()
    assert folders.read_marker(out)["recipe"] == "r2"


def test_user_folder_with_config_json_is_never_deleted(tmp_path):
    """The reported data loss: a folder with any config.json was taken for a dataset."""
    user = tmp_path / "project"
    (user / "src").mkdir(parents=True)
    (user / "src" / "keep").write_text("precious")
    write_json(user / "config.json", {"name": "my app"})
    before = sorted(p.relative_to(user) for p in user.rglob("*"))
    with pytest.raises(InputError, match="not made by nerfgauge"):
        claim(user, overwrite=True)
    assert sorted(p.relative_to(user) for p in user.rglob("*")) == before  # not even a lock file added
    with pytest.raises(InputError, match="no .nerfgauge.json"):
        folders.remove_owned(user, "dataset")
    assert (user / "src" / "keep").read_text() == "precious"


def test_other_kind_and_symlinks_refused(tmp_path):
    run = tmp_path / "run"
    claim(run, kind="run")
    with pytest.raises(InputError, match="holds a nerfgauge run, not a dataset"):
        claim(run, overwrite=True)
    with pytest.raises(InputError, match="not a dataset"):
        folders.remove_owned(run, "dataset")
    link = tmp_path / "link"
    link.symlink_to(run, target_is_directory=True)
    with pytest.raises(InputError, match="symbolic link"):
        claim(link, kind="run", overwrite=True)
    with pytest.raises(InputError, match="symbolic link"):
        folders.remove_owned(link, "run")
    assert (run / folders.MARKER).is_file()


def test_overwrite_does_not_follow_symlinks_inside(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep").write_text("x")
    out = tmp_path / "ds"
    claim(out)
    (out / "escape").symlink_to(outside, target_is_directory=True)
    claim(out, "r2", overwrite=True)
    assert (outside / "keep").read_text() == "x"
    assert not (out / "escape").exists()


def test_a_file_where_a_folder_should_be(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        claim(tmp_path / "file")


def test_second_writer_is_refused_with_the_holders_pid(tmp_path):
    out = tmp_path / "ds"
    with folders.folder_lock(out):
        with pytest.raises(InputError, match=f"in use by another nerfgauge process \\(PID {os.getpid()}\\)"):
            with folders.folder_lock(out):
                pass
    with folders.folder_lock(out):  # released: free again
        pass


def test_lock_dies_with_its_holder(tmp_path):
    """kill -9 of the holder frees the folder (the kernel drops the flock)."""
    out = tmp_path / "ds"
    code = ("import sys, time; from nerfgauge.core.folders import folder_lock\n"
            "with folder_lock(sys.argv[1]):\n    print('locked', flush=True); time.sleep(60)")
    holder = subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(InputError, match=f"PID {holder.pid}"):
            with folders.folder_lock(out):
                pass
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    with folders.folder_lock(out):
        pass


def test_only_the_lock_holder_cleans_temporaries(tmp_path):
    out = tmp_path / "ds"
    claim(out)
    (out / "train").mkdir()
    stale = out / "train" / ".r_000.png.tmp123"
    stale.write_bytes(b"half")
    claim(out)  # resume under the lock: stale temporaries go
    assert not stale.exists()


@pytest.mark.parametrize("make", ["fifo", "folder", "symlink", "device"])
def test_atomic_writes_refuse_special_targets(tmp_path, make):
    target = tmp_path / "target"
    if make == "fifo":
        os.mkfifo(target)
    elif make == "folder":
        target.mkdir()
    elif make == "symlink":
        (tmp_path / "real").write_text("keep")
        target.symlink_to(tmp_path / "real")
    else:
        target = Path("/dev/null")
    kind_before = target.lstat().st_mode
    with pytest.raises(InputError, match="refusing to write"):
        write_bytes_atomic(target, b"{}")
    assert target.lstat().st_mode == kind_before
    assert not list(tmp_path.glob(".*.tmp*"))


def test_atomic_write_replaces_a_regular_file_whole(tmp_path):
    target = tmp_path / "a.json"
    target.write_text("old")
    write_bytes_atomic(target, b"new")
    assert target.read_bytes() == b"new"
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]


def test_recipe_hash_is_canonical():
    assert folders.recipe_hash({"a": 1, "b": [1, 2]}) == folders.recipe_hash({"b": [1, 2], "a": 1})
    assert folders.recipe_hash({"a": 1}) != folders.recipe_hash({"a": 2})


def test_temporaries_of_a_nested_claimed_folder_are_left_to_its_claimer(tmp_path):
    out = tmp_path / "pipeline"
    claim(out, kind="pipeline")
    claim(out / "dataset")
    live = out / "dataset" / ".r_000.png.tmp99"
    live.write_bytes(b"being written by the dataset's own writer")
    stale = out / ".report.html.tmp98"
    stale.write_bytes(b"left by a killed run")
    claim(out, kind="pipeline")
    assert live.exists() and not stale.exists()


def test_a_full_disk_names_the_file(tmp_path, monkeypatch):
    import errno

    target = tmp_path / "out.json"

    def full(self, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", full)
    with pytest.raises(OSError) as raised:
        write_bytes_atomic(target, b"{}")
    assert raised.value.filename == str(target) and raised.value.errno == errno.ENOSPC
    assert not target.exists()
