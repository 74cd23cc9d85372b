"""`nerfgauge bench parametrisation`: the automatic parametrisation against each forced one,
at equal steps and seed, on captures nobody tuned the rule for (issue 52).

For each scene (default: scenes/checks.py's TRIAL_CHECK_SCENES, in no bench and no suite):
one dataset (`nerfgauge generate`), then `nerfgauge train --steps N --seed S` with the
automatic parametrisation and with each forced one, each rendered and evaluated on the
test views. Step-budgeted, so the figures do not depend on the machine's load. Forward
space is forced only where every camera stands outside the scene's box (it needs cameras
on one side looking one way). The automatic run's config.json says what it picked, why,
and, where the rule was unsure, what its trial measured (nerf.trials).

Writes OUT/parametrisation.json (rewritten after each run) and OUT/parametrisation.md; OUT
is a nerfgauge "bench" folder, OUT/SCENE/dataset a dataset folder, OUT/SCENE/run-KIND run
folders (each replaced through its own marker on a rerun).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

from nerfgauge.orchestrate.bench.common import claim_bench_folder, run_child

from nerfgauge.core import arguments
from nerfgauge.core.dataset import open_dataset
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, write_bytes_atomic, write_json
from nerfgauge.core.folders import remove_owned
from nerfgauge.scenes import make_scene
from nerfgauge.scenes.checks import TRIAL_CHECK_SCENES

FORCED = ("bounded", "contracted", "forward")
# issue 52's bar: the automatic choice within this of the best forced one on each capture
WITHIN_DB = 0.3


@dataclass(frozen=True)
class ParametrisationBenchConfig:
    scenes: tuple = TRIAL_CHECK_SCENES
    width: int = 64
    height: int = 64
    views: int = 40
    val_views: int = 4
    test_views: int = 8
    spp: int = 64
    steps: int = 300
    seed: int = 0

    def validate(self) -> None:
        arguments.check_fields(self, {"width": arguments.IMAGE_SIDE, "height": arguments.IMAGE_SIDE,
                                      "views": arguments.VIEWS, "val_views": arguments.VIEWS,
                                      "test_views": arguments.VIEWS, "spp": arguments.SPP, "steps": arguments.STEPS,
                                      "seed": arguments.SEED}, flags={"width": "--res", "height": "--res"})
        if not self.scenes:
            raise InputError("--scenes is empty")
        for scene in self.scenes:
            make_scene(scene, self.seed)  # an unknown name raises InputError naming the known ones

    def command(self, out) -> str:
        return (f"nerfgauge bench parametrisation --scenes {','.join(self.scenes)} --res {self.width}x{self.height} "
                f"--views {self.views} --val-views {self.val_views} --test-views {self.test_views} --spp {self.spp} "
                f"--steps {self.steps} --seed {self.seed} --out {out}")


def _run(argv: list, what: str) -> None:
    code, _, _ = run_child([str(a) for a in argv])
    if code != 0:
        raise InputError(f"bench parametrisation: {what} failed (exit {code}): nerfgauge {' '.join(map(str, argv))}")


def cameras_outside(dataset: Path) -> bool:
    """Whether every train camera of `dataset` stands outside its scene box (forward space
    can then be forced)."""
    ds = open_dataset(dataset)
    c2w, aabb = ds.cameras("train").c2w, ds.bounds
    if aabb is None:
        return True
    positions = c2w[:, :3, 3]
    return not bool(((positions >= aabb[0]) & (positions <= aabb[1])).all(axis=1).any())


def scene_row(config: ParametrisationBenchConfig, scene: str, out: Path, save) -> dict:
    """One scene: its dataset, the automatic run and each forced one. `save(row)` is called
    after each run with the row so far."""
    dataset = out / "dataset"
    if not (dataset / "manifest.json").is_file():
        _run(["generate", scene, "--out", dataset, "--views", config.views, "--val-views", config.val_views,
              "--test-views", config.test_views, "--res", f"{config.width}x{config.height}", "--spp", config.spp,
              "--seed", config.seed, "--quiet", "--overwrite"], f"generate {scene}")
    kinds = ("auto",) + tuple(k for k in FORCED if k != "forward" or cameras_outside(dataset))
    row = {"scene": scene, "runs": {}}
    for kind in kinds:
        run = out / f"run-{kind}"
        remove_owned(run, "run")
        _run(["train", dataset, "--out", run, "--steps", config.steps, "--seed", config.seed, "--quiet"]
             + ([] if kind == "auto" else ["--parametrisation", kind]), f"train {scene} {kind}")
        _run(["render", run, "--quiet", "--overwrite"], f"render {scene} {kind}")
        _run(["evaluate", dataset, "--pred", run / "renders", "--out", run / "metrics.json", "--no-held-out",
              "--overwrite"], f"evaluate {scene} {kind}")
        run_config = read_json(run / "config.json")
        row["runs"][kind] = {"psnr": read_json(run / "metrics.json")["mean"]["psnr"],
                             "parametrisation": run_config["parametrisation"],
                             "reason": run_config["auto_reasons"]["parametrisation"],
                             "trial": (run_config.get("trials") or {}).get("parametrisation"),
                             "final_resolution": run_config["final_resolution"]}
        save(row)
    return row | verdict(row)


def verdict(row: dict) -> dict:
    """The automatic run against the best forced one: {"best_forced", "auto_minus_best", "within"}."""
    forced = {kind: run["psnr"] for kind, run in row["runs"].items() if kind != "auto"}
    if "auto" not in row["runs"] or not forced:
        return {}
    best = max(forced, key=forced.get)
    gap = row["runs"]["auto"]["psnr"] - forced[best]
    return {"best_forced": best, "auto_minus_best": gap, "within": gap >= -WITHIN_DB}


def bench_parametrisation(config: ParametrisationBenchConfig, out, progress_print=print) -> list:
    config.validate()
    out = Path(out)
    rows = []

    def save(current=None):
        shown = rows + ([current | verdict(current)] if current is not None else [])
        write_json(out / "parametrisation.json", {"config": asdict(config), "command": config.command(out),
                                                   "rows": shown})

    with claim_bench_folder(out, "parametrisation"):
        for scene in config.scenes:
            progress_print(f"bench parametrisation: {scene}")
            rows.append(scene_row(config, scene, out / scene, save))
            save()
        write_bytes_atomic(out / "parametrisation.md", (table_markdown(rows, config.command(out)) + "\n").encode())
    return rows


def _trial_cell(run: dict) -> str:
    trial = run.get("trial")
    if not trial:
        return "no (the rule is sure)"
    scores = ", ".join(f"{kind} {psnr:.2f}" for kind, psnr in trial["val_psnr"].items())
    return f"yes, {100 * trial['share']:g}% each: {scores} dB (val) -> {trial['chosen']}"


def table_markdown(rows: list, command: str) -> str:
    head = ("scene", "automatic pick", "trial", "auto", *FORCED, "auto - best forced", f"within {WITHIN_DB} dB")
    lines = [f"`{command}`", "", "test PSNR (dB), equal steps and seed:", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        runs = row["runs"]
        auto = runs.get("auto", {})
        cells = [row["scene"], auto.get("parametrisation", "–"), _trial_cell(auto) if auto else "–",
                 f"{auto['psnr']:.2f}" if auto else "–"]
        cells += [f"{runs[k]['psnr']:.2f}" if k in runs else "–" for k in FORCED]
        cells += [f"{row['auto_minus_best']:+.2f} (best: {row['best_forced']})" if "best_forced" in row else "–",
                  ("yes" if row["within"] else "**no**") if "within" in row else "–"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
