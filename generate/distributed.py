"""Rendering the pending views on a dask.distributed cluster: `generate --scheduler ADDRESS`.

    --scheduler tcp://HOST:PORT   a running scheduler (`dask scheduler`, dask-jobqueue on
                                  SLURM, dask-kubernetes, ...); its workers must have
                                  nerfgauge installed and see the output folder at the
                                  same path (a shared filesystem)
    --scheduler local:N           an in-process LocalCluster of N worker processes, listening
                                  on the loopback interface only and without Dask's HTTP
                                  dashboard (`local_cluster`)

Each view is one task, named by the recipe hash and the view, whose function renders the
view with the seed of (seed, split, index) and writes its files through the atomic writers
(core.images: a temporary name, renamed). A task whose view is already complete on disk
writes nothing, so a task retried after a lost worker, or run twice, leaves the same files,
and the dataset equals a single-process run byte for byte. A task that raises is retried
`RETRIES` times (dask `retries=`); a task whose worker dies is rescheduled by the scheduler
(up to its `distributed.scheduler.allowed-failures`, 3 by default). Dask is imported only
here, only with --scheduler (the `dask` extra: pip install 'nerfgauge[dask]').

A running scheduler is asked who it is before the Client connects (`check_scheduler`): the
connection, dask's handshake and the scheduler's `identity` reply must all arrive within
CONNECT_TIMEOUT_SECONDS, and the reply must come from a scheduler. dask's own connect bounds
only the TCP connection: a server that accepts and then says nothing held `Client()` forever,
and one that answers random bytes raised whatever its deserialiser met (a 6 EiB allocation).
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import os
import re
import threading
import time
from pathlib import Path

from nerfgauge.core.errors import InputError, raise_floating_point_warnings
from nerfgauge.core.folders import recipe_hash
from nerfgauge.generate.views import load_mitsuba_scene, render_one, view_complete, write_view

RETRIES = 2  # a task that raises runs up to 3 times
# A remote scheduler must be connected to and answer who it is within this many seconds,
# or the command stops with one line (README: "a scheduler that cannot be reached within 5 s").
CONNECT_TIMEOUT_SECONDS = 5.0
LOOPBACK = "127.0.0.1"  # where a local cluster's scheduler, nannies, workers and HTTP servers listen
HTTP_ROUTES = ("distributed.http.health",)  # all a local cluster's HTTP servers serve (local_cluster)
LOCAL_PREFIX = "local:"
ADDRESS = re.compile(r"^(tcp|tls|ws|wss|ucx)://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})$")
INSTALL_HINT = "pip install 'nerfgauge[dask]' (or dask[distributed])"
# What a local cluster's worker processes get when two or more share this machine's cores, unless
# the user's environment sets it. libgomp's threads (torch's, and numba's OpenMP layer under the
# compiled renderer and the splat rasteriser) spin between parallel regions by default and so take
# the cores from the other workers; PASSIVE puts them to sleep. Measured on 2 cores
# (docs/tutorials/suite-on-dask.md): `suite run smoke --seeds 3 --scheduler local:2` 36.9 and 36.0 s
# by default, 32.2 and 31.8 s with it; the tests' training files on two pytest workers 377 and
# 311 s against 259 and 201 s (tox.ini sets it there).
SHARED_CORES_ENVIRONMENT = {"OMP_WAIT_POLICY": "PASSIVE"}


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


def shared_cores_environment(workers: int, in_process: bool = False, environ=os.environ) -> dict:
    """What each worker process of a local cluster of `workers` is given (set in it before it
    imports torch): SHARED_CORES_ENVIRONMENT's variables that `environ` lacks, when two or more
    worker processes share the cores; else nothing."""
    if workers < 2 or in_process:
        return {}
    return {name: value for name, value in SHARED_CORES_ENVIRONMENT.items() if name not in environ}


@contextlib.contextmanager
def local_cluster(workers: int, **options):
    """A dask LocalCluster of `workers` processes, for the block, that listens on the
    loopback interface only and serves no dashboard. The one way nerfgauge starts a local
    cluster (generate and suite run through `dask_client`, the dask bench); `options` go to
    LocalCluster.

    Dask's defaults exposed the cluster: its dashboard binds every interface when given a
    bare port (":0") and shows anyone who can reach the machine the cluster's identity,
    logs and call stacks. Here the scheduler, nannies and workers listen on 127.0.0.1; the
    Bokeh dashboard is off; the HTTP servers dask starts anyway (scheduler and workers)
    bind 127.0.0.1 on a free port and serve only the health check (no logs, call stacks,
    metrics or cluster info), set before the nannies start their workers (which inherit
    the configuration). Two or more worker processes share the cores: each gets
    SHARED_CORES_ENVIRONMENT where the user's environment does not set it."""
    import dask  # dask: an optional extra (callers checked require_dask)
    from distributed import LocalCluster  # dask

    in_process = options.get("processes") is False  # workers as threads, over dask's in-process comm: no host
    environment = {**shared_cores_environment(workers, in_process), **options.get("env", {})}
    if environment:  # a nanny's option: in-process workers (processes=False) take none
        options["env"] = environment
    with dask.config.set({"distributed.scheduler.http.routes": list(HTTP_ROUTES),
                          "distributed.worker.http.routes": list(HTTP_ROUTES)}), \
            LocalCluster(n_workers=workers, host=None if in_process else LOOPBACK, dashboard_address=None,
                         worker_dashboard_address=None, silence_logs=50,
                         scheduler_kwargs={"dashboard": False, "dashboard_address": f"{LOOPBACK}:0"},
                         **options) as cluster:
        yield cluster


