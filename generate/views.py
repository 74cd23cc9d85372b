"""One view of a dataset, from its seed to its files: the renderer's seed of each view,
which views are complete on disk and which are pending, loading the Mitsuba scene and
rendering one view, and writing its files. The generator (generate.pipeline), its local
workers (generate.workers) and its dask tasks (generate.distributed) share these.

`the_plan` below is a generate.pipeline.Plan (poses, intrinsics, stems, config).
"""

from __future__ import annotations

import math
import numbers
import time
from pathlib import Path

import numpy as np

from nerfgauge.core import dataset, owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, write_json
from nerfgauge.core.images import premultiplied_to_png_rgba, write_exr, write_png
from nerfgauge.generate.degrade import degrade_images
from nerfgauge.generate.mitsuba_scene import scene_dict
from nerfgauge.generate.motion import render_motion_view
from nerfgauge.generate import transients
from nerfgauge.generate.render import BACKGROUNDS, render_view
from nerfgauge.generate.variant import use_variant

SPLIT_SEED_OFFSET = {"train": 0, "val": 1_000_000, "test": 2_000_000}


def view_seed(config_seed: int, split: str, index: int) -> int:
    """The renderer's seed for one view: a function of (seed, split, index) only, so the
    same view gets the same noise however views are ordered or spread over workers."""
    return (config_seed * 7_919_993 + SPLIT_SEED_OFFSET[split] + index) % (2**32)


def view_complete(out: Path, stem: str) -> bool:
    """All nine files are there and the noise record is one render.noise_estimate writes
    (`noise_record`): a resumed view whose record is not is rendered again, not trusted."""
    files = dataset.frame_files(stem)
    return all((out / rel).is_file() for rel in files.values()) and noise_record(out / files["noise"]) is not None


NOISE_KEYS = {"spp", "passes", "png_quantisation_mse", "noise_psnr", "psnr_ceiling"}  # render.noise_estimate's
NOISE_PSNR_KEYS = {"linear", *(f"srgb_{name}" for name in BACKGROUNDS)}


def noise_record(path: Path) -> dict | None:
    """A view's _noise.json re-validated as render.noise_estimate makes it (its keys, spp a
    positive whole number that its passes add up to, every figure a finite number, `reason`
    exactly when there is no estimate); None when it is not one. It is state scene.json is
    built from on a resumed run, so it is data to check, not to trust."""
    try:
        record = read_json(path, finite=True)
    except (InputError, OSError):
        return None

    def figures(value, keys) -> bool:
        return isinstance(value, dict) and set(value) == keys and all(
            isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) for v in value.values())

    spp, passes, estimate = record.get("spp"), record.get("passes"), record.get("noise_psnr")
    whole = [spp] + (passes if isinstance(passes, list) else [])
    if not (isinstance(passes, list) and len(passes) in (1, 2) and all(type(n) is int and n > 0 for n in whole)
            and sum(passes) == spp and figures(record.get("png_quantisation_mse"), set(BACKGROUNDS))):
        return None
    if estimate is None:
        ok = set(record) == NOISE_KEYS | {"reason"} and record["psnr_ceiling"] is None \
            and isinstance(record["reason"], str)
    else:
        ok = set(record) == NOISE_KEYS and figures(estimate, NOISE_PSNR_KEYS) \
            and figures(record["psnr_ceiling"], set(BACKGROUNDS))
    return record if ok else None


def write_view(out: Path, stem: str, images) -> None:
    """Write one view's nine files; the PNG last is no marker: completeness is all nine."""
    files = {kind: out / rel for kind, rel in dataset.frame_files(stem).items()}
    owned.make_folder(files["png"].parent)
    write_exr(files["exr"], {"RGBA": images.rgba}, {"nerfgauge": "linear RGBA, premultiplied alpha = coverage"})
    write_exr(files["distance"], {dataset.DEPTH_CHANNEL: images.distance}, {"nerfgauge_depth": "ray_distance", "nerfgauge_miss": "0"})
    write_exr(files["z_depth"], {dataset.DEPTH_CHANNEL: images.z_depth}, {"nerfgauge_depth": "z_depth", "nerfgauge_miss": "0"})
    write_exr(files["normals"], {"X": images.normals[..., 0], "Y": images.normals[..., 1], "Z": images.normals[..., 2]},
              {"nerfgauge": "world-space shading normals, 0 on misses"})
    write_png(files["mask"], (images.hit * 255).astype(np.uint8))
    dataset.write_instance_png(files["instance"], images.instance)
    write_exr(files["albedo"], {"R": images.albedo[..., 0], "G": images.albedo[..., 1], "B": images.albedo[..., 2]},
              {"nerfgauge": "linear albedo of the first surface (Mitsuba aov integrator), box-filtered, 0 on misses"})
    write_json(files["noise"], images.noise)
    write_png(files["png"], premultiplied_to_png_rgba(images.rgba))


def pending_views(out: Path, the_plan) -> list:
    """(split, index) of every view whose files are not all on disk."""
    return [(split, i) for split in dataset.SPLITS for i, stem in enumerate(the_plan.stems[split])
            if not view_complete(out, stem)]


def load_mitsuba_scene(out, the_plan):
    """Set the variant and load the scene from the meshes already on disk. Returns (mi, scene)."""
    mi = use_variant(the_plan.variant)
    mesh_paths = {path.stem: path for path in (out / "meshes").glob("*.ply")}
    # optimize=False: Mitsuba would otherwise merge shapes that share a BSDF into one mesh
    # (two untextured objects of a GLB become "ball.ply + crate.ply"), and every pixel of
    # both would get one instance id.
    return mi, mi.load_dict(scene_dict(mi, the_plan.scene, mesh_paths, the_plan.config.max_depth), optimize=False)


def render_one(mi, scene, out, the_plan, split, index):
    config = the_plan.config
    # the static scene, or it with the view's transient objects (generate.transients)
    scene, integrator, legend = transients.scene_for_view(mi, scene, out, the_plan, split, index)
    start = time.perf_counter()
    path = the_plan.motion_path(split, index)
    if path is not None:  # a moving camera: generate.motion integrates the frame
        images, _ = render_motion_view(mi, scene, path, config.motion_model(), the_plan.intrinsics, config.spp,
                                       view_seed(config.seed, split, index), aabb=the_plan.scene.aabb,
                                       integrator=integrator, legend=legend, distortion=the_plan.distortion(split),
                                       lens=the_plan.lens(split))
    else:
        images = render_view(mi, scene, the_plan.poses[split][index], the_plan.intrinsics, config.spp,
                             view_seed(config.seed, split, index), target=config.noise_target,
                             lens=the_plan.lens(split), distortion=the_plan.distortion(split),
                             integrator=integrator, legend=legend)
    degradations = config.degradations()
    if split == "train" and degradations.photometric:  # train views only (generate.degrade)
        images = degrade_images(images, degradations.view_photometric(config.seed, index), the_plan.intrinsics)
    return images, time.perf_counter() - start
