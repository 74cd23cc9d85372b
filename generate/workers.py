"""Rendering the pending views: in this process, or spread over worker processes.

The Mitsuba scene is loaded once per process. In-process, file writing runs on a
background thread while the next view renders (Dr.Jit releases the GIL while its kernels
run), so the generator's time stays close to Mitsuba's own render time.

Worker processes die with their parent: a `generate` killed with SIGKILL leaves no
workers rendering on (they would write into a folder whose lock is already released).
"""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor, as_completed

from nerfgauge.core.errors import raise_floating_point_warnings
from nerfgauge.generate.distributed import render_on_cluster
from nerfgauge.generate.views import load_mitsuba_scene, render_one, write_view
from nerfgauge.core.progress import progress as progress_bar

_WORKER = {}  # per worker process: the loaded scene (set once by the pool initializer)


def render_views(out, the_plan, todo, *, workers: int = 1, progress: bool = True, client=None) -> float:
    """Render and write every (split, index) in `todo`: on the dask cluster of `client`
    (a distributed.Client, see generate.distributed) if given, else here or on `workers`
    local processes. Returns seconds spent rendering (summed over processes)."""
    total = sum(len(s) for s in the_plan.stems.values())
    bar = progress_bar(total=total, initial=total - len(todo), unit="view", desc="generate", enabled=progress)
    try:
        if client is not None and todo:
            return render_on_cluster(client, out, the_plan, todo, bar)
        if workers == 1 or len(todo) < 2:
            return _render_here(out, the_plan, todo, bar)
        return _render_pool(out, the_plan, todo, workers, bar)
    finally:
        bar.close()


def _render_here(out, the_plan, todo, bar) -> float:
    mi, scene = load_mitsuba_scene(out, the_plan)
    render_seconds = 0.0
    with ThreadPoolExecutor(max_workers=1) as writer:
        pending = None
        for split, index in todo:
            images, seconds = render_one(mi, scene, out, the_plan, split, index)
            render_seconds += seconds
            if pending is not None:
                pending.result()  # at most one view waits for the disk
                bar.update(1)
            pending = writer.submit(write_view, out, the_plan.stems[split][index], images)
        if pending is not None:
            pending.result()
            bar.update(1)
    return render_seconds


PR_SET_PDEATHSIG = 1  # linux/prctl.h
PARENT_POLL_SECONDS = 0.5


def die_with_parent(parent_pid: int) -> None:
    """End this process when `parent_pid` (its parent) ends, however the parent ends.

    On Linux the kernel sends SIGKILL at the parent's death (prctl PR_SET_PDEATHSIG). It
    fires when the parent *thread* that started this process exits; ProcessPoolExecutor
    with the spawn context starts workers from the thread that calls submit() (Python
    3.9+, without max_tasks_per_child), which for render_views is the thread that runs
    the whole pool, so it lives as long as the parent needs the workers. Everywhere (and
    in case the parent died before prctl took effect) a daemon thread also exits the
    process once its parent PID changes (the orphan was re-parented)."""
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent_pid:
        os._exit(1)  # the parent is already gone

    def watch():
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_SECONDS)
        os._exit(1)

    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()


def _init_worker(out, the_plan, parent_pid):
    die_with_parent(parent_pid)
    raise_floating_point_warnings()  # as in the parent (core.errors): raised, never printed by a worker
    _WORKER["mi"], _WORKER["scene"] = load_mitsuba_scene(out, the_plan)
    _WORKER["out"], _WORKER["plan"] = out, the_plan


def _work(split, index) -> float:
    images, seconds = render_one(_WORKER["mi"], _WORKER["scene"], _WORKER["out"], _WORKER["plan"], split, index)
    write_view(_WORKER["out"], _WORKER["plan"].stems[split][index], images)
    return seconds


def _render_pool(out, the_plan, todo, workers, bar) -> float:
    # spawn, not fork: Dr.Jit's thread pool does not survive a fork.
    context = multiprocessing.get_context("spawn")
    render_seconds = 0.0
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_init_worker,
                             initargs=(out, the_plan, os.getpid())) as pool:
        futures = [pool.submit(_work, split, index) for split, index in todo]
        for future in as_completed(futures):
            render_seconds += future.result()
            bar.update(1)
    return render_seconds