def _reason(error: BaseException) -> str:
    return f"{type(error).__name__}: {(str(error).splitlines() or [''])[0]}".rstrip(": ")


def check_scheduler(address: str, timeout: float | None = None) -> dict:
    """The `identity` of the dask scheduler at `address` (its type, id, workers ...), asked
    over a fresh connection whose connect, handshake and reply all fit in `timeout` seconds
    (default CONNECT_TIMEOUT_SECONDS). InputError, one line, when nothing answers in time,
    when the answer is not dask's protocol, or when it comes from something other than a
    scheduler (a worker's address). Runs on a thread of its own, so a caller inside an
    event loop (Jupyter) can use it."""
    from distributed.comm import connect  # dask: an optional extra (callers checked require_dask)
    from distributed.security import Security  # dask

    timeout = CONNECT_TIMEOUT_SECONDS if timeout is None else float(timeout)

    async def identity():
        comm = await connect(address, timeout=timeout, **Security().get_connection_args("client"))
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    async def bounded():
        return await asyncio.wait_for(identity(), timeout)

    outcome = {}

    def run():
        try:
            outcome["reply"] = asyncio.run(bounded())
        except BaseException as error:  # reported below, on the caller's thread
            outcome["error"] = error

    thread = threading.Thread(target=run, name="nerfgauge-scheduler-probe", daemon=True)
    thread.start()
    thread.join(timeout + 5.0)  # wait_for ends the probe at `timeout`; the margin only guards that promise
    error = outcome.get("error")
    if thread.is_alive() or isinstance(error, asyncio.TimeoutError):
        raise InputError(f"cannot reach the dask scheduler at {address} within {timeout:g} s (it did not answer "
                         f"dask's handshake in time)")
    if isinstance(error, OSError):  # refused, unreachable, DNS: dask retried until the deadline
        raise InputError(f"cannot reach the dask scheduler at {address} within {timeout:g} s ({_reason(error)})")
    if error is not None:  # whatever the bytes made dask's deserialiser do
        raise InputError(f"{address} did not answer as a dask scheduler does ({_reason(error)}); "
                         "is it a dask scheduler's address?")
    reply = outcome.get("reply")
    kind = reply.get("type") if isinstance(reply, dict) else None
    if not isinstance(kind, str) or "Scheduler" not in kind:
        what = f"a dask {kind}" if isinstance(kind, str) else f"a {type(reply).__name__}"
        raise InputError(f"{address} is not a dask scheduler (asked who it is, it answered as {what}); "
                         "give the scheduler's address")
    return reply


def check_reachable(scheduler: str) -> None:
    """Before a command writes anything: `scheduler` well formed (parse_scheduler), and a
    running scheduler's address answering as one within CONNECT_TIMEOUT_SECONDS
    (check_scheduler); dask installed either way. InputError, one line, otherwise."""
    kind, value = parse_scheduler(scheduler)
    require_dask()
    if kind == "address":
        check_scheduler(value)


@contextlib.contextmanager
def dask_client(scheduler: str):
    """A distributed.Client on `scheduler` for the duration of the block. A LocalCluster of
    N single-threaded worker processes for local:N (`local_cluster`: loopback only, no
    dashboard; closed afterwards); a running cluster is checked first (`check_scheduler`:
    within CONNECT_TIMEOUT_SECONDS) and only disconnected from."""
    kind, value = parse_scheduler(scheduler)
    require_dask()
    import dask  # dask: an optional extra (require_dask says so)
    from distributed import Client  # dask

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
            with local_cluster(value, threads_per_worker=1, processes=True) as cluster, Client(cluster) as client:
                # N workers share this machine's cores instead of each taking all of them.
                client.run(set_render_threads, max(1, (os.cpu_count() or 1) // value))
                client.run(raise_floating_point_warnings)  # as in this process (core.errors); ours to set
                yield client
            return
        check_scheduler(value)
        try:
            client = Client(value, timeout=CONNECT_TIMEOUT_SECONDS)
        except (OSError, TimeoutError) as error:
            raise InputError(f"cannot reach the dask scheduler at {value} within {CONNECT_TIMEOUT_SECONDS:g} s "
                             f"({_reason(error)})") from None
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
