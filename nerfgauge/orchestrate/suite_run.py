"""`nerfgauge suite run SUITE --out DIR`: our compact NeRF and the baselines through a whole
suite, each stage through its public function (generate, nerf train and render, eval
baselines and evaluate), then the leaderboard.

    DIR/                          the suite folder (orchestrate.suite): datasets, suite manifest
    DIR/runs/<id>/                our NeRF's training run on dataset <id>
    DIR/predictions/<method>/<id>/ renders of every method (ours: renders folder; baselines)
    DIR/predictions/<method>/suite.json  which suite they were made for
    DIR/results/<method>/         `suite evaluate` of those predictions (orchestrate.suite)
    DIR/leaderboard.{md,html,json}, DIR/report/<id>/report.html (orchestrate.suite_report)

Datasets are resumed (orchestrate.suite.generate_suite); training, renders and baselines are made
again on every run (their folders are ours and replaced through their markers).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from nerfgauge.core.files import write_bytes_atomic, write_json
from nerfgauge.orchestrate.suite import OURS, SUITE_FILE, Suite, dataset_dir, evaluate_suite, generate_suite
from nerfgauge.core.dataset import open_dataset
from nerfgauge.eval.baselines import baseline_folder, write_baseline
from nerfgauge.eval.geometry import score_geometry, summary
from nerfgauge.nerf.mesh import NoSurface, mesh_from_run, ply_bytes
from nerfgauge.orchestrate.suite_report import write_leaderboard

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


def run_suite(suite: Suite, out, *, overwrite: bool = False, progress: bool = False, log=print) -> dict:
    """Generate, train, render, baselines, evaluate, leaderboard. Returns the leaderboard."""
    from nerfgauge.nerf.config import TrainConfig  # torch: kept off `nerfgauge --help`'s import path
    from nerfgauge.nerf.render_views import render_split  # torch
    from nerfgauge.nerf.train import train  # torch

    out = Path(out)
    start = time.perf_counter()
    generate_suite(suite, out, overwrite=overwrite, progress=progress, log=log)
    split = suite.protocol["split"]
    predictions = out / "predictions"
    extras, baseline_roots, skipped = {}, {}, {}
    for index, entry in enumerate(suite.scenes, 1):
        data = dataset_dir(out, entry)
        if entry.foreign:
            for method, reason in skipped_on_folder(suite, entry).items():
                skipped.setdefault(method, {})[entry.id] = reason
                log(f"[{index}/{len(suite.scenes)}] {entry.id}: {method} skipped: {reason}")
            continue
        run_dir = out / "runs" / entry.id
        log(f"[{index}/{len(suite.scenes)}] {entry.id}: train {suite.train.get('model', 'compact')} "
            f"{suite.train['steps']} steps")
        config = TrainConfig(dataset=str(data), seed=entry.seed, **suite.train)
        clock = time.perf_counter()
        summary = train(config, run_dir, overwrite=True, progress=progress)
        stages = {"train": time.perf_counter() - clock}
        clock = time.perf_counter()
        render_split(run_dir, split, predictions / OURS / entry.id, overwrite=True, progress=progress)
        stages["render"], clock = time.perf_counter() - clock, time.perf_counter()
        extras[entry.id] = {"train_seconds": summary["seconds"], "model_bytes": summary["model_bytes"],
                            "steps": summary["steps"], "geometry": geometry_of(suite, data, run_dir, log)}
        stages["geometry"], clock = time.perf_counter() - clock, time.perf_counter()
        layout = open_dataset(data).scene.get("camera", {}).get("layout")
        for method in methods_for(suite, layout):
            target = predictions / method / entry.id
            with baseline_folder(data, method, target, split, overwrite=True):
                write_baseline(data, method, target, split)
            baseline_roots.setdefault(method, []).append(entry.id)
        stages["baselines"] = time.perf_counter() - clock
        log(f"    {entry.id}: " + ", ".join(f"{name} {seconds:.1f} s" for name, seconds in stages.items()))
    methods = {OURS: extras} if extras else {}
    for method, ids in baseline_roots.items():
        methods[method] = {entry_id: {"train_seconds": 0.0, "model_bytes": None} for entry_id in ids}
    for method, method_extras in methods.items():
        root = predictions / method
        write_json(root / SUITE_FILE, suite.identity())
        ids = set(method_extras)
        if ids != {entry.id for entry in suite.scenes}:
            log(f"{method}: applies to {len(ids)} of {len(suite.scenes)} datasets; scored on those only")
            evaluate_subset(suite, out, method, root, ids, method_extras, log, skipped.get(method))
        else:
            evaluate_suite(suite, out, method, root, extras=method_extras, log=log)
    board = write_leaderboard(suite, out, log=log)
    log(f"suite {suite.name} v{suite.version}: {time.perf_counter() - start:.1f} s in all")
    return board


def evaluate_subset(suite: Suite, out, method: str, root, ids: set, extras: dict, log, skipped=None) -> dict:
    """evaluate_suite on the suite's entries in `ids` (a baseline that applies to some
    layouts only); the leaderboard shows the others as not applicable."""
    subset = dataclasses.replace(suite, scenes=tuple(e for e in suite.scenes if e.id in ids))
    return evaluate_suite(suite, out, method, root, extras=extras, log=log, entries=subset.scenes, skipped=skipped)


def geometry_of(suite: Suite, data: Path, run_dir: Path, log):
    """Our NeRF's mesh scored against the exact meshes (eval.geometry.summary's flat numbers),
    when the suite's protocol asks for it; {"n/a": reason} when the field has no surface."""
    settings = suite.protocol.get("geometry")
    if not settings:
        return None
    try:
        mesh = mesh_from_run(run_dir, settings["resolution"])
    except NoSurface as reason:
        log(f"geometry n/a: {reason}")
        return {"n/a": str(reason)}
    write_bytes_atomic(run_dir / "mesh.ply", ply_bytes(mesh.vertices, mesh.faces))
    document, _ = score_geometry(data, run_dir / "mesh.ply", samples=settings["samples"])
    return summary(document)
