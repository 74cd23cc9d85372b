"""`nerfgauge suite run SUITE --out DIR`: our compact NeRF and the baselines through a whole
suite, each stage through its public function (generate, nerf train and render, eval
baselines and evaluate), then the leaderboard.

    DIR/                          the suite folder (orchestrate.suite): datasets, suite manifest
    DIR/runs/<id>/                our NeRF's training run on dataset <id>
                                  (--seeds: DIR/runs/seed-<s>/<id>/, one per training seed)
    DIR/predictions/<method>/<id>/ renders of every method (ours: renders folder; baselines;
                                  --seeds: ours in predictions/compact-nerf/seed-<s>/<id>/)
    DIR/jobs/<job>.json           a finished job's record (orchestrate.suite.jobs: resuming)
    DIR/predictions/<method>/suite.json  which suite they were made for
    DIR/results/<method>/         `suite evaluate` of those predictions (orchestrate.suite)
    DIR/leaderboard.{md,html,json}, DIR/report/<id>/report.html (orchestrate.suite.report)

Datasets are resumed (orchestrate.suite.generate_suite); so are the (dataset, method, seed) jobs
(training, renders, baselines: orchestrate.suite.jobs), each skipped when its record says it
finished with the same settings, dataset and nerfgauge version; scoring and the leaderboard
are made again on every run. --scheduler runs generation and the jobs on a dask cluster.
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path

from nerfgauge.core import arguments
from nerfgauge.core.files import write_json
from nerfgauge.orchestrate.suite.definition import (OURS, SUITE_FILE, Suite, dataset_dir, evaluate_suite, generate_suite,
                                         seed_folder)
from nerfgauge.core.dataset import open_dataset
from nerfgauge.generate.distributed import check_reachable, parse_scheduler
from nerfgauge.orchestrate.suite.jobs import baseline_job, run_jobs, train_job
from nerfgauge.orchestrate.suite.report import write_leaderboard

def methods_for(suite: Suite, layout: str) -> list[str]:
    """The suite's baselines that apply to a dataset of `layout`."""
    return [m for m in suite.protocol.get("baselines", []) if not m.startswith("lightfield") or layout == "lightfield"]


def skipped_on_folder(suite: Suite, entry) -> dict:
    """{method: why it is skipped} on a folder entry (ground truth nerfgauge did not write):
    every method `suite run` runs needs something such a folder lacks."""
    reasons = {OURS: "our NeRF's runs are bound to a nerfgauge dataset's manifest (a folder entry has none); "
                     "score its renders with nerfgauge suite evaluate"}
    for method in suite.protocol.get("baselines", []):
        reasons[method] = ("needs a light-field camera grid (scene.json camera.lightfield)" if method.startswith("lightfield")
                           else "needs the scene's bounds (scene.json), which a folder entry lacks")
    return reasons


