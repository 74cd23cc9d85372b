"""A suite run's jobs, here or on a dask.distributed cluster: `suite run --scheduler ADDRESS`.

A job is one (method, dataset, seed): the method (orchestrate.suite.methods, through the
method interface: ours, a baseline, another tool's spec, a user's class) trains with that
seed into its run folder and renders the scoring split into its renders folder; our NeRF's
mesh is scored too where the suite asks (`method_job`). A scoring job scores one run's
renders under the suite's [scoring] (orchestrate.suite.definition.score_renders); the
results and the leaderboard are assembled on the client once every job is done.

A method that fails (an exception from its train or render: a command that exits non-zero,
runs past twice its budget or writes no renders, MethodFailed, or a user's class raising)
fails its job only: the job returns {"failed": reason} (and the traceback goes into
RUN/failure.txt), its renders folder is removed, no record is written (the next run tries
it again), and the suite goes on; the method's row on the leaderboard says why.

Where jobs run: `scheduler=None` runs them one after another in this process;
`local:N` starts a LocalCluster of N single-threaded worker processes; `tcp://HOST:PORT`
uses a running scheduler (generate.distributed.dask_client: the same addresses as
`generate --scheduler`). Attaching SLURM or Kubernetes needs no launcher of ours: start the
cluster with dask-jobqueue (`SLURMCluster(...).scale(jobs=N)`) or the Dask Kubernetes
operator (`KubeCluster(...)`), and pass its scheduler address (`cluster.scheduler_address`)
as --scheduler; workers need nerfgauge installed, the suite folder at the same path (a
shared filesystem), and whatever the methods need (a spec's environment, a user's module
on their path). Each job is a dask task named by the job's key (`nerfgauge-job-...`),
retried RETRIES times if it raises; a lost worker's task is rescheduled by the scheduler.

Resumable job by job: a finished method job writes OUT/jobs/<method>/[seed-<s>/]<id>.json
(its result and its `recipe`: the method entry with the sha256 of its spec or module file,
the length it was given, the seed, the dataset's manifest sha256, the split, the geometry
settings, nerfgauge's version and a hash of the training and baseline code) after its
files, and removes it before it starts; a job whose record matches and whose renders are
there is skipped. An interrupted suite run therefore redoes only the jobs that had not
finished. Scoring is made again on every run.

Same numbers as a local run: a job's result depends only on its inputs. Training is
step-counted (a suite's [train] needs `steps`; a time budget, where a suite gives one,
decides by the clock), seeded by the job's seed, and runs with the same thread count
wherever it runs (`suite run --threads`, else the [train] `threads`, TrainConfig's default
2, except that `local:N` shares this machine's cores: orchestrate.suite.run.training_threads);
torch on CPU with a fixed thread count repeats its results (tests/test_suite_seeds.py
compares the per-run metrics of a local and a 2-worker run). Another thread count splits
some float sums differently: a 600-step run with 1 and with 2 threads gave the same val
PSNR and fp16 node values apart by at most 0.0078, so compare a local:N run with a local
run at its --threads. Scoring jobs run at that thread count too, here and on a cluster:
LPIPS's float32 convolutions sum in an order that depends on it (measured: 8.0778154e-3
against 8.0778152e-3 for the same renders at two counts). What may differ: wall-clock
figures (train_seconds, steps_per_second, ms_per_frame, evaluate_seconds), and on a GPU
worker, CUDA kernels are not bitwise repeatable.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import time
import traceback
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from nerfgauge.core import owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, write_bytes_atomic, write_json
from nerfgauge import nerf as nerf_package
from nerfgauge.core.folders import read_marker, recipe_hash, remove_owned
from nerfgauge.orchestrate.suite.definition import job_result
from nerfgauge import methods as methods_package
from nerfgauge.methods.builtin import NeRF
from nerfgauge.eval.geometry import score_geometry, summary
from nerfgauge.generate.distributed import dask_client

RETRIES = 2
JOBS = "jobs"  # OUT/jobs/<key>.json: a finished job's record
PREDICTIONS = "predictions"  # OUT/predictions/<method>/[seed-<s>/]<id>/: a job's renders
FAILURE = "failure.txt"  # RUN/failure.txt: why a method failed, its traceback


def job_record_path(out, key: str) -> Path:
    return Path(out) / JOBS / f"{key}.json"


def finished(out, key: str, recipe: dict, outputs) -> dict | None:
    """The recorded result of job `key` when it finished with this recipe and its outputs
    (paths) are all there; None otherwise."""
    path = job_record_path(out, key)
    if not path.is_file():
        return None
    record = read_json(path, finite=True)  # a record is data: malformed is one line (orchestrate.suite.job_result)
    if record.get("recipe") != recipe_hash(recipe) or not all(Path(p).exists() for p in outputs):
        return None
    return job_result(record, recipe, path)


def job_name(method: str, entry_id: str, seed) -> str:
    """A method job's key, and its record's path under OUT/jobs/: <method>/[seed-<s>/]<id>."""
    return f"{method}/" + ("" if seed is None else f"seed-{seed}/") + entry_id


def method_job(out: str, job_key: str, entry, train: dict, dataset: str, manifest_sha256: str, run_dir: str,
               renders: str, seed, split: str, geometry: dict | None, threads: int | None = None,
               points_manifest_sha256: str | None = None) -> dict:
    """Train `entry`'s method (orchestrate.suite.methods.MethodEntry) on `dataset` with
    `seed` (None: a method that does not train, run once) into run_dir, render `split`
    into `renders`, score our NeRF's mesh (geometry settings, or None). An arm that states
    points trains on the entry's copy with them (orchestrate.suite.points): `dataset` is
    the copy, points_manifest_sha256 its manifest's hash (in the recipe). Returns the
    record's result (definition.JOB_RESULT) with "resumed", or {"failed": reason} when the
    method failed. Skipped (resumed) when finished with the same recipe."""
    import torch  # torch: only where a job runs

    out, run_dir, renders = Path(out), Path(run_dir), Path(renders)
    try:
        method = entry.resolve()  # here, on the worker: a spec's or a module's file as it is there
        request = entry.request(method, train, dataset=dataset, run=run_dir, seed=0 if seed is None else seed,
                                threads=threads, overwrite=True)
    except InputError as error:
        return {"failed": _failure(error, run_dir, renders, out), "resumed": False}
    geometry = geometry if isinstance(method, NeRF) else None  # a mesh from our fields only
    recipe = {"kind": "method", "method": entry.identity(), "seed": seed, "steps": request.steps,
              "budget_seconds": request.budget_seconds, "manifest_sha256": manifest_sha256, "split": split,
              "geometry": geometry, "renders": renders.relative_to(out).as_posix(), "version": _version(),
              **({"points_manifest_sha256": points_manifest_sha256} if points_manifest_sha256 else {})}
    done = finished(out, job_key, recipe, [renders])
    if done is not None:
        return {**done, "resumed": True}
    owned.remove_file(job_record_path(out, job_key))
    # training may set torch's thread count for the whole process; a job run in the
    # client's process (no scheduler) puts it back, so what follows runs as after a cluster's jobs
    client_threads = torch.get_num_threads()
    try:
        trained = method.train(request)
        rendered = method.render(run_dir, Path(dataset), split, renders, overwrite=True)
    except Exception as error:  # noqa: BLE001 - the method's failure is its job's, not the suite's
        return {"failed": _failure(error, run_dir, renders, out), "resumed": False}
    finally:
        torch.set_num_threads(client_threads)
    where = Path(rendered.out).resolve()
    wrong = (f"its renders landed in {where}, outside {renders}" if not where.is_relative_to(renders.resolve())
             else f"it wrote no renders under {where}" if rendered.frames < 1 or not where.is_dir() else None)
    if wrong is not None:
        return {"failed": _failure(InputError(f"method {method.name}: {wrong}"), run_dir, renders, out),
                "resumed": False}
    result = {"method": entry.name, "seed": seed, "train_seconds": trained.seconds, "steps": trained.steps,
              "steps_per_second": trained.steps_per_second, "cpu_seconds": trained.cpu_seconds,
              "peak_memory_bytes": trained.peak_memory_bytes, "model_bytes": trained.model_bytes,
              "budget_seconds": request.budget_seconds, "threads": trained.extra.get("threads", threads),
              "geometry": _geometry(dataset, str(run_dir), geometry),
              "renders": where.relative_to(out.resolve()).as_posix(), "pred_format": rendered.pred_format,
              "frames": rendered.frames, "render_seconds": rendered.seconds}
    result = {name: (None if isinstance(value, float) and not math.isfinite(value) else value)
              for name, value in result.items()}
    owned.make_folder(job_record_path(out, job_key).parent)
    write_json(job_record_path(out, job_key), {"recipe": recipe_hash(recipe), "result": result})
    return {**result, "resumed": False}


def _failure(error: BaseException, run_dir: Path, renders: Path, out: Path) -> str:
    """One line saying why a method failed (MethodFailed's reason; an InputError's line;
    else the error's type and first line). Its traceback goes into RUN/failure.txt; its
    renders folder, if it claimed one, is removed with the folders left empty up to
    OUT/predictions/: nothing of a failed job stays outside its run folder."""
    reason = failure_line(error)
    write_bytes_atomic(owned.make_folder(run_dir) / FAILURE, "".join(
        traceback.format_exception(type(error), error, error.__traceback__)).encode())
    marker = read_marker(renders) if renders.is_dir() and not renders.is_symlink() else None
    if marker is not None:
        remove_owned(renders, marker["kind"])
    folder, stop = renders if renders.is_dir() else renders.parent, out / PREDICTIONS
    while folder != stop and folder.is_relative_to(stop) and folder.is_dir() and not any(folder.iterdir()):
        owned.remove_empty_folder(folder)
        folder = folder.parent
    return reason


def failure_line(error: BaseException) -> str:
    """Why a job failed, in one line: MethodFailed's reason, an InputError's line, else the
    error's type and first line."""
    reason = getattr(error, "reason", None)
    if isinstance(reason, str):
        return reason
    line = (str(error).splitlines() or [""])[0]
    return line if isinstance(error, InputError) else f"{type(error).__name__}: {line}".rstrip(": ")


def _version() -> str:
    """nerfgauge's version and the sha256 of the training, rendering and method code (the
    nerf package's and the methods package's sources): a job finished by other code is
    redone (the package version alone does not change between commits)."""
    try:
        package = version("nerfgauge")
    except PackageNotFoundError:
        package = "unknown"
    digest = hashlib.sha256()
    nerf_sources = sorted(Path(nerf_package.__file__).parent.glob("*.py"))
    method_sources = sorted(Path(methods_package.__file__).parent.glob("*.py"))
    for source in [*nerf_sources, *method_sources]:
        digest.update(source.name.encode() + b"\0" + source.read_bytes())
    return f"{package}+{digest.hexdigest()[:16]}"


def _geometry(dataset: str, run_dir: str, settings: dict | None):
    """Our NeRF's mesh scored against the exact meshes (eval.geometry.summary's numbers);
    {"n/a": reason} when the field has no surface; None when the protocol asks for none."""
    if not settings:
        return None
    from nerfgauge.nerf.mesh import NoSurface, mesh_from_run, ply_bytes  # torch

    try:
        mesh = mesh_from_run(run_dir, settings["resolution"])
    except NoSurface as reason:
        return {"n/a": str(reason)}
    write_bytes_atomic(Path(run_dir) / "mesh.ply", ply_bytes(mesh.vertices, mesh.faces))
    document, _ = score_geometry(dataset, Path(run_dir) / "mesh.ply", samples=settings["samples"])
    return summary(document)


def run_jobs(jobs: list, scheduler: str | None, log=print) -> dict:
    """jobs: [(key, function, kwargs)]. Runs them (here, in order, when scheduler is None;
    else as dask tasks) and returns {key: result}. A job that fails after its retries is
    one InputError line naming it."""
    with job_runner(scheduler, log) as run:
        return run(jobs)


@contextlib.contextmanager
def job_runner(scheduler: str | None, log=print):
    """A function that runs a list of jobs as run_jobs does, on one cluster client for the
    block (a suite run's method jobs, then its scoring jobs, share the cluster)."""
    if scheduler is None:
        yield lambda jobs: _run_here(jobs, log)
        return
    with dask_client(scheduler) as client:
        yield lambda jobs: _run_on(client, scheduler, jobs, log)


def _said(result: dict) -> str:
    if "failed" in result:
        return f"failed: {result['failed']}"
    return "finished earlier, skipped" if result.get("resumed") else ""


def _run_here(jobs: list, log) -> dict:
    results = {}
    for index, (key, function, kwargs) in enumerate(jobs, 1):
        start = time.perf_counter()
        results[key] = function(**kwargs)
        log(f"    job {index}/{len(jobs)} {key}: {_said(results[key]) or f'{time.perf_counter() - start:.1f} s'}")
    return results


def _run_on(client, scheduler: str, jobs: list, log) -> dict:
    from distributed import as_completed  # dask: an optional extra (dask_client checked it)

    results = {}
    futures = {client.submit(function, retries=RETRIES, key=f"nerfgauge-job-{key}", pure=False, **kwargs): key
               for key, function, kwargs in jobs}
    log(f"    {len(futures)} jobs on {scheduler}")
    try:
        for done, future in enumerate(as_completed(futures), 1):
            key = futures[future]
            try:
                results[key] = future.result()
            except Exception as error:  # the job's own exception, or KilledWorker
                reason = (str(error).splitlines() or [type(error).__name__])[0]
                raise InputError(f"suite job {key} failed on the dask cluster after its retries: "
                                 f"{type(error).__name__}: {reason}") from None
            log(f"    job {done}/{len(futures)} {key}: {_said(results[key]) or 'done'}")
    finally:
        for future in futures:
            future.release()
    return results
