"""Rendering the pending views on a dask.distributed cluster: `generate --scheduler ADDRESS`.

    --scheduler tcp://HOST:PORT   a running scheduler (`dask scheduler`, dask-jobqueue on
                                  SLURM, dask-kubernetes, ...); its workers must have
                                  nerfgauge installed and see the output folder at the
                                  same path (a shared filesystem)
    --scheduler local:N           an in-process LocalCluster of N worker processes

Each view is one task, named by the recipe hash and the view, whose function renders the
view with the seed of (seed, split, index) and writes its files through the atomic writers
(core.images: a temporary name, renamed). A task whose view is already complete on disk
writes nothing, so a task retried after a lost worker, or run twice, leaves the same files,
and the dataset equals a single-process run byte for byte. A task that raises is retried
`RETRIES` times (dask `retries=`); a task whose worker dies is rescheduled by the scheduler
(up to its `distributed.scheduler.allowed-failures`, 3 by default). Dask is imported only
here, only with --scheduler (the `dask` extra: pip install 'nerfgauge[dask]').
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import re
import threading
import time
from pathlib import Path

from nerfgauge.core.errors import InputError
from nerfgauge.core.folders import recipe_hash
from nerfgauge.generate.views import load_mitsuba_scene, render_one, view_complete, write_view

RETRIES = 2  # a task that raises runs up to 3 times
CONNECT_TIMEOUT_SECONDS = 5.0
LOCAL_PREFIX = "local:"
ADDRESS = re.compile(r"^(tcp|tls|ws|wss|ucx)://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})$")
INSTALL_HINT = "pip install 'nerfgauge[dask]' (or dask[distributed])"


def parse_scheduler(text: str) -> tuple[str, object]:
    """"local:2" -> ("local", 2); "tcp://10.0.0.5:8786" -> ("address", "tcp://10.0.0.5:8786").
    Anything else is an InputError naming the two accepted forms."""
    if not isinstance(text, str):
        raise InputError(f"--scheduler must be tcp://HOST:PORT or local:N, got {text!r}")
    if text.startswith(LOCAL_PREFIX):
        count = text[len(LOCAL_PREFIX):]
        if not count.isdigit() or int(count) < 1 or int(count) > 1024:
            raise InputError(f"--scheduler {text!r}: local:N needs N worker processes, 1 to 1024")
        return "local", int(count)
    match = ADDRESS.match(text)
    if not match:
        raise InputError(f"--scheduler {text!r} is not tcp://HOST:PORT or local:N")
    if not 1 <= int(match.group(3)) <= 65535:
        raise InputError(f"--scheduler {text!r}: port {match.group(3)} is not in 1..65535")
    return "address", text


def require_dask() -> None:
    """A one-line InputError when dask.distributed is not installed."""
    if importlib.util.find_spec("distributed") is None or importlib.util.find_spec("dask") is None:
        raise InputError(f"--scheduler needs dask.distributed, which is not installed: {INSTALL_HINT}")


@contextlib.contextmanager
def dask_client(scheduler: str):
    """A distributed.Client on `scheduler` for the duration of the block. A LocalCluster of
    N single-threaded worker processes for local:N (closed afterwards); a running cluster is
    only disconnected from. Unreachable addresses fail within CONNECT_TIMEOUT_SECONDS."""
    kind, value = parse_scheduler(scheduler)
    require_dask()
    import dask  # dask: an optional extra (require_dask says so)
    from distributed import Client, LocalCluster  # dask

    # Quiet: the progress bar and our one-line errors are the user's view of the cluster.
    # A local cluster's workers: without the Nanny's MALLOC_TRIM_THRESHOLD_=65536 (glibc then
    # hands freed memory back to the OS at every turn; a suite's training jobs, which allocate
    # and free small tensors each step, ran 1.45x slower with it: 5.4-6.0 s against 3.6-4.0 s,
    # BENCHMARKS.md "Suites on a Dask cluster") and without the statistical profiler (~5%).
    environ = {key: value for key, value in dask.config.get("distributed.nanny.pre-spawn-environ", {}).items()
               if key != "MALLOC_TRIM_THRESHOLD_"}
    with dask.config.set({"distributed.comm.timeouts.connect": f"{CONNECT_TIMEOUT_SECONDS}s",
                          "distributed.admin.system-monitor.gil.enabled": False,
                          "distributed.worker.profile.enabled": False,
                          "distributed.nanny.pre-spawn-environ": environ}):
        if kind == "local":
            # One thread per worker: Mitsuba's LLVM backend already uses every core it is given.
            with LocalCluster(n_workers=value, threads_per_worker=1, processes=True, dashboard_address=":0",
                              silence_logs=50) as cluster, Client(cluster) as client:
                # N workers share this machine's cores instead of each taking all of them.
                client.run(set_render_threads, max(1, (os.cpu_count() or 1) // value))
                yield client
            return
        try:
            client = Client(value, timeout=CONNECT_TIMEOUT_SECONDS)
        except (OSError, TimeoutError) as error:
            reason = (str(error).splitlines() or [type(error).__name__])[0]
            raise InputError(f"cannot reach the dask scheduler at {value} within {CONNECT_TIMEOUT_SECONDS:g} s "
                             f"({reason})") from None
        with client:
            yield client


def set_render_threads(count: int) -> int:
    """Run on a worker: Dr.Jit's (and so Mitsuba's) render threads in this process."""
    import drjit  # drjit: only on a worker that renders

    drjit.set_thread_count(count)
    return drjit.thread_count()


# --- on the workers -----------------------------------------------------------------------------

_SCENES = {}  # per worker process: (out, recipe hash) -> (mi, scene), loaded once
_LOCK = threading.Lock()  # one load or render at a time per process (workers may run several threads)


def render_task(out: str, the_plan, recipe: str, split: str, index: int) -> float:
    """Render and write one view unless it is already complete. Returns render seconds (0 if skipped)."""
    out = Path(out)
    stem = the_plan.stems[split][index]
    if view_complete(out, stem):  # a retried or repeated task: the files are there, bytes the same
        return 0.0
    with _LOCK:
        if (str(out), recipe) not in _SCENES:
            _SCENES.clear()  # one dataset per worker process at a time
            _SCENES[(str(out), recipe)] = load_mitsuba_scene(out, the_plan)
        mi, scene = _SCENES[(str(out), recipe)]
        images, seconds = render_one(mi, scene, out, the_plan, split, index)
    write_view(out, stem, images)
    return seconds


def _the_plan(the_plan):
    return the_plan


# --- on the client ------------------------------------------------------------------------------


def render_on_cluster(client, out, the_plan, todo, bar) -> float:
    """Submit one task per (split, index) in `todo`, advance `bar` as each finishes.
    Returns the render seconds summed over the workers."""
    from distributed import as_completed  # dask: an optional extra

    recipe = recipe_hash(the_plan.recipe())
    # The plan as a task of its own rather than scattered data: the scheduler keeps it (pickled
    # once) and recomputes it if every worker that held it is lost.
    plan_future = client.submit(_the_plan, the_plan, key=f"nerfgauge-plan-{recipe[:12]}", pure=False)
    futures = {client.submit(render_task, str(out), plan_future, recipe, split, index, retries=RETRIES,
                             key=f"nerfgauge-view-{recipe[:12]}-{split}-{index}", pure=False): (split, index)
               for split, index in todo}
    render_seconds = 0.0
    try:
        for future in as_completed(futures):
            if future.status != "finished":
                split, index = futures[future]
                try:
                    future.result()
                except Exception as error:  # the task's own exception, or KilledWorker
                    reason = (str(error).splitlines() or [type(error).__name__])[0]
                    raise InputError(f"view {the_plan.stems[split][index]} failed on the dask cluster after its "
                                     f"retries: {type(error).__name__}: {reason}") from None
            render_seconds += future.result()
            bar.update(1)
    finally:
        for future in futures:
            future.release()
        plan_future.release()
    return render_seconds


def wait_for_workers(client, count: int, timeout: float = 60.0) -> None:
    """Block until `count` workers are connected (tests and benches start clusters)."""
    deadline = time.monotonic() + timeout
    while len(client.scheduler_info()["workers"]) < count:
        if time.monotonic() > deadline:
            raise InputError(f"fewer than {count} dask workers joined within {timeout:g} s")
        time.sleep(0.1)