def training_threads(suite: Suite, scheduler: str | None, threads: int | None) -> tuple[int, str]:
    """Torch threads for each training job, and why: as given; else the suite's [train]
    threads (TrainConfig's default when it names none), except on local:N where N workers
    times that would exceed this machine's cores: then cores // N (at least 1). Oversubscribed
    torch threads spin against each other: on 2 cores, local:2 with 2 threads a job took 7.2x
    as long for the standard suite's primitives job (450 s against 63 s, BENCHMARKS.md)."""
    if threads is not None:
        return arguments.THREADS.check(threads, "--threads"), "--threads"
    from nerfgauge.nerf.config import TrainConfig  # the default lives with the config
    wanted = int(suite.train.get("threads", TrainConfig.threads))
    source = "the suite's [train] threads" if "threads" in suite.train else "the training default"
    if scheduler is None:
        return wanted, source
    kind, workers = parse_scheduler(scheduler)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if kind == "local" and workers * wanted > cores:
        share = max(1, cores // workers)
        return share, (f"{workers} local workers share {cores} cores; {source} ({wanted}) would oversubscribe "
                       f"them. Per-run metrics equal a local run's with --threads {share}")
    return wanted, source


def run_suite(suite: Suite, out, *, overwrite: bool = False, progress: bool = False, log=print,
              seeds=None, scheduler: str | None = None, threads: int | None = None) -> dict:
    """Generate, train, render, baselines, evaluate, leaderboard. Returns the leaderboard.

    seeds: None trains our NeRF once per dataset with the dataset entry's seed (runs/<id>/,
    predictions/<method>/<id>/); a list of training seeds trains it once per seed, into
    runs/seed-<s>/<id>/ and predictions/compact-nerf/seed-<s>/<id>/, scored per seed and
    aggregated (orchestrate.suite.evaluate_suite, results/<method>/<id>/aggregate.json). The
    baselines are deterministic functions of the dataset: run once, paired with every seed.
    scheduler: None runs the jobs here; local:N or tcp://HOST:PORT runs generation's views
    and every (dataset, method, seed) job on a dask cluster (orchestrate.suite.jobs).
    threads: torch threads per training job; None: `training_threads` (the suite's, or a
    share of this machine's cores on local:N)."""
    out = Path(out)
    if scheduler is not None:
        check_reachable(scheduler)  # a malformed or unreachable address is one line before anything is written
    seeds = None if seeds is None else tuple(arguments.check_seeds(seeds))
    threads, why = training_threads(suite, scheduler, threads)
    start = time.perf_counter()
    manifest = generate_suite(suite, out, overwrite=overwrite, progress=progress, log=log, scheduler=scheduler)
    split = suite.protocol["split"]
    predictions = out / "predictions"
    baseline_roots, skipped, jobs, owners = {}, {}, [], {}
    for index, entry in enumerate(suite.scenes, 1):
        data = dataset_dir(out, entry)
        if entry.foreign:
            for method, reason in skipped_on_folder(suite, entry).items():
                skipped.setdefault(method, {})[entry.id] = reason
                log(f"[{index}/{len(suite.scenes)}] {entry.id}: {method} skipped: {reason}")
            continue
        manifest_sha256 = manifest["datasets"][entry.id]["manifest_sha256"]
        for seed in (entry.seed,) if seeds is None else seeds:
            where = entry.id if seeds is None else f"{seed_folder(seed)}/{entry.id}"
            key = f"train-{entry.id}" + ("" if seeds is None else f"-{seed_folder(seed)}")
            jobs.append((key, train_job, dict(out=str(out), job_key=key, train=suite.train, threads=threads,
                                              dataset=str(data),
                                              manifest_sha256=manifest_sha256, run_dir=str(out / "runs" / where),
                                              renders=str(predictions / OURS / where), seed=seed, split=split,
                                              geometry=suite.protocol.get("geometry"))))
            owners[key] = (entry.id, None if seeds is None else seed)
        layout = open_dataset(data).scene.get("camera", {}).get("layout")
        for method in methods_for(suite, layout):
            key = f"baseline-{method}-{entry.id}"
            jobs.append((key, baseline_job, dict(out=str(out), job_key=key, dataset=str(data),
                                                 manifest_sha256=manifest_sha256, method=method,
                                                 target=str(predictions / method / entry.id), split=split)))
            baseline_roots.setdefault(method, []).append(entry.id)
    log(f"{len(jobs)} jobs: {sum(k.startswith('train-') for k, _, _ in jobs)} trainings "
        f"({suite.train.get('model', 'compact')}, {suite.train['steps']} steps"
        + (f", seeds {', '.join(map(str, seeds))}" if seeds is not None else "") + f"), "
        f"{sum(k.startswith('baseline-') for k, _, _ in jobs)} baselines"
        + ("" if scheduler is None else f", on {scheduler}") + f"; {threads} torch thread(s) a training ({why})")
    clock = time.perf_counter()
    done = run_jobs(jobs, scheduler, log)
    log(f"jobs: {time.perf_counter() - clock:.1f} s")
    extras = {}
    for key, (entry_id, seed) in owners.items():
        row = {name: done[key][name] for name in ("train_seconds", "model_bytes", "steps", "steps_per_second",
                                                  "geometry", "seed")}
        if seed is None:
            extras[entry_id] = row
        else:
            extras.setdefault(entry_id, {})[seed] = row
    methods = {OURS: extras} if extras else {}
    for method, ids in baseline_roots.items():
        methods[method] = {entry_id: {"train_seconds": 0.0, "model_bytes": None} for entry_id in ids}
    for method, method_extras in methods.items():
        root = predictions / method
        write_json(root / SUITE_FILE, suite.identity())
        method_seeds = seeds if method == OURS else None
        ids = set(method_extras)
        if ids != {entry.id for entry in suite.scenes}:
            log(f"{method}: applies to {len(ids)} of {len(suite.scenes)} datasets; scored on those only")
            evaluate_subset(suite, out, method, root, ids, method_extras, log, skipped.get(method), method_seeds)
        else:
            evaluate_suite(suite, out, method, root, extras=method_extras, log=log, seeds=method_seeds)
    board = write_leaderboard(suite, out, log=log)
    log(f"suite {suite.name} v{suite.version}: {time.perf_counter() - start:.1f} s in all")
    return board


def evaluate_subset(suite: Suite, out, method: str, root, ids: set, extras: dict, log, skipped=None,
                    seeds=None) -> dict:
    """evaluate_suite on the suite's entries in `ids` (a baseline that applies to some
    layouts only); the leaderboard shows the others as not applicable."""
    subset = dataclasses.replace(suite, scenes=tuple(e for e in suite.scenes if e.id in ids))
    return evaluate_suite(suite, out, method, root, extras=extras, log=log, entries=subset.scenes, skipped=skipped,
                          seeds=seeds)
