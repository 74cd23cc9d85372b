"""`nerfgauge bench hard`: the hard scenes through the whole pipeline, checked for finiteness.

For each scene: `nerfgauge run SCENE --steps N` in its own process (generate, train the
compact NeRF briefly, render, evaluate), then an audit of everything it wrote:

- the dataset: every EXR (linear colour, ray distance, z-depth, normals) finite;
- training: exit code (3 = the training loop met a non-finite loss or gradient and
  stopped), every logged loss and val PSNR finite;
- renders: every predicted depth EXR finite (colour is 8-bit PNG, finite by construction);
- metrics: metrics.json parses with NaN/inf refused, and every metric is either a number
  or null with a frame count of 0 (undefined on that scene, e.g. depth with no hit pixel).

Writes OUT/hard.json (rows, rewritten after each scene) and OUT/hard.md (the table); OUT
is a nerfgauge "bench" folder (claimed and locked), each OUT/SCENE a "pipeline" folder
claimed by its `nerfgauge run` child.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from nerfgauge.orchestrate.bench.common import claim_bench_folder, run_child
from nerfgauge.eval.report import read_log

from nerfgauge.core import arguments
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, write_bytes_atomic, write_json
from nerfgauge.core.images import read_exr
from nerfgauge.scenes import make_scene


@dataclass(frozen=True)
class HardConfig:
    scenes: tuple
    width: int = 64
    height: int = 64
    views: int = 40
    test_views: int = 8
    spp: int = 64
    steps: int = 400
    seed: int = 0

    def validate(self) -> None:
        arguments.check_fields(self, {"width": arguments.IMAGE_SIDE, "height": arguments.IMAGE_SIDE,
                                      "views": arguments.VIEWS, "test_views": arguments.VIEWS,
                                      "spp": arguments.SPP, "steps": arguments.STEPS, "seed": arguments.SEED},
                               flags={"width": "--res", "height": "--res"})
        if not self.scenes:
            raise InputError("--scenes is empty")
        for scene in self.scenes:
            make_scene(scene, self.seed)  # an unknown name raises InputError naming the known ones

    def command(self, out) -> str:
        return (f"nerfgauge bench hard --scenes {','.join(self.scenes)} --res {self.width}x{self.height} "
                f"--views {self.views} --test-views {self.test_views} --spp {self.spp} --steps {self.steps} --out {out}")


def non_finite_exr_values(folder: Path, pattern: str) -> tuple[int, int]:
    """(files, non-finite values) over the EXRs matching `pattern` under `folder`."""
    files = bad = 0
    for path in sorted(folder.rglob(pattern)):
        channels, _ = read_exr(path)
        files += 1
        bad += sum(int((~np.isfinite(values)).sum()) for values in channels.values())
    return files, bad


def audit(out: Path) -> dict:
    """The finiteness checks of one `nerfgauge run` output folder (see the module doc)."""
    found = {}
    found["dataset_exr_files"], found["dataset_non_finite"] = non_finite_exr_values(out / "dataset", "*.exr")
    log_path = out / "run" / "log.jsonl"
    entries = read_log(log_path, finite=False) if log_path.is_file() else []
    numbers = [e[key] for e in entries for key in ("loss", "val_psnr") if e.get(key) is not None]
    found["log_entries"] = len(entries)
    found["log_non_finite"] = sum(not np.isfinite(x) for x in numbers)
    if entries:
        found["steps_per_second"], found["resolution"] = entries[-1].get("steps_per_second"), entries[-1].get("resolution")
    found["render_depth_files"], found["render_depth_non_finite"] = non_finite_exr_values(out / "run" / "renders",
                                                                                          "*_depth.exr")
    metrics_path = out / "eval" / "compact" / "metrics.json"
    try:
        metrics = read_json(metrics_path, finite=True)
    except InputError as error:
        found["metrics_error"] = str(error).splitlines()[0]
        return found
    found["mean"] = metrics["mean"]
    # metrics with a note (LPIPS without its weights) are not measured here, not empty
    absent = set(metrics.get("notes") or {})
    nulls = [name for name, value in metrics["mean"].items() if value is None and name not in absent]
    found["undefined"] = sorted(name for name in nulls if metrics["count"].get(name, 0) != 0)
    found["no_pixels"] = sorted(name for name in nulls if metrics["count"].get(name, 0) == 0)
    found["not_measured"] = sorted(absent)
    return found


def all_finite(found: dict) -> bool:
    return (found.get("exit") == 0 and "metrics_error" not in found and not found["undefined"]
            and found["dataset_non_finite"] == 0 and found["log_non_finite"] == 0
            and found["render_depth_non_finite"] == 0 and found["log_entries"] > 0)


def bench_hard(config: HardConfig, out: Path, progress_print=print) -> list:
    config.validate()
    out = Path(out)
    rows = []
    with claim_bench_folder(out, "hard"):
        for scene in config.scenes:
            progress_print(f"bench hard: {scene}")
            folder = out / scene
            code, seconds, peak_mb = run_child(
                ["run", scene, "--out", str(folder), "--res", f"{config.width}x{config.height}", "--views",
                 str(config.views), "--test-views", str(config.test_views), "--spp", str(config.spp), "--steps",
                 str(config.steps), "--seed", str(config.seed), "--overwrite", "--quiet"])
            row = {"scene": scene, "exit": code, "seconds": seconds, "peak_memory_mb": peak_mb} | audit(folder)
            row["finite"] = all_finite(row)
            rows.append(row)
            write_json(out / "hard.json", {"config": asdict(config), "command": config.command(out), "rows": rows})
        write_bytes_atomic(out / "hard.md", (table_markdown(rows, config.command(out)) + "\n").encode())
    return rows


def _cell(value, digits=2):
    return "–" if value is None else f"{value:.{digits}f}"


def table_markdown(rows: list, command: str) -> str:
    head = ("scene", "exit", "all finite", "test PSNR", "SSIM", "fg PSNR", "co-visible PSNR", "capture bound",
            "depth AbsRel", "resolved AbsRel", "δ<1.25", "IoU", "steps/s", "grid", "no pixels to score")
    lines = [f"`{command}`", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        mean = r.get("mean", {})
        cells = [r["scene"], str(r["exit"]), "yes" if r["finite"] else "**no**", _cell(mean.get("psnr")),
                 _cell(mean.get("ssim"), 4), _cell(mean.get("psnr_foreground")),
                 _cell(mean.get("psnr_covisible")), _cell(mean.get("psnr_capture_bound")),
                 _cell(mean.get("depth_absrel"), 4),
                 _cell(mean.get("depth_absrel_resolved"), 4),
                 _cell(mean.get("depth_delta1"), 3), _cell(mean.get("opacity_iou"), 3),
                 _cell(r.get("steps_per_second"), 1), str(r.get("resolution", "–")),
                 (", ".join(r.get("no_pixels", [])) or "–")
                 + (f" (not measured: {', '.join(r['not_measured'])})" if r.get("not_measured") else "")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
