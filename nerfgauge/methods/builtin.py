"""nerfgauge's own methods behind the method interface: the compact and the vanilla NeRF
(nerf/), Gaussian splatting (splat/), and the non-learned baselines (methods.baselines).

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
from nerfgauge.splat.config import SplatConfig

# TrainConfig (and SplatConfig) fields the request sets; a method's settings table may not set them as well
REQUEST_FIELDS = ("dataset", "seed", "steps", "budget_seconds", "threads", "device", "model")


def config_fields(method: Method, request: TrainRequest, known: set) -> dict:
    """The config fields of `request` for a method whose config has the fields `known`:
    the request's seed, length, threads and device, and its settings (each a known field the
    request does not set; InputError naming the first other)."""
    clash = sorted(set(request.settings) & set(REQUEST_FIELDS))
    if clash:
        raise InputError(f"method {method.name}: {clash[0]!r} is set by the job, not by the method's settings")
    unknown = sorted(set(request.settings) - known)
    if unknown:
        raise InputError(f"method {method.name}: unknown setting {unknown[0]!r} (its config's fields: "
                         f"{', '.join(sorted(known - set(REQUEST_FIELDS)))})")
    if request.steps is None and request.budget_seconds is None:
        raise InputError(f"method {method.name} trains: give it steps or a time budget")
    length = {"steps": request.steps} if request.steps is not None else {"budget_seconds": request.budget_seconds}
    threads = {} if request.threads is None else {"threads": request.threads}
    return {"seed": request.seed, "device": request.device, **length, **threads, **request.settings}


class NeRF(Method):
    """Our NeRFs (nerf.train, nerf.render_views): `settings` are TrainConfig fields."""

    needs = Needs(manifest=True, scene_bounds=True)
    produces = Produces(depth=True, normals=True)

    def __init__(self, model: str, summary: str):
        self.model, self.name, self.summary = model, model, summary

    def config(self, request: TrainRequest):
        from nerfgauge.nerf.config import TrainConfig  # torch

        fields = config_fields(self, request, set(TrainConfig.__dataclass_fields__))
        config = TrainConfig(dataset=str(request.dataset), model=self.model, **fields)
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


class Splat(Method):
    """3D Gaussian splatting (splat.train, splat.render_views): `settings` are SplatConfig
    fields (init: which of the dataset's COLMAP points it starts from, ...). It starts from
    the points of the dataset's COLMAP model (sparse/0); init = "none" draws them in the
    scene bounds instead, but the harness still asks for the model."""

    name = "splat"
    summary = "3D Gaussian splatting (Kerbl et al. 2023) on the CPU, from the dataset's COLMAP points"
    needs = Needs(manifest=True, colmap_model=True, initial_points=True)
    produces = Produces(depth=True)

    def config(self, request: TrainRequest):
        config = SplatConfig(dataset=str(request.dataset),
                             **config_fields(self, request, set(SplatConfig.__dataclass_fields__)))
        config.validate()
        return config

    def check(self, request: TrainRequest) -> None:
        self.config(request)  # the settings as SplatConfig checks them

    def train(self, request: TrainRequest) -> TrainResult:
        from nerfgauge.splat.train import train  # torch

        config = self.config(request)
        with measured() as cost:
            summary = train(request.dataset, request.run, config, overwrite=request.overwrite,
                            progress=request.progress)
        return TrainResult(seconds=summary["seconds"], steps=summary["steps"], cpu_seconds=cost.cpu_seconds,
                           peak_memory_bytes=cost.peak_memory_bytes, model_bytes=summary["model_bytes"],
                           extra={"val_psnr": summary["val_psnr"], "gaussians": summary["gaussians"],
                                  "threads": config.threads, "wall_seconds": cost.seconds})

    def render(self, run, dataset, split, out, *, overwrite=False, progress=False) -> RenderResult:
        from nerfgauge.splat.render_views import render_split  # torch

        start = time.perf_counter()  # the run is checked against `dataset`'s manifest (its own or a copy)
        timing = render_split(run, split, out, dataset=dataset, overwrite=overwrite, progress=progress)
        return RenderResult(out=Path(out), frames=int(timing["frames"]), seconds=time.perf_counter() - start)


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
        Splat(),
        Baseline("nearest", "the training image whose camera is closest to the query camera, copied",
                 Needs(scene_bounds=True)),
        Baseline("lightfield-nearest", "the two-plane light field, nearest camera and pixel", grid),
        Baseline("lightfield-quadrilinear", "the two-plane light field, quadrilinear interpolation", grid),
        Baseline("refocus", "synthetic-aperture refocusing over the light field's camera grid", grid),
    ]
    return {method.name: method for method in methods}
