"""A suite run's jobs, here or on a dask.distributed cluster: `suite run --scheduler ADDRESS`.

A job is one (dataset, method, seed): for our NeRF, train with that seed, render the
protocol's split and mesh-score the field (`train_job`); for a baseline, write its renders
(`baseline_job`). Scoring (eval.evaluate, fast) and the leaderboard run on the client after
every job is done (orchestrate.suite.evaluate_suite).

Where jobs run: `scheduler=None` runs them one after another in this process;
`local:N` starts a LocalCluster of N single-threaded worker processes; `tcp://HOST:PORT`
uses a running scheduler (generate.distributed.dask_client: the same addresses as
`generate --scheduler`). Attaching SLURM or Kubernetes needs no launcher of ours: start the
cluster with dask-jobqueue (`SLURMCluster(...).scale(jobs=N)`) or the Dask Kubernetes
operator (`KubeCluster(...)`), and pass its scheduler address (`cluster.scheduler_address`)
as --scheduler; workers need nerfgauge installed and the suite folder at the same path
(a shared filesystem). Each job is a dask task named by the job's key (`nerfgauge-job-...`),
retried RETRIES times if it raises; a lost worker's task is rescheduled by the scheduler.

Resumable job by job: a finished job writes OUT/jobs/<key>.json (its result and its
`recipe`: the training settings with the seed, the dataset's manifest sha256, the split,
the geometry settings, nerfgauge's version and a hash of the training and baseline code)
after its files, and removes it before it
starts; a job whose record matches and whose outputs are there is skipped. An
interrupted suite run therefore redoes only the jobs that had not finished.

Same numbers as a local run: a job's result depends only on its inputs. Training is
step-counted (a suite's [train] needs `steps`), seeded by the job's seed, and runs with
the same torch thread count wherever it runs (`suite run --threads`, else the [train]
`threads`, TrainConfig's default 2, except that `local:N` shares this machine's cores:
orchestrate.suite.run.training_threads); torch on CPU with a fixed thread count repeats
its results (tests/test_suite_seeds.py compares the per-run metrics of a local and a
2-worker run). Another thread count splits some float sums differently: a 600-step run
with 1 and with 2 threads gave the same val PSNR and fp16 node values apart by at most
0.0078, so compare a local:N run with a local run at its --threads. What may differ:
wall-clock figures (train_seconds, steps_per_second, ms_per_frame, evaluate_seconds),
the thread count as above, and anything a time budget would decide
(suites have none). On a GPU worker, CUDA kernels are not bitwise repeatable. Scoring runs
in the client with torch's default thread count either way (a local job restores it after
training); LPIPS's float32 convolutions sum in an order that depends on that count, so
LPIPS scored on machines with different core counts may differ in the 9th digit (measured:
8.0778154e-3 against 8.0778152e-3 before the restore, the same renders).
"""

from __future__ import annotations

import hashlib
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from nerfgauge.core import owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, write_bytes_atomic, write_json
from nerfgauge import nerf as nerf_package
from nerfgauge.core.folders import recipe_hash
from nerfgauge.orchestrate.suite.definition import job_result
from nerfgauge.methods import baselines as baselines_module
from nerfgauge.methods.baselines import baseline_folder, write_baseline
from nerfgauge.eval.geometry import score_geometry, summary
from nerfgauge.generate.distributed import dask_client

RETRIES = 2
JOBS = "jobs"  # OUT/jobs/<key>.json: a finished job's record


def job_record_path(out, key: str) -> Path:
    owned.make_folder(Path(out) / JOBS)
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


