"""The CLI boundary (RELIABILITY.md): every failure the user's environment or input can cause is
one line on stderr and exit 2 (3 for NaN results, 130 for Ctrl-C), never a traceback;
numeric flags refuse NaN, inf and non-positive counts; commands write only into folders
nerfgauge made, and delete only those.

Each test goes through `nerfgauge.cli.main([...])` and snapshots tmp_path before and after:
a refused command leaves everything as it was. Faults are real where this machine allows
(/proc, a path under a regular file, /dev/full, a FIFO, a 64 KiB tmpfs filled up, a
read-only tmpfs: mounts need root and are skipped otherwise); a full disk, a read-only
file system and permission denied are also injected into one write, so the translation
is checked where mounts are not available.
"""

from __future__ import annotations

import errno
import os
import stat
import subprocess
from pathlib import Path

import pytest

from nerfgauge.cli import main
from nerfgauge.core.errors import InputError, NumericalError, input_error_from_os, os_errors_as_input_errors
from nerfgauge.core.folders import LOCK, MARKER, read_marker, write_marker


def snapshot(root: Path) -> dict:
    """Every path under root (symlinks not followed) with its type and content hash; lock
    files (.nerfgauge.lock, in folders that already hold our marker) aside."""
    import hashlib

    found = {}
    for path in sorted(root.rglob("*")):
        if path.name == LOCK:
            assert (path.parent / MARKER).is_file(), f"a lock file in a folder nerfgauge did not make: {path}"
            continue
        mode = path.lstat().st_mode
        if stat.S_ISREG(mode):
            found[str(path.relative_to(root))] = ("file", hashlib.sha256(path.read_bytes()).hexdigest())
        else:
            found[str(path.relative_to(root))] = (stat.filemode(mode)[0], None)
    return found


def one_error_line(capsys, command: str) -> str:
    """stderr of the last command: exactly one line, `nerfgauge COMMAND: error: ...`, no traceback."""
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"nerfgauge {command}: error: "), err
    assert "Traceback" not in err
    return lines[0]


@pytest.fixture(scope="module")
def predictions(tmp_path_factory, tiny_dataset):
    """The tiny dataset's test split rendered by the nearest-view baseline (a prediction folder)."""
    out = tmp_path_factory.mktemp("predictions") / "nearest"
    assert main(["baseline", str(tiny_dataset), "--method", "nearest", "--out", str(out)]) == 0
    return out


# --------------------------------------------------------------------------------------
# the translation itself


