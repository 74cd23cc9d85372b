"""`generate --scheduler` (generate.distributed): the same bytes as one process, also after
a worker is killed mid-generation; idempotent tasks; one-line errors for bad addresses,
an unreachable scheduler and a missing dask; the default path never imports dask."""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from nerfgauge.cli import main
from nerfgauge.core import dataset
from nerfgauge.core.errors import InputError
from nerfgauge.generate import distributed
from nerfgauge.generate.pipeline import GenerateConfig, generate, plan

HAVE_DASK = importlib.util.find_spec("distributed") is not None
needs_dask = pytest.mark.skipif(not HAVE_DASK, reason="dask.distributed is not installed (the dask extra)")
TINY = dict(views=6, val_views=1, test_views=2, width=24, height=24, spp=4)


def tree(root: Path) -> dict:
    """{relative path: bytes} of every file, the lock file aside (it names its last holder's PID)."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != ".nerfgauge.lock"}


@pytest.mark.parametrize("text, expected", [
    ("local:2", ("local", 2)), ("local:1", ("local", 1)),
    ("tcp://127.0.0.1:8786", ("address", "tcp://127.0.0.1:8786")),
    ("tcp://node-12.cluster:8786", ("address", "tcp://node-12.cluster:8786")),
    ("tls://[::1]:8786", ("address", "tls://[::1]:8786")),
])
def test_scheduler_addresses_parse(text, expected):
    assert distributed.parse_scheduler(text) == expected


@pytest.mark.parametrize("text", ["", "local:", "local:0", "local:-1", "local:x", "127.0.0.1:8786", "tcp://:8786",
                                  "tcp://host", "tcp://host:0", "tcp://host:65536", "http://host:80", "tcp://a b:1"])
def test_malformed_addresses_exit_2_in_one_line_and_write_nothing(text, tmp_path, capsys):
    out = tmp_path / "ds"
    assert main(["generate", "primitives", "--out", str(out), "--views", "2", "--res", "16", "--quiet",
                 "--scheduler", text]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--scheduler" in err and "Traceback" not in err
    assert not out.exists()


@needs_dask
def test_an_unreachable_scheduler_is_one_line_within_the_timeout(tmp_path, capsys, monkeypatch):
    import socket

    monkeypatch.setattr(distributed, "CONNECT_TIMEOUT_SECONDS", 1.0)
    with socket.socket() as probe:  # a port nobody listens on: bound, never listening
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
        out = tmp_path / "ds"
        start = time.monotonic()
        code = main(["generate", "primitives", "--out", str(out), "--views", "2", "--res", "16", "--quiet",
                     "--scheduler", f"tcp://127.0.0.1:{port}"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert f"cannot reach the dask scheduler at tcp://127.0.0.1:{port} within 1 s" in err
    assert time.monotonic() - start < 15 and not out.exists()


def test_without_dask_scheduler_is_one_line_and_workers_clash(tmp_path, capsys, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name in ("dask", "distributed")
                        else real(name, *a))
    out = tmp_path / "ds"
    assert main(["generate", "primitives", "--out", str(out), "--views", "2", "--res", "16", "--quiet",
                 "--scheduler", "local:2"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "needs dask.distributed, which is not installed: pip install 'nerfgauge[dask]'" in err
    assert not out.exists()
    monkeypatch.undo()
    if HAVE_DASK:
        with pytest.raises(InputError, match="--workers 2 and --scheduler local:2"):
            generate(GenerateConfig(**TINY), out, workers=2, scheduler="local:2", progress=False)


@pytest.mark.slow  # a fresh interpreter imports Mitsuba: 5-10 s on a loaded machine
def test_the_default_path_imports_no_dask(tmp_path):
    code = ("import sys; from nerfgauge.generate.pipeline import GenerateConfig, generate; "
            f"generate(GenerateConfig(views=2, val_views=0, test_views=1, width=16, height=16, spp=2), {str(tmp_path / 'd')!r}, "
            "workers=1, progress=False); "
            "assert not {'dask', 'distributed'} & set(sys.modules), sorted(m for m in sys.modules if 'dask' in m)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]


def test_a_task_is_idempotent(tmp_path, make_dataset):
    """A retried task whose view is complete writes nothing; one whose files are partly
    gone writes them again, with the same bytes."""
    config = GenerateConfig(**TINY)
    out = make_dataset(tmp_path / "ds", **TINY)
    before = tree(out)
    the_plan = plan(config)
    stem = the_plan.stems["train"][1]
    png = out / (stem + ".png")
    mtime = png.stat().st_mtime_ns
    assert distributed.render_task(str(out), the_plan, "r", "train", 1) == 0.0  # complete: skipped
    assert png.stat().st_mtime_ns == mtime
    png.unlink()
    (out / (stem + "_distance.exr")).unlink()
    assert distributed.render_task(str(out), the_plan, "r", "train", 1) > 0.0  # rendered again
    assert tree(out) == before


@needs_dask
def test_a_task_failing_after_its_retries_is_one_clear_error(tmp_path):
    from distributed import Client
    from tqdm import tqdm

    the_plan = plan(GenerateConfig(**TINY))
    with distributed.local_cluster(1, processes=False) as cluster, \
            Client(cluster) as client, tqdm(disable=True) as bar:
        # no meshes in the folder: loading the scene fails on every try
        with pytest.raises(InputError, match=r"view train/r_000 failed on the dask cluster after its retries"):
            distributed.render_on_cluster(client, tmp_path / "empty", the_plan, [("train", 0)], bar)


@needs_dask
@pytest.mark.slow  # starts a LocalCluster of two processes (about 5-10 s here)
def test_local_cluster_gives_the_single_process_bytes(tmp_path, capsys):
    args = ["--views", "8", "--val-views", "1", "--test-views", "2", "--res", "24", "--spp", "4"]
    assert main(["generate", "primitives", "--out", str(tmp_path / "one"), "--quiet", *args]) == 0
    assert main(["generate", "primitives", "--out", str(tmp_path / "dask"), "--scheduler", "local:2", *args]) == 0
    captured = capsys.readouterr()
    assert "11 views rendered" in captured.out
    assert "11/11" in captured.err and "view/s" in captured.err  # tqdm: count, rate (and ETA) across the cluster
    assert tree(tmp_path / "one") == tree(tmp_path / "dask")
    # rerun: complete, nothing to render, nothing changed
    assert main(["generate", "primitives", "--out", str(tmp_path / "dask"), "--scheduler", "local:2", "--quiet", *args]) == 0
    assert "nothing to render" in capsys.readouterr().out
    assert tree(tmp_path / "one") == tree(tmp_path / "dask")


@needs_dask
@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="kills a worker process by PID")
def test_a_worker_killed_mid_generation_still_gives_the_single_process_bytes(tmp_path, monkeypatch):
    from distributed import Client

    config = GenerateConfig(views=60, val_views=0, test_views=2, width=32, height=32, spp=16)
    generate(config, tmp_path / "clean", progress=False)
    out = tmp_path / "killed"
    killed = {}

    def views_done():  # r_007.png is a view's last file (r_007_mask.png is not)
        return sum(not p.name.endswith("_mask.png") for p in out.glob("train/*.png"))

    def kill_a_worker(pids):
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and views_done() < 2:
            time.sleep(0.01)
        killed["views"], killed["pid"] = views_done(), pids[0]
        os.kill(pids[0], signal.SIGKILL)  # both workers are rendering: one of them dies mid-view

    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)  # tox sets it; here the cluster must
    with distributed.local_cluster(2, threads_per_worker=1) as cluster, \
            Client(cluster) as watcher:
        distributed.wait_for_workers(watcher, 2)
        assert set(watcher.run(os.getenv, "OMP_WAIT_POLICY").values()) == {"PASSIVE"}
        killer = threading.Thread(target=kill_a_worker, args=(sorted(watcher.run(os.getpid).values()),))
        killer.start()
        result = generate(config, out, scheduler=cluster.scheduler_address, progress=False)
        killer.join()
    assert "pid" in killed and killed["views"] < 62, killed  # the kill landed while views were left
    with pytest.raises(ProcessLookupError):
        os.kill(killed["pid"], 0)
    assert result["views_rendered"] == 62
    assert dataset.verify_manifest(out) == []
    assert tree(out) == tree(tmp_path / "clean")


def test_workers_sharing_the_cores_sleep_between_openmp_regions_unless_the_user_says():
    assert distributed.shared_cores_environment(2, environ={}) == {"OMP_WAIT_POLICY": "PASSIVE"}
    assert distributed.shared_cores_environment(8, environ={"OMP_WAIT_POLICY": "ACTIVE"}) == {}  # the user's
    assert distributed.shared_cores_environment(1, environ={}) == {}  # a lone worker spins as it likes
    assert distributed.shared_cores_environment(2, in_process=True, environ={}) == {}  # threads of this process


@pytest.mark.slow
@needs_dask
def test_suite_generate_on_a_local_cluster_equals_the_plain_run(tmp_path):
    """`suite generate --scheduler local:2` renders every dataset's views as cluster tasks:
    the suite folder (datasets and suite-manifest.json) equals a plain run byte for byte."""
    plain, clustered = tmp_path / "plain", tmp_path / "cluster"
    assert main(["suite", "generate", "smoke", "--out", str(plain)]) == 0
    assert main(["suite", "generate", "smoke", "--out", str(clustered), "--scheduler", "local:2"]) == 0
    assert tree(clustered) == tree(plain)


def test_suite_generate_refuses_a_malformed_scheduler_before_writing(tmp_path, capsys):
    out = tmp_path / "suite"
    assert main(["suite", "generate", "smoke", "--out", str(out), "--scheduler", "local:zero"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "local:N" in err[0] and not out.exists()