def train_job(out: str, job_key: str, train: dict, dataset: str, manifest_sha256: str, run_dir: str, renders: str,
              seed: int, split: str, geometry: dict | None, threads: int | None = None) -> dict:
    """Train our NeRF with `seed`, render `split` into `renders`, score its mesh (geometry
    settings, or None). Returns the cost row: {"train_seconds", "model_bytes", "steps",
    "steps_per_second", "geometry", "seed", "threads", "resumed"}. Skipped (resumed) when finished.
    threads: torch threads for training (None: the [train] table's); like a run's, not part
    of the recipe (nerf.train.NOT_RECIPE), though the float sums it splits may round apart."""
    recipe = {"kind": "train", "train": train, "seed": seed, "manifest_sha256": manifest_sha256, "split": split,
              "geometry": geometry, "version": _version()}
    outputs = [Path(run_dir) / "model.pt", Path(renders) / "timing.json"]
    done = finished(out, job_key, recipe, outputs)
    if done is not None:
        return {**done, "resumed": True}
    owned.remove_file(job_record_path(out, job_key))
    from nerfgauge.nerf.config import TrainConfig  # torch: only where a job runs
    from nerfgauge.nerf.render_views import render_split  # torch
    from nerfgauge.nerf.train import train as train_run  # torch

    import torch  # torch: only where a job runs

    config = TrainConfig(dataset=dataset, seed=seed, **{**train, **({} if threads is None else {"threads": threads})})
    # training sets torch's thread count for the whole process; a job run in the client's
    # process (no scheduler) puts it back, so the scoring that follows (LPIPS's convolutions
    # sum in a thread-count-dependent order) runs as it does after a cluster's jobs
    client_threads = torch.get_num_threads()
    try:
        summary = train_run(config, run_dir, overwrite=True, progress=False)
        render_split(run_dir, split, renders, overwrite=True, progress=False)
        result = {"train_seconds": summary["seconds"], "model_bytes": summary["model_bytes"],
                  "steps": summary["steps"], "steps_per_second": summary["steps"] / max(summary["seconds"], 1e-9),
                  "seed": seed, "threads": config.threads, "geometry": _geometry(dataset, run_dir, geometry)}
    finally:
        torch.set_num_threads(client_threads)
    write_json(job_record_path(out, job_key), {"recipe": recipe_hash(recipe), "result": result})
    return {**result, "resumed": False}


def baseline_job(out: str, job_key: str, dataset: str, manifest_sha256: str, method: str, target: str,
                 split: str) -> dict:
    """A baseline's renders of `split` into `target` (deterministic: no seed). Resumable as train_job."""
    recipe = {"kind": "baseline", "method": method, "manifest_sha256": manifest_sha256, "split": split,
              "version": _version()}
    done = finished(out, job_key, recipe, [Path(target)])
    if done is not None:
        return {**done, "resumed": True}
    owned.remove_file(job_record_path(out, job_key))
    with baseline_folder(dataset, method, target, split, overwrite=True):
        write_baseline(dataset, method, target, split)
    result = {"method": method}
    write_json(job_record_path(out, job_key), {"recipe": recipe_hash(recipe), "result": result})
    return {**result, "resumed": False}


def _version() -> str:
    """nerfgauge's version and the sha256 of the training, rendering and baseline code (the
    nerf package's and methods/baselines.py's sources): a job finished by other code is redone
    (the package version alone does not change between commits)."""
    try:
        package = version("nerfgauge")
    except PackageNotFoundError:
        package = "unknown"
    digest = hashlib.sha256()
    nerf_sources = sorted(Path(nerf_package.__file__).parent.glob("*.py"))
    for source in [*nerf_sources, Path(baselines_module.__file__)]:
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
    results = {}
    if scheduler is None:
        for index, (key, function, kwargs) in enumerate(jobs, 1):
            start = time.perf_counter()
            results[key] = function(**kwargs)
            log(f"    job {index}/{len(jobs)} {key}: "
                + ("finished earlier, skipped" if results[key].get("resumed") else f"{time.perf_counter() - start:.1f} s"))
        return results
    with dask_client(scheduler) as client:
        from distributed import as_completed  # dask: an optional extra (dask_client checked it)

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
                log(f"    job {done}/{len(futures)} {key}: "
                    + ("finished earlier, skipped" if results[key].get("resumed") else "done"))
        finally:
            for future in futures:
                future.release()
    return results