def test_an_os_error_becomes_one_line_naming_its_paths_and_reason():
    error = input_error_from_os(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/data/a.tmp", None, "/data/a"))
    assert isinstance(error, InputError) and error.errno == errno.ENOSPC
    assert str(error) == "/data/a.tmp -> /data/a: No space left on device (ENOSPC)"
    assert str(input_error_from_os(PermissionError(errno.EACCES, "Permission denied", "/x\ny"))) == \
        "/x\\ny: Permission denied (EACCES)"  # a newline in a path does not make a second line
    assert str(input_error_from_os(OSError(errno.EIO, os.strerror(errno.EIO)))) == \
        "Input/output error (EIO)"
    with pytest.raises(InputError, match=r"^/nowhere/x: No such file or directory \(ENOENT\)$") as raised:
        with os_errors_as_input_errors():
            open("/nowhere/x")
    assert isinstance(raised.value.__cause__, FileNotFoundError)


# --------------------------------------------------------------------------------------
# OS errors: real faults


def test_evaluate_out_under_proc_is_one_line(tiny_dataset, predictions, tmp_path, capsys):
    before = snapshot(predictions)
    assert main(["evaluate", str(tiny_dataset), "--pred", str(predictions), "--out", "/proc/nerfgauge-x/m.json"]) == 2
    line = one_error_line(capsys, "evaluate")
    assert "/proc/nerfgauge-x" in line
    assert snapshot(predictions) == before and not Path("/proc/nerfgauge-x").exists()


def test_run_out_under_proc_is_one_line(tmp_path, capsys):
    assert main(["run", "--out", "/proc/nerfgauge-x", "--steps", "2", "--res", "16", "--quiet"]) == 2
    assert "/proc/nerfgauge-x: No such file or directory (ENOENT)" in one_error_line(capsys, "run")


@pytest.mark.parametrize("command", [
    ["run", "--steps", "2", "--res", "16", "--quiet", "--out"],
    ["bench", "train", "--out"],
    ["bench", "scaling", "--out"],
    ["bench", "hard", "--scenes", "thin", "--out"],
])
def test_an_out_folder_under_a_regular_file_is_one_line(tmp_path, capsys, command):
    (tmp_path / "file").write_text("precious")
    before = snapshot(tmp_path)
    assert main([*command, str(tmp_path / "file" / "sub")]) == 2
    line = one_error_line(capsys, " ".join(c for c in command[:2] if not c.startswith("-")))
    assert f"{tmp_path / 'file' / 'sub'}" in line and "Not a directory (ENOTDIR)" in line
    assert snapshot(tmp_path) == before


def test_evaluate_and_baseline_out_under_a_regular_file(tiny_dataset, predictions, tmp_path, capsys):
    (tmp_path / "file").write_text("precious")
    before = snapshot(tmp_path)
    assert main(["evaluate", str(tiny_dataset), "--pred", str(predictions),
                 "--out", str(tmp_path / "file" / "metrics.json")]) == 2
    assert f"{tmp_path / 'file'}" in one_error_line(capsys, "evaluate")
    assert main(["baseline", str(tiny_dataset), "--method", "nearest", "--out", str(tmp_path / "file" / "b")]) == 2
    assert f"{tmp_path / 'file' / 'b'}: Not a directory" in one_error_line(capsys, "baseline")
    assert main(["check", str(predictions / "metrics.json"), "--thresholds", str(tmp_path / "file"),
                 "--junit", str(tmp_path / "file" / "j.xml")]) == 2
    one_error_line(capsys, "check")
    assert snapshot(tmp_path) == before


def test_evaluate_out_dev_full_and_a_fifo_are_refused_untouched(tiny_dataset, predictions, tmp_path, capsys):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    before, predictions_before = snapshot(tmp_path), snapshot(predictions)
    dev_maps = Path("/dev/error_maps")  # where the maps of `--out /dev/full` went before the fix
    dev_maps_before = snapshot(dev_maps) if dev_maps.exists() else None
    for target in ("/dev/full", str(fifo)):
        assert main(["evaluate", str(tiny_dataset), "--pred", str(predictions), "--out", target]) == 2
        assert f"refusing to write {target}: it is not a regular file" in one_error_line(capsys, "evaluate")
    assert stat.S_ISCHR(os.stat("/dev/full").st_mode)
    assert (snapshot(dev_maps) if dev_maps.exists() else None) == dev_maps_before
    assert stat.S_ISFIFO(fifo.lstat().st_mode)
    assert snapshot(tmp_path) == before and snapshot(predictions) == predictions_before
    assert main(["check", str(predictions / "metrics.json"), "--thresholds", str(tmp_path / "t.toml"),
                 "--junit", "/dev/full"]) == 2
    assert "refusing to write /dev/full" in one_error_line(capsys, "check")


def test_a_real_full_disk_is_one_line(tiny_dataset, predictions, mount_tmpfs, capsys):
    disk = mount_tmpfs("size=64k")
    fd = os.open(disk / "filler", os.O_WRONLY | os.O_CREAT)
    try:  # fill it up, unbuffered
        for size in (4096, 1):
            with pytest.raises(OSError) as full:
                while True:
                    os.write(fd, b"\0" * size)
            assert full.value.errno == errno.ENOSPC
    finally:
        os.close(fd)
    assert main(["evaluate", str(tiny_dataset), "--pred", str(predictions), "--out", str(disk / "m.json")]) == 2
    # write() does not name its file (the OSError has no filename), so the line may not either
    assert "No space left on device (ENOSPC)" in one_error_line(capsys, "evaluate")
    assert sorted(p.name for p in disk.rglob("*") if p.is_file() and p.name != ".nerfgauge.lock"
                  and p.stat().st_size) == ["filler"]  # no partial file left that looks complete


def test_a_real_read_only_file_system_is_one_line(tiny_dataset, predictions, mount_tmpfs, capsys):
    disk = mount_tmpfs("ro,size=64k")
    for argv, command in [(["evaluate", str(tiny_dataset), "--pred", str(predictions), "--out",
                            str(disk / "m.json")], "evaluate"),
                          (["baseline", str(tiny_dataset), "--method", "nearest", "--out", str(disk / "b")], "baseline"),
                          (["run", "--steps", "2", "--res", "16", "--quiet", "--out", str(disk / "r")], "run")]:
        assert main(argv) == 2
        assert "Read-only file system (EROFS)" in one_error_line(capsys, command)
    assert list(disk.iterdir()) == []


@pytest.mark.parametrize("code,reason", [(errno.ENOSPC, "No space left on device (ENOSPC)"),
                                         (errno.EROFS, "Read-only file system (EROFS)"),
                                         (errno.EACCES, "Permission denied (EACCES)")])
def test_an_injected_write_failure_names_the_file_and_reason(tiny_dataset, predictions, tmp_path, capsys,
                                                             monkeypatch, code, reason):
    """The metrics file's write fails as a full disk, a read-only mount or a denied
    permission would make it fail (root ignores permission bits, so it is injected)."""
    import nerfgauge.eval.evaluate as evaluate_module

    def failing_write(path, obj):
        raise OSError(code, os.strerror(code), str(path))

    monkeypatch.setattr(evaluate_module, "write_json", failing_write)
    out = tmp_path / "e" / "metrics.json"
    assert main(["evaluate", str(tiny_dataset), "--pred", str(predictions), "--out", str(out)]) == 2
    assert one_error_line(capsys, "evaluate") == f"nerfgauge evaluate: error: {out}: {reason}"
    assert not out.exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes through permission bits")
def test_a_real_read_only_folder_is_one_line(tiny_dataset, predictions, tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        assert main(["evaluate", str(tiny_dataset), "--pred", str(predictions), "--out",
                     str(locked / "m.json")]) == 2
        assert "Permission denied (EACCES)" in one_error_line(capsys, "evaluate")
        assert list(locked.iterdir()) == []
    finally:
        locked.chmod(0o755)


def test_a_huge_allocation_is_one_line(tiny_dataset, predictions, monkeypatch, capsys):
    import numpy as np

    import nerfgauge.eval.commands as eval_commands  # the `evaluate` command's own reference

    def huge(*args, **kwargs):
        return np.ones((1 << 27, 1 << 20))  # 1 PiB: more than any machine's address space holds

    monkeypatch.setattr(eval_commands, "evaluate", huge)
    assert main(["evaluate", str(tiny_dataset), "--pred", str(predictions)]) == 2
    assert "out of memory: Unable to allocate" in one_error_line(capsys, "evaluate")


def test_debug_shows_the_traceback_and_other_exit_codes_stay(monkeypatch, capsys, tmp_path):
    import nerfgauge.eval.commands as eval_commands

    def raising(error):
        def run(args):
            raise error
        return run

    monkeypatch.setattr(eval_commands, "run_check", raising(OSError(errno.ENOSPC, "No space left on device", "x")))
    argv = ["check", "m.json", "--thresholds", "t.toml"]
    monkeypatch.setenv("NERFGAUGE_DEBUG", "1")
    with pytest.raises(OSError):
        main(argv)
    monkeypatch.delenv("NERFGAUGE_DEBUG")
    monkeypatch.setattr(eval_commands, "run_check", raising(NumericalError("loss became nan at step 3")))
    assert main(argv) == 3
    assert capsys.readouterr().err == "nerfgauge check: numerical error: loss became nan at step 3\n"
    monkeypatch.setattr(eval_commands, "run_check", raising(KeyboardInterrupt()))
    assert main(argv) == 130
    assert capsys.readouterr().err == "nerfgauge check: interrupted\n"
    monkeypatch.setattr(eval_commands, "run_check", raising(ZeroDivisionError("a bug")))
    with pytest.raises(ZeroDivisionError):  # a bug keeps its traceback
        main(argv)


# --------------------------------------------------------------------------------------
# arguments


@pytest.mark.parametrize("argv,expected", [
    (["bench", "train", "--budgets", "nan"], "argument --budgets: expected a finite number, got 'nan'"),
    (["bench", "train", "--budgets", "30,inf"], "argument --budgets: expected a finite number, got 'inf' (in '30,inf')"),
    (["bench", "train", "--budgets", "30,0"], "argument --budgets: expected a number above 0, up to 1e+07, got '0'"),
    (["bench", "train", "--budgets", "30,"], "argument --budgets: expected comma-separated values, got '30,'"),
    (["bench", "train", "--views", "0"], "argument --views: expected an integer from 1 to 100000, got '0'"),
    (["bench", "train", "--scenes", "a,,b"], "argument --scenes: expected comma-separated names"),
    (["bench", "generate", "--repeats", "0"], "argument --repeats: expected an integer from 1 to 10000, got '0'"),
    (["bench", "generate", "--spp", "nan"], "argument --spp: expected an integer, got 'nan'"),
    (["bench", "hard", "--steps", "-5"], "argument --steps: expected an integer from 1 to 1000000000, got '-5'"),
    (["bench", "hard", "--test-views", "inf"], "argument --test-views: expected an integer, got 'inf'"),
    (["bench", "scaling", "--budget-seconds", "nan"], "argument --budget-seconds: expected a finite number"),
    (["run", "--budget-seconds", "nan"], "argument --budget-seconds: expected a finite number, got 'nan'"),
    (["run", "--budget-seconds=-inf"], "argument --budget-seconds: expected a finite number, got '-inf'"),
    (["run", "--budget-seconds", "0"], "argument --budget-seconds: expected a number above 0, up to 1e+07, got '0'"),
    (["run", "--steps", "0"], "argument --steps: expected an integer from 1 to 1000000000, got '0'"),
    (["run", "--views", "1e3"], "argument --views: expected an integer, got '1e3'"),
    (["run", "--test-views", "0"], "argument --test-views: expected an integer from 1 to 100000, got '0'"),
    (["run", "--spp", "-1"], "argument --spp: expected an integer from 1 to 65536, got '-1'"),
    (["run", "--seed", "-1"], "argument --seed: expected an integer from 0 to 2147483647, got '-1'"),
    (["run", "--out", ""], "argument --out: expected a path, got an empty string"),
    (["generate", "primitives", "--out", "d", "--pose-noise-rotation", "-1"],
     "argument --pose-noise-rotation: expected a number from 0 to 45, got '-1'"),
    (["generate", "primitives", "--out", "d", "--pose-noise-translation", "nan"],
     "argument --pose-noise-translation: expected a finite number, got 'nan'"),
    (["generate", "primitives", "--out", "d", "--exposure-ev", "inf"],
     "argument --exposure-ev: expected a finite number, got 'inf'"),
    (["generate", "primitives", "--out", "d", "--white-balance", "-0.1"],
     "argument --white-balance: expected a number from 0 to 10, got '-0.1'"),
    (["generate", "primitives", "--out", "d", "--vignetting", "1"],
     "argument --vignetting: expected a number at least 0, below 1, got '1'"),
    (["run", "--degrade-seed", "-3"], "argument --degrade-seed: expected an integer from 0 to 2147483647, got '-3'"),
    (["evaluate", "ds", "--poses", ""], "argument --poses: expected a path, got an empty string"),
    (["evaluate", "ds", "--pred", ""], "argument --pred: expected a path, got an empty string"),
    (["baseline", "ds", "--method", "nearest", "--out", " "], "argument --out: expected a path"),
    (["check", "m.json", "--thresholds", ""], "argument --thresholds: expected a path"),
    (["evaluate", "ds"], "the following arguments are required: --pred"),
    (["bench"], "the following arguments are required: KIND"),
    (["no-such-command"], "argument COMMAND: invalid choice: 'no-such-command'"),
])
def test_bad_flags_are_one_line_without_usage_and_exit_2(tmp_path, capsys, monkeypatch, argv, expected):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and expected in err and "usage:" not in err, err
    assert list(tmp_path.iterdir()) == []


def test_help_still_prints_usage(capsys):
    assert main(["run", "--help"]) == 0
    assert capsys.readouterr().out.startswith("usage: nerfgauge run")
    assert main(["bench", "train", "--help"]) == 0
    assert "--budgets BUDGETS" in capsys.readouterr().out


# --------------------------------------------------------------------------------------
# folders: run --overwrite, baseline --out, evaluate's error maps, bench


def user_folder_like_a_pipeline(out: Path) -> None:
    """What an earlier run's layout looks like, but made by the user (no marker anywhere)."""
    for name in ("run", "eval/compact", "baselines/nearest", "report"):
        (out / name).mkdir(parents=True)
        (out / name / "precious.txt").write_text(name)
    (out / "report.html").write_text("mine")


def test_run_overwrite_never_deletes_a_folder_nerfgauge_did_not_make(tmp_path, capsys):
    out = tmp_path / "out"
    user_folder_like_a_pipeline(out)
    before = snapshot(tmp_path)
    assert main(["run", "--out", str(out), "--overwrite", "--steps", "2", "--res", "16", "--quiet"]) == 2
    assert "not made by nerfgauge" in one_error_line(capsys, "run")
    assert snapshot(tmp_path) == before


def test_run_overwrite_deletes_only_what_holds_our_marker(tmp_path, capsys):
    """A pipeline folder of ours (same settings) whose run/ is the user's: refused, all kept."""
    from nerfgauge.run import RunConfig

    out = tmp_path / "out"
    user_folder_like_a_pipeline(out)
    config = RunConfig(out=str(out), width=16, height=16, steps=2)
    write_marker(out, "pipeline", config.recipe())
    before = snapshot(tmp_path)
    assert main(["run", "--out", str(out), "--overwrite", "--steps", "2", "--res", "16", "--quiet"]) == 2
    assert f"refusing to delete {out / 'run'}: it has no {MARKER}" in one_error_line(capsys, "run")
    assert snapshot(tmp_path) == before


def test_run_overwrite_refuses_a_symlinked_run_folder(tmp_path, capsys):
    from nerfgauge.run import RunConfig

    precious = tmp_path / "precious"
    precious.mkdir()
    write_marker(precious, "run", None)  # even a nerfgauge run folder: not through a link
    (precious / "model.pt").write_bytes(b"weights")
    out = tmp_path / "out"
    out.mkdir()
    write_marker(out, "pipeline", RunConfig(out=str(out), width=16, height=16, steps=2).recipe())
    (out / "run").symlink_to(precious)
    before = snapshot(tmp_path)
    assert main(["run", "--out", str(out), "--overwrite", "--steps", "2", "--res", "16", "--quiet"]) == 2
    assert "symbolic link" in one_error_line(capsys, "run")
    assert snapshot(tmp_path) == before


def test_earlier_outputs_go_through_their_markers_and_user_files_stay(tmp_path):
    from nerfgauge.run import remove_earlier_outputs

    out = tmp_path / "out"
    for folder, kind in (("run", "run"), ("baselines/nearest", "baseline"), ("eval/compact/error_maps", "evaluation"),
                         ("eval/nearest/error_maps", "evaluation")):
        (out / folder).mkdir(parents=True)
        write_marker(out / folder, kind, None)
        (out / folder / "frame.png").write_bytes(b"png")
    for name in ("eval/compact/metrics.json", "eval/nearest/metrics.json", "report/curve.png", "report/grid.png",
                 "report.html"):
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text("old")
    (out / "eval" / "compact" / "notes.txt").write_text("mine")
    (out / "report" / "mine.png").write_text("mine")
    write_marker(out, "pipeline", None)
    remove_earlier_outputs(out, "compact")
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == \
        [MARKER, "eval", "eval/compact", "eval/compact/notes.txt", "report", "report/mine.png"]


def test_baseline_out_claims_its_folder(tiny_dataset, tmp_path, capsys):
    user = tmp_path / "user"
    user.mkdir()
    (user / "keep.txt").write_text("mine")
    before = snapshot(tmp_path)
    assert main(["baseline", str(tiny_dataset), "--method", "nearest", "--out", str(user)]) == 2
    assert "not made by nerfgauge" in one_error_line(capsys, "baseline")
    assert snapshot(tmp_path) == before

    out = tmp_path / "b"
    assert main(["baseline", str(tiny_dataset), "--method", "nearest", "--out", str(out)]) == 0
    assert read_marker(out)["kind"] == "baseline"
    assert main(["baseline", str(tiny_dataset), "--method", "nearest", "--out", str(out)]) == 0  # same: continues
    assert main(["baseline", str(tiny_dataset), "--method", "nearest", "--split", "val", "--out", str(out)]) == 2
    assert "pass --overwrite" in one_error_line(capsys, "baseline")
    assert main(["baseline", str(tiny_dataset), "--method", "nearest", "--split", "val", "--out", str(out),
                 "--overwrite"]) == 0
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == ["timing.json", "val"]


def test_evaluate_error_maps_never_go_into_a_folder_nerfgauge_did_not_make(tiny_dataset, predictions, tmp_path,
                                                                          capsys):
    (tmp_path / "error_maps").mkdir()
    (tmp_path / "error_maps" / "holiday.png").write_bytes(b"mine")
    before = snapshot(tmp_path)
    assert main(["evaluate", str(tiny_dataset), "--pred", str(predictions), "--out", str(tmp_path / "m.json")]) == 2
    assert "not made by nerfgauge" in one_error_line(capsys, "evaluate")
    assert snapshot(tmp_path) == before
    out = tmp_path / "fresh" / "m.json"
    assert main(["evaluate", str(tiny_dataset), "--pred", str(predictions), "--out", str(out)]) == 0
    assert read_marker(out.parent / "error_maps")["kind"] == "evaluation"


@pytest.mark.parametrize("kind", ["train", "scaling", "hard"])
def test_bench_refuses_a_folder_that_is_not_a_bench(tmp_path, capsys, kind):
    user = tmp_path / "user"
    user.mkdir()
    (user / "thesis.tex").write_text("mine")
    before = snapshot(tmp_path)
    extra = ["--scenes", "thin"] if kind == "hard" else []
    assert main(["bench", kind, *extra, "--out", str(user)]) == 2
    assert "not made by nerfgauge" in one_error_line(capsys, f"bench {kind}")
    assert snapshot(tmp_path) == before


def test_one_bench_does_not_write_into_another_bench_folder(tmp_path, capsys):
    out = tmp_path / "b"
    out.mkdir()
    write_marker(out, "bench", None)
    from nerfgauge.orchestrate.bench.common import claim_bench_folder

    with claim_bench_folder(tmp_path / "s", "scaling"):
        pass
    before = snapshot(tmp_path)
    assert main(["bench", "hard", "--scenes", "thin", "--out", str(tmp_path / "s")]) == 2
    assert "another recipe" in one_error_line(capsys, "bench hard")
    assert snapshot(tmp_path) == before


def test_a_closed_stdout_is_not_reported(tmp_path):
    """`nerfgauge scenes | head -1`: the reader left; exit 141 like SIGPIPE, nothing on stderr."""
    import sys

    read_end, write_end = os.pipe()
    os.close(read_end)  # every write to stdout now fails with EPIPE
    try:
        result = subprocess.run([sys.executable, "-m", "nerfgauge.cli", "scenes"], stdout=write_end,
                                stderr=subprocess.PIPE, timeout=120)
    finally:
        os.close(write_end)
    assert (result.returncode, result.stderr) == (141, b"")
