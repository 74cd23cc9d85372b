"""nerfgauge's own methods behind the method interface: the compact and the vanilla NeRF
(nerf/), and the non-learned baselines (methods.baselines).

torch is imported inside the functions that train or render, so listing the methods
(`nerfgauge methods`) stays instant.
"""

from __future__ import annotations

import time
from pathlib import Path

from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json
from nerfgauge.methods.baselines import baseline_folder, write_baseline
from nerfgauge.methods.interface import Method, Needs, Produces, RenderResult, TrainRequest, TrainResult
from nerfgauge.methods.measure import measured

# TrainConfig fields the request sets; a method's settings table may not set them as well
REQUEST_FIELDS = ("dataset", "seed", "steps", "budget_seconds", "threads", "device", "model")


class NeRF(Method):
    """Our NeRFs (nerf.train, nerf.render_views): `settings` are TrainConfig fields."""

    needs = Needs(manifest=True, scene_bounds=True)
    produces = Produces(depth=True, normals=True)

    def __init__(self, model: str, summary: str):
        self.model, self.name, self.summary = model, model, summary

    def config(self, request: TrainRequest):
        from nerfgauge.nerf.config import TrainConfig  # torch

        clash = sorted(set(request.settings) & set(REQUEST_FIELDS))
        if clash:
            raise InputError(f"method {self.name}: {clash[0]!r} is set by the job, not by the method's settings")
        known = set(TrainConfig.__dataclass_fields__)
        unknown = sorted(set(request.settings) - known)
        if unknown:
            raise InputError(f"method {self.name}: unknown setting {unknown[0]!r} (TrainConfig fields: "
                             f"{', '.join(sorted(known - set(REQUEST_FIELDS)))})")
        length = {"steps": request.steps} if request.steps is not None else {"budget_seconds": request.budget_seconds}
        if request.steps is None and request.budget_seconds is None:
            raise InputError(f"method {self.name} trains: give it steps or a time budget")
        threads = {} if request.threads is None else {"threads": request.threads}
        config = TrainConfig(dataset=str(request.dataset), model=self.model, seed=request.seed,
                             device=request.device, **length, **threads, **request.settings)
        config.validate()
        return config

    def check(self, request: TrainRequest) -> None:
        self.config(request)  # the settings as TrainConfig checks them

    def train(self, request: TrainRequest) -> TrainResult:
        from nerfgauge.nerf.train import train  # torch

        config = self.config(request)
        with measured() as cost:
            summary = train(config, request.run, overwrite=request.overwrite, progress=request.progress)
        return TrainResult(seconds=summary["seconds"], steps=summary["steps"], cpu_seconds=cost.cpu_seconds,
                           peak_memory_bytes=cost.peak_memory_bytes, model_bytes=summary["model_bytes"],
                           extra={"val_psnr": summary["val_psnr"], "threads": config.threads,
                                  "wall_seconds": cost.seconds})

    def render(self, run, dataset, split, out, *, overwrite=False, progress=False) -> RenderResult:
        from nerfgauge.nerf.render_views import render_split  # torch

        # the dataset trained on renders as a run's own (its renders' recipe names no other dataset)
        trained_on = Path(read_json(Path(run) / "config.json").get("dataset", ""))
        other = None if trained_on.resolve() == Path(dataset).resolve() else dataset
        start = time.perf_counter()
        timing = render_split(run, split, out, overwrite=overwrite, progress=progress, dataset=other)
        return RenderResult(out=Path(out), frames=int(timing.get("frames", 0)), seconds=time.perf_counter() - start)


class Baseline(Method):
    """A non-learned baseline (methods.baselines): nothing to train; it renders from the
    training images directly."""

    learned = False
    accepts_budget = False

    def __init__(self, name: str, summary: str, needs: Needs):
        self.name, self.summary, self.needs = name, summary, needs

    def train(self, request: TrainRequest) -> TrainResult:
        return TrainResult(seconds=0.0, steps=None)

    def render(self, run, dataset, split, out, *, overwrite=False, progress=False) -> RenderResult:
        with baseline_folder(dataset, self.name, out, split, overwrite=overwrite):
            timing = write_baseline(dataset, self.name, out, split)
        return RenderResult(out=Path(out), frames=int(timing["frames"]), seconds=float(timing["seconds"]))


def builtin_methods() -> dict:
    """{name: Method} of every method nerfgauge ships, in the order `nerfgauge methods` lists them."""
    grid = Needs(lightfield_layout=True)
    methods = [
        NeRF("compact", "the compact NeRF: a voxel grid with occupancy skipping, modelling only what the scene needs"),
        NeRF("vanilla", "the original NeRF (Mildenhall et al. 2020): positional encoding, an MLP, coarse and fine"),
        Baseline("nearest", "the training image whose camera is closest to the query camera, copied",
                 Needs(scene_bounds=True)),
        Baseline("lightfield-nearest", "the two-plane light field, nearest camera and pixel", grid),
        Baseline("lightfield-quadrilinear", "the two-plane light field, quadrilinear interpolation", grid),
        Baseline("refocus", "synthetic-aperture refocusing over the light field's camera grid", grid),
    ]
    return {method.name: method for method in methods}
