"""`nerfgauge suite run SUITE --out DIR`: the suite's methods (or those --methods names)
through a whole suite, each stage through its public function (generate; every method
through the method interface; evaluate), then the leaderboard.

    DIR/                          the suite folder (orchestrate.suite): datasets, suite manifest
    DIR/points/<spec>/<id>/       dataset <id> with other initial points, for the arms that state
                                  them (`points = "sfm"`: orchestrate.suite.points)
    DIR/runs/<method>/<id>/       a method's run on dataset <id> (its training: ours, another
                                  tool's outputs and logs; failure.txt when it failed)
                                  (--seeds: DIR/runs/<method>/seed-<s>/<id>/ for a learned method)
    DIR/predictions/<method>/<id>/ its renders of the scoring split (--seeds: .../seed-<s>/<id>/)
    DIR/jobs/<method>/[seed-<s>/]<id>.json  a finished job's record (orchestrate.suite.jobs: resuming)
    DIR/predictions/<method>/suite.json  which suite they were made for
    DIR/results/<method>/         its scores (orchestrate.suite.definition.write_result)
    DIR/leaderboard.{md,html,json}, DIR/report/<id>/report.html (orchestrate.suite.report)

Datasets are resumed (orchestrate.suite.generate_suite); so are the (method, dataset, seed)
jobs (orchestrate.suite.jobs), each skipped when its record says it finished with the same
method, settings, length, dataset and nerfgauge version. A method that needs what a dataset
lacks (methods.interface.missing_needs: our NeRF a nerfgauge dataset, the light-field
baselines a camera grid) is skipped there with the reason; one that fails gets its row with
the reason and the rest of the suite goes on. Scoring runs as jobs too, on the same runner,
and is made again on every run, as is the leaderboard. --scheduler runs generation and
every job on a dask cluster.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from nerfgauge.core import arguments, owned
from nerfgauge.core.dataset import open_dataset
from nerfgauge.core.files import write_json
from nerfgauge.core.folders import folder_lock
from nerfgauge.generate.distributed import check_reachable, parse_scheduler
from nerfgauge.methods.interface import missing_needs
from nerfgauge.orchestrate.suite.definition import (RESULT_FILE, SUITE_FILE, Suite, dataset_dir, generate_suite,
                                                    identity_key, score_renders, scoring_tasks, seed_folder,
                                                    write_result)
from nerfgauge.orchestrate.suite.jobs import PREDICTIONS, job_name, job_runner, method_job
from nerfgauge.orchestrate.suite.methods import select
from nerfgauge.orchestrate.suite.points import check_points_available, make_points_dataset, needs_copy, points_folder
from nerfgauge.orchestrate.suite.report import write_leaderboard

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
              seeds=None, scheduler: str | None = None, threads: int | None = None, methods=None) -> dict:
    """Generate, run every (method, dataset, seed) job, score, leaderboard. Returns the leaderboard.

    methods: None runs the suite's [[methods]]; names (a list, or "A,B,..."), each one of
    the suite's methods (by name or method, with its settings) or anything the method
    registry resolves, run instead (orchestrate.suite.methods.select).
    seeds: None trains each learned method once per dataset with the dataset entry's seed
    (runs/<method>/<id>/, predictions/<method>/<id>/); a list of training seeds trains it
    once per seed, into runs/<method>/seed-<s>/<id>/ and predictions/<method>/seed-<s>/<id>/,
    scored per seed and aggregated (results/<method>/<id>/aggregate.json). Methods that do
    not train (the baselines) are deterministic functions of the dataset: run once, paired
    with every seed. scheduler: None runs the jobs here; local:N or tcp://HOST:PORT runs
    generation's views and every job on a dask cluster (orchestrate.suite.jobs).
    threads: threads per job; None: `training_threads` (the suite's, or a share of this
    machine's cores on local:N)."""
    out = Path(out)
    if scheduler is not None:
        check_reachable(scheduler)  # a malformed or unreachable address is one line before anything is written
    seeds = None if seeds is None else tuple(arguments.check_seeds(seeds))
    entries = suite.methods if methods is None else select(suite.methods, methods, suite.train)
    threads, why = training_threads(suite, scheduler, threads)
    resolved = {entry.name: entry.resolve() for entry in entries}
    check_points_available(entries)  # sfm points need pycolmap: one line before anything is written
    start = time.perf_counter()
    manifest = generate_suite(suite, out, overwrite=overwrite, progress=progress, log=log, scheduler=scheduler)
    with job_runner(scheduler, log) as run_on:
        copies = points_datasets(suite, out, entries, run_on, log)
        jobs, owners, skipped, refused = method_jobs(suite, out, entries, resolved, manifest, seeds, threads, log,
                                                     copies)
        log(f"{len(jobs)} jobs: " + ", ".join(f"{e.name} ({_length(resolved[e.name], e, suite.train)}"
                                              + (f", {e.points} points" if e.points else "") + ")" for e in entries)
            + (f"; seeds {', '.join(map(str, seeds))}" if seeds is not None else "")
            + ("" if scheduler is None else f"; on {scheduler}") + f"; {threads} thread(s) a job ({why})")
        clock = time.perf_counter()
        renders, extras, failed = collect(out, owners, run_on(jobs))
        for name, reasons in refused.items():  # arms whose points could not be made on a dataset
            failed.setdefault(name, {}).update(reasons)
        log(f"jobs: {time.perf_counter() - clock:.1f} s")
        with folder_lock(out):
            tasks = {entry.name: scoring_tasks(suite, out, entry.name, renders.get(entry.name, {}), threads,
                                               failures=True, datasets=arm_datasets(entry, copies))
                     for entry in entries}
            for entry in entries:
                owned.remove_file(out / "results" / entry.name / RESULT_FILE)  # no stale result beside new metrics
                if (out / PREDICTIONS / entry.name).is_dir():
                    write_json(out / PREDICTIONS / entry.name / SUITE_FILE, suite.identity())
            scored = run_on([(task["key"], score_renders, task["kwargs"]) for method_tasks in tasks.values()
                             for task in method_tasks])
            for entry in entries:
                write_result(suite, out, manifest, entry.name, tasks[entry.name],
                             [scored[task["key"]] for task in tasks[entry.name]],
                             seeds=seeds if resolved[entry.name].learned else None, extras=extras.get(entry.name),
                             skipped=skipped.get(entry.name), failed=failed.get(entry.name),
                             pred_root=str(out / PREDICTIONS / entry.name))
    for name, reasons in failed.items():
        log(f"{name} failed on {len(reasons)} dataset(s): {next(iter(reasons.values()))}")
    board = write_leaderboard(suite, out, log=log)
    log(f"suite {suite.name} v{suite.version}: {time.perf_counter() - start:.1f} s in all")
    return board


def points_datasets(suite: Suite, out: Path, entries, run_on, log) -> dict:
    """{(points spec, dataset id): orchestrate.suite.points.make_points_dataset's result}:
    a copy of each of the suite's own datasets with the points an arm states, where the
    dataset holds other points; made as jobs on the suite's runner, before the method jobs."""
    jobs, owners = [], {}
    for spec in sorted({entry.points for entry in entries if entry.points is not None}):
        for scene in suite.scenes:
            base = dataset_dir(out, scene)
            if scene.foreign or not needs_copy(base, spec):
                continue
            key = f"points/{spec}/{scene.id}"
            jobs.append((key, make_points_dataset, dict(out=str(out), base=str(base), spec=spec,
                                                        target=str(points_folder(out, spec, scene.id)))))
            owners[key] = (spec, scene.id)
    if not jobs:
        return {}
    log(f"{len(jobs)} datasets with other initial points: " + ", ".join(owners))
    done = run_on(jobs)
    return {owners[key]: result for key, result in done.items()}


def arm_datasets(entry, copies: dict) -> dict:
    """{dataset id: the copy with the points `entry` states} where one was made (points_datasets)."""
    return {scene_id: copy["dataset"] for (spec, scene_id), copy in copies.items()
            if spec == entry.points and "dataset" in copy}


def method_jobs(suite: Suite, out: Path, entries, resolved: dict, manifest: dict, seeds, threads, log,
                copies: dict | None = None) -> tuple:
    """([(key, method_job, kwargs)], {key: (method, dataset id, seed folder or None)},
    {method: {dataset id: why skipped}}, {method: {dataset id: why it failed}}): a job per
    method, dataset and seed (`job_seeds`), where the dataset has what the method needs
    (missing_needs). An arm that states points trains on the dataset's copy with them
    (copies: `points_datasets`; none there: the dataset holds them), and fails on a
    dataset whose copy could not be made."""
    jobs, owners, skipped, refused, copies = [], {}, {}, {}, copies or {}
    for index, scene in enumerate(suite.scenes, 1):
        ds = open_dataset(dataset_dir(out, scene))
        for entry in entries:
            reasons = missing_needs(resolved[entry.name], ds)
            if entry.points is not None and scene.foreign:
                reasons.append(f"states points {entry.points}, which only a nerfgauge dataset's COLMAP export holds")
            if reasons:
                skipped.setdefault(entry.name, {})[scene.id] = "; ".join(reasons)
                log(f"[{index}/{len(suite.scenes)}] {scene.id}: {entry.name} skipped: {'; '.join(reasons)}")
                continue
            copy = copies.get((entry.points, scene.id))
            if copy is not None and "failed" in copy:
                refused.setdefault(entry.name, {})[scene.id] = copy["failed"]
                log(f"[{index}/{len(suite.scenes)}] {scene.id}: {entry.name} failed: {copy['failed']}")
                continue
            data = Path(arm_datasets(entry, copies).get(scene.id, dataset_dir(out, scene)))
            points_sha256 = None if copy is None else copy["manifest_sha256"]
            for seed, folder_seed in job_seeds(resolved[entry.name], scene, seeds):
                key = job_name(entry.name, scene.id, folder_seed)
                where = Path(entry.name) / ("" if folder_seed is None else seed_folder(folder_seed)) / scene.id
                jobs.append((key, method_job, dict(
                    out=str(out), job_key=key, entry=entry, train=suite.train, dataset=str(data),
                    manifest_sha256=identity(manifest["datasets"][scene.id]),
                    run_dir=str(out / "runs" / where), renders=str(out / PREDICTIONS / where), seed=seed,
                    split=suite.scoring["split"], geometry=suite.scoring.get("geometry"), threads=threads,
                    points_manifest_sha256=points_sha256)))
                owners[key] = (entry.name, scene.id, folder_seed)
    return jobs, owners, skipped, refused


def collect(out: Path, owners: dict, done: dict) -> tuple:
    """From the method jobs' results: ({method: {dataset id: {seed folder or None: (renders,
    pred format)}}}, {method: extras for write_result}, {method: {dataset id: why it failed}}).
    A dataset where one seed failed is failed: its other seeds are not scored."""
    renders, extras, failed = {}, {}, {}
    for key, (name, entry_id, folder_seed) in owners.items():
        result = done[key]
        if "failed" in result:
            failed.setdefault(name, {}).setdefault(entry_id, result["failed"] if folder_seed is None
                                                   else f"seed {folder_seed}: {result['failed']}")
            continue
        renders.setdefault(name, {}).setdefault(entry_id, {})[folder_seed] = (str(out / result["renders"]),
                                                                            result["pred_format"])
        row = {field: result[field] for field in EXTRAS}
        row["ms_per_frame"] = 1000.0 * result["render_seconds"] / result["frames"]
        if folder_seed is None:
            extras.setdefault(name, {})[entry_id] = row
        else:
            extras.setdefault(name, {}).setdefault(entry_id, {})[folder_seed] = row
    renders = {name: {entry_id: runs for entry_id, runs in by_entry.items() if entry_id not in failed.get(name, {})}
               for name, by_entry in renders.items()}
    return renders, extras, failed


EXTRAS = ("train_seconds", "steps", "steps_per_second", "cpu_seconds", "peak_memory_bytes", "model_bytes",
          "budget_seconds", "geometry", "seed")  # a job's training figures beside its scores


def identity(record: dict) -> str:
    """The hash a job's recipe binds it to: the dataset's manifest sha256, or a folder
    entry's ground-truth files' (orchestrate.suite.definition.identity_key)."""
    return record[identity_key(record)]


def job_seeds(method, scene, seeds) -> list[tuple]:
    """[(training seed, seed folder or None)] of one method on one dataset: a learned
    method once with the entry's seed, or once per --seeds seed; a method that does not
    train once, without a seed."""
    if not method.learned:
        return [(None, None)]
    if seeds is None:
        return [(scene.seed, None)]
    return [(seed, seed) for seed in seeds]


def _length(method, entry, train: dict) -> str:
    steps, budget = method.train_length(*entry.length(train))
    return "no training" if steps is None and budget is None else \
        f"{steps} steps" if budget is None else f"{budget:g} s budget"
