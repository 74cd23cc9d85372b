"""`nerfgauge generate`: render a scene into a complete, resumable, deterministic dataset.

Order of work: validate everything (nothing is written on bad input) -> claim the folder
(core.folders: refuses folders nerfgauge did not make, holds the write lock for the whole
run) -> config.json -> meshes -> views (each file written under a temporary name and
renamed, a view is done when all its files exist) -> transforms, scene.json ->
manifest.json last. A run that is interrupted resumes and renders only the missing views.

A dataset is identified by the hash of its recipe, which includes the sha256 of every
input file (user meshes) and the versions of the renderer, so a rerun after any of them
changed is refused (or, with --overwrite, re-rendered) instead of resumed as "complete".
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.metadata
import math
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from nerfgauge.generate import holdout, layouts, motion, transients
from nerfgauge.generate.degrade import FIELDS as DEGRADATION_FIELDS
from nerfgauge.generate.degrade import Degradations, add_frame_extras, camera_spread, frame_extras, train_poses
from nerfgauge.generate.export import export_colmap, export_current, require_pycolmap
from nerfgauge.generate.points import parse_spec
from nerfgauge.generate.distributed import dask_client, parse_scheduler, require_dask
from nerfgauge.generate.mitsuba_scene import instance_names, write_meshes
from nerfgauge.generate.render import NoiseTarget
from nerfgauge.generate.variant import CHOICES as VARIANT_CHOICES
from nerfgauge.generate.variant import resolve_variant
from nerfgauge.generate.views import noise_record, pending_views
from nerfgauge.generate.workers import render_views
from nerfgauge.scenes import make_scene
from nerfgauge.scenes.registry import scene_inputs

from nerfgauge.core import arguments, dataset, owned
from nerfgauge.core.camera import Intrinsics, ThinLens, check_lens
from nerfgauge.core.distortion import Distortion, parse_distortion
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, write_json
from nerfgauge.core.folders import claim_folder, read_marker, recipe_hash

CONFIG = "config.json"
DEFAULT_LAYOUT = "hemisphere"
DEFAULT_ELEVATION = (10.0, 75.0)
# Cameras inside an enclosure looking up past its walls see only sky: "inside" defaults to a
# band around the horizon (a scene's hint or --elevation still wins).
DEFAULT_ELEVATION_BY_LAYOUT = {"inside": (-20.0, 20.0)}
MAX_NOISE_PSNR = 80.0  # dB; beyond it the 8-bit PNG's own rounding (about 59 dB) dominates anyway
NOISE_PSNR = arguments.bounded(float, 0, MAX_NOISE_PSNR, above=True)
DEFAULT_MAX_SPP = 4096
LENS_SPLITS = {"test": ("test",), "all": ("train", "val", "test")}  # --lens-splits -> splits with the lens
DISTORTION_SPLITS = ("train",)  # issue 35: degradations apply to the training views only
RENDERER_PACKAGES = ("mitsuba", "drjit", "nerfgauge")  # their versions are part of a dataset's recipe


def renderer_versions() -> dict:
    """{package: installed version} of what renders a dataset (read without importing it)."""
    versions = {}
    for package in RENDERER_PACKAGES:
        try:
            versions[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            versions[package] = "not installed"
    return versions


@dataclass(frozen=True)
class GenerateConfig:
    """Everything that defines a dataset's content. Saved as config.json beside it."""

    scene: str = "primitives"
    seed: int = 0
    views: int = 100
    val_views: int = 10
    test_views: int = 20
    width: int = 128
    height: int = 128
    # Samples per pixel, or "auto" (add samples until noise_psnr is reached). 72 = two passes
    # of 36, a 6x6 multijitter grid each: as noisy as one 64-sample pass was (64 = 2 x 32 is
    # not a grid Mitsuba can lay out, 2.2 dB noisier at 128 px; docs/conventions.md "Noise").
    spp: object = 72
    max_depth: int = 8
    fov: float = 40.0
    layout: str = "auto"  # "auto": the scene's suggested cameras, else the hemisphere
    sampling: str = "fibonacci"
    elevation: Optional[tuple] = None  # None: the scene's suggestion, else DEFAULT_ELEVATION
    radius: Optional[float] = None  # None: the scene's suggestion, else fit the AABB's bounding sphere in view
    variant: str = "auto"
    noise_psnr: Optional[float] = None  # --spp auto's target: each view's sRGB noise PSNR, dB
    max_spp: int = DEFAULT_MAX_SPP  # --spp auto's cap per view
    # Thin lens (Mitsuba's thinlens sensor) for the colour of the views of lens_splits
    # ("test" or "all"); aperture 0 with no focus distance: every view a pinhole.
    aperture: float = 0.0
    focus_distance: Optional[float] = None
    lens_splits: str = "test"
    units: str = "normalise"  # "keep": user assets stay in their files' units
    envmap: Optional[str] = None  # an equirectangular .exr/.hdr lighting the scene instead of its lights
    envmap_rotation: float = 0.0  # degrees about +Z
    # Degraded TRAIN views (generate.degrade, docs/conventions.md "Degradations"); all 0: none.
    pose_noise_rotation: float = 0.0  # RMS rotation angle of the train poses' noise, degrees
    pose_noise_translation: float = 0.0  # RMS centre offset, fraction of the train cameras' spread
    exposure_ev: float = 0.0  # std of each train view's exposure, EV
    white_balance: float = 0.0  # std of each train view's log2 R and B gains
    vignetting: float = 0.0  # k of 1 - k r^2 on every train view
    degrade_seed: Optional[int] = None  # None: --seed
    # Lens distortion of the train views (--distortion opencv:k1,k2,p1,p2[,k3] or
    # fisheye:k1,k2,k3,k4; core.distortion); None: pinhole. Val and test stay pinhole.
    distortion: Optional[str] = None
    # Motion blur / rolling shutter of the train views (--motion-blur TRAVEL or
    # travel=T,rotation=DEG,exposure=E,readout=R; generate.motion); None: still cameras.
    motion_blur: Optional[str] = None
    # issue 35 item 6 (generate.holdout): a held-out sector "azimuth:A:B" / "elevation:A:B" and
    # test views at other distances (scales, e.g. (0.5, 1, 2)); None: the layout's splits
    holdout: Optional[str] = None
    test_scales: Optional[tuple] = None
    # issue 35 item 5 (generate.transients): this many small objects, each in this fraction of the train views
    transients: int = 0
    transient_fraction: float = 0.5

    def validate(self) -> None:
        positive = {"views": self.views, "width": self.width, "height": self.height, "max-depth": self.max_depth,
                    "max-spp": self.max_spp}
        if self.spp != "auto":
            positive["spp"] = self.spp
        for name, value in positive.items():
            if not isinstance(value, (int, np.integer)) or value <= 0:
                raise InputError(f"--{name} must be a positive integer, got {value!r}")
        for name, value in {"val-views": self.val_views, "test-views": self.test_views}.items():
            if not isinstance(value, (int, np.integer)) or value < 0:
                raise InputError(f"--{name} must be a non-negative integer, got {value!r}")
        if max(self.width, self.height) > 8192:
            raise InputError(f"--res {self.width}x{self.height} is larger than 8192 pixels on a side")
        # the command line's ranges (core.arguments), for values given through the API
        for name, value, limits in (("views", self.views, arguments.VIEWS), ("val-views", self.val_views, arguments.SPLIT_VIEWS),
                                    ("test-views", self.test_views, arguments.SPLIT_VIEWS),
                                    ("max-spp", self.max_spp, arguments.SPP), ("max-depth", self.max_depth, arguments.MAX_PATH_DEPTH),
                                    ("seed", self.seed, arguments.SEED),
                                    ("envmap-rotation", self.envmap_rotation, arguments.ROTATION_DEGREES),
                                    ("spp", None if self.spp == "auto" else self.spp, arguments.SPP),
                                    ("radius", self.radius, arguments.DISTANCE)):
            if value is not None:
                limits.check(value, f"--{name}")
        for value in self.elevation or ():
            arguments.ELEVATION_DEGREES.check(value, "--elevation")
        if not (0 < self.fov < 180) or not math.isfinite(self.fov):
            raise InputError(f"--fov must be in (0, 180) degrees, got {self.fov}")
        if self.radius is not None and not (self.radius > 0 and math.isfinite(self.radius)):
            raise InputError(f"--radius must be positive, got {self.radius}")
        if self.layout != "auto" and self.layout not in layouts.LAYOUTS:
            raise InputError(f"unknown layout {self.layout!r}; choose auto or one of {', '.join(layouts.LAYOUTS)}")
        if self.variant not in VARIANT_CHOICES:
            raise InputError(f"unknown variant {self.variant!r}; choose one of {', '.join(VARIANT_CHOICES)}")
        if not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise InputError(f"--seed must be a non-negative integer, got {self.seed!r}")
        self._validate_noise()
        self._validate_lens()
        self.degradations().validate()
        distortion = self.distortion_model()
        if distortion is not None:
            distortion.check_image(Intrinsics.from_fov(self.width, self.height, self.fov))
        blur = self.motion_model()
        if blur is not None:
            blur.check_rows(self.height)
            if self.spp == "auto":
                raise InputError("--motion-blur renders a fixed --spp per sub-frame; it does not combine with --spp auto")
            if self.lens() is not None and "train" in LENS_SPLITS[self.lens_splits] and blur.readout > 0:
                raise InputError("--motion-blur with a rolling shutter (readout > 0) does not combine with a thin lens "
                                 "on the train views (--lens-splits all)")
        if self.holdout is not None:
            holdout.parse_holdout(self.holdout)
        if self.test_scales is not None:
            holdout.parse_scales(self.test_scales)
        transients.check(self.transients, self.transient_fraction)


    def degradations(self) -> Degradations:
        """The train-view degradations (generate.degrade)."""
        return Degradations.of(self)

    def _validate_noise(self) -> None:
        target = self.noise_psnr
        if target is not None and (isinstance(target, bool) or not isinstance(target, (int, float, np.number))
                                   or not math.isfinite(target) or not 0 < target <= MAX_NOISE_PSNR):
            raise InputError(f"--noise-psnr must be a finite number of dB in (0, {MAX_NOISE_PSNR:g}], got {target!r}")
        if self.spp == "auto" and target is None:
            raise InputError("--spp auto needs --noise-psnr TARGET (dB)")
        if target is not None and self.spp == 1:
            raise InputError("--spp 1 renders one pass, so there is no noise estimate to reach --noise-psnr; "
                             "use --spp auto")
        if target is not None and self.spp != "auto":
            raise InputError(f"--noise-psnr is the target of --spp auto, not of a fixed --spp {self.spp}")
        if self.spp == "auto" and self.max_spp < 2:
            raise InputError(f"--max-spp must be at least 2 with --spp auto, got {self.max_spp}")

    @property
    def noise_target(self):
        """The render's NoiseTarget with --spp auto, else None."""
        return NoiseTarget(float(self.noise_psnr), max_spp=int(self.max_spp)) if self.spp == "auto" else None

    def _validate_lens(self) -> None:
        if self.lens_splits not in LENS_SPLITS:
            raise InputError(f"--lens-splits must be one of {', '.join(LENS_SPLITS)}, got {self.lens_splits!r}")
        if self.aperture != 0 and self.focus_distance is None:
            check_lens(self.aperture, 1.0)  # a negative aperture is named first
            raise InputError(f"--aperture {self.aperture:g} needs --focus-distance (distance of the plane in focus)")
        self.lens()  # InputError for a negative aperture or a focus distance <= 0

    def lens(self) -> Optional[ThinLens]:
        """The thin lens of the lens splits' views, None for a pinhole-only dataset."""
        if self.aperture == 0 and self.focus_distance is None:
            return None
        return ThinLens(self.aperture, self.focus_distance)

    def motion_model(self) -> Optional[motion.MotionBlur]:
        """The train views' motion blur (generate.motion), None for still cameras."""
        return motion.parse_motion_blur(self.motion_blur)

    def distortion_model(self) -> Optional[Distortion]:
        """The train views' lens distortion (core.distortion), None for none."""
        return parse_distortion(self.distortion)

    def to_json(self) -> dict:
        """The recipe's config. The lens, units and envmap fields only when they differ from
        the defaults, so a dataset keeps the recipe (and hash) it had before they existed."""
        out = dataclasses.asdict(self) | {"elevation": None if self.elevation is None else list(self.elevation)}
        if self.lens() is None and self.lens_splits == "test":
            for key in ("aperture", "focus_distance", "lens_splits"):
                del out[key]
        for name, default in (("units", "normalise"), ("envmap", None), ("envmap_rotation", 0.0), ("distortion", None),
                              ("motion_blur", None), ("holdout", None), ("test_scales", None), ("transients", 0),
                              *((name, getattr(Degradations(), name)) for name in DEGRADATION_FIELDS)):
            if out[name] == default:
                del out[name]
        if "transients" not in out and out["transient_fraction"] == 0.5:
            del out["transient_fraction"]
        if "test_scales" in out:
            out["test_scales"] = list(holdout.parse_scales(self.test_scales))
        return out


@dataclass(frozen=True)
class Plan:
    """What a run will produce: the resolved scene, cameras and frame names."""

    config: GenerateConfig
    scene: object
    intrinsics: Intrinsics
    layout: layouts.LayoutSpec  # as resolved: "auto" replaced by the scene's suggestion
    poses: dict  # split -> [n, 4, 4]
    stems: dict  # split -> [n] frame stems
    variant: str
    lightfield: Optional[dict]
    inputs: dict  # {path: sha256} of every file the scene was read from (user meshes)
    versions: dict  # renderer_versions()
    extrapolation: Optional[dict] = None  # scene.json's "extrapolation" (generate.holdout), None without one
    transients: tuple = ()  # generate.transients.Transient objects of the train views

    @property
    def radius(self) -> float:
        return self.layout.radius

    def lens(self, split: str) -> Optional[ThinLens]:
        """The thin lens the colour of `split`'s views is rendered through (None: pinhole)."""
        return self.config.lens() if split in LENS_SPLITS[self.config.lens_splits] else None

    def distortion(self, split: str) -> Optional[Distortion]:
        """The lens distortion `split`'s views are seen through: the train views only."""
        return self.config.distortion_model() if split in DISTORTION_SPLITS else None

    def motion_path(self, split: str, index: int) -> Optional[motion.CameraPath]:
        """The path of view `index` of `split` during its frame (train views with
        --motion-blur), None for a still camera."""
        blur = self.config.motion_model()
        if blur is None or split not in DISTORTION_SPLITS:
            return None
        return motion.view_path(self.poses[split][index], blur, self.scene.aabb, self.config.seed, index)

    def recipe(self) -> dict:
        """What config.json holds: the config plus the resolved radius and variant, the
        sha256 of every input file and the renderer's versions. Its hash names the dataset."""
        return {"schema": 2, "config": self.config.to_json(), "layout": self.layout.layout, "radius": self.radius,
                "variant": self.variant, "inputs": self.inputs, "versions": self.versions}


def plan(config: GenerateConfig) -> Plan:
    """Validate and resolve everything without writing anything."""
    config.validate()
    scene = make_scene(config.scene, config.seed, units=config.units, envmap=config.envmap,
                       envmap_rotation=config.envmap_rotation)
    intrinsics = Intrinsics.from_fov(config.width, config.height, config.fov)
    spec = layout_spec(config, scene)
    rng = np.random.default_rng(config.seed)
    poses = layouts.camera_poses(spec, scene.aabb, rng)
    held_out = holdout.extrapolation_split(spec, scene.aabb, poses, config.holdout, config.test_scales, config.seed,
                                           config.sampling)
    poses, extrapolation = (poses, None) if held_out is None else held_out
    lightfield = layouts.lightfield_plane(spec, scene.aabb) if spec.layout == "lightfield" else None
    stems = {split: [dataset.frame_stem(split, i, len(poses[split])) for i in range(len(poses[split]))]
             for split in dataset.SPLITS}
    if config.motion_model() is not None:  # a path the sub-frames cannot sample is refused before rendering
        motion.check_paths(poses["train"], config.motion_model(), scene.aabb, config.seed, intrinsics, stems["train"])
    return Plan(config, scene, intrinsics, spec, poses, stems, resolve_variant(config.variant), lightfield,
                scene_inputs(scene), renderer_versions(),
                extrapolation and holdout.frame_record(extrapolation, stems["test"]),
                transients.place(scene, config.transients, config.transient_fraction, len(poses["train"]), config.seed))


def layout_spec(config: GenerateConfig, scene) -> layouts.LayoutSpec:
    """The cameras asked for: the command line first, then (with --layout auto) the
    scene's suggestion, then the defaults (hemisphere, elevation 10-75 (inside: -20-20),
    radius that fits)."""
    hint = scene.cameras if config.layout == "auto" else None
    layout = config.layout if hint is None else hint.layout
    layout = DEFAULT_LAYOUT if layout == "auto" else layout
    radius = config.radius or (hint and hint.radius) or layouts.default_radius(scene.aabb, config.fov, config.width,
                                                                                config.height)
    elevation = config.elevation or (hint and hint.elevation) or DEFAULT_ELEVATION_BY_LAYOUT.get(layout,
                                                                                                 DEFAULT_ELEVATION)
    return layouts.LayoutSpec(layout, (config.views, config.val_views, config.test_views), float(radius),
                              tuple(float(a) for a in elevation), config.sampling,
                              eye=hint and hint.eye, target=hint and hint.target, spread=hint and hint.spread)


def stale_inputs(old: dict, new: dict) -> str | None:
    """What changed between two recipes' inputs or renderer versions, as "another version
    of bunny.obj (sha256 ...)"; None when those agree (the rest of the recipe may not)."""
    old_inputs, old_versions = old.get("inputs"), old.get("versions")
    if not isinstance(old_inputs, dict) or not isinstance(old_versions, dict):
        return None
    for path, digest in new["inputs"].items():
        if path in old_inputs and old_inputs[path] != digest:
            return f"another version of {Path(path).name} (sha256 {str(old_inputs[path])[:16]}..., now {digest[:16]}...)"
    for package, version in new["versions"].items():
        if package in old_versions and old_versions[package] != version:
            return f"{package} {old_versions[package]} (this is {package} {version})"
    return None


def refuse_stale(out: Path, recipe: dict) -> None:
    """Refuse, with what changed, to resume a dataset of ours whose input files or
    renderer versions are not the ones it was made from. Other differences are left to
    claim_folder's "another recipe" refusal; this only gives the reason a name."""
    if out.is_symlink() or not out.is_dir():
        return
    marker = read_marker(out)
    if marker is None or marker["kind"] != "dataset" or marker.get("recipe") == recipe_hash(recipe):
        return
    try:
        old = read_json(out / CONFIG)
    except InputError:
        return
    change = stale_inputs(old, recipe)
    if change:
        raise InputError(f"{out} was made from {change}; pass --overwrite to re-render it")


def finish(out: Path, the_plan: Plan) -> None:
    """Transforms, scene.json, then manifest.json (last: its presence means complete)."""
    import drjit  # drjit, mitsuba: loaded by the renderer anyway; here for scene.json's versions
    import mitsuba  # mitsuba, as above
    import trimesh  # trimesh: scene.json's versions

    intrinsics, stems, poses = the_plan.intrinsics, the_plan.stems, the_plan.poses
    # Degraded train views (generate.degrade): the train transforms hold the perturbed poses,
    # each train frame its exact pose and photometric parameters; other splits are exact.
    degradations, seed = the_plan.config.degradations(), the_plan.config.seed
    poses = dict(poses, train=train_poses(poses["train"], degradations, seed))
    extras = frame_extras(degradations, seed, the_plan.poses["train"])
    for split in dataset.SPLITS:
        transforms = dataset.synthetic_transforms(intrinsics, stems[split], poses[split], the_plan.lens(split),
                                                  the_plan.distortion(split))
        if split == "train":
            add_frame_extras(transforms, stems[split], extras, with_dot=True)
        write_json(out / f"transforms_{split}.json", transforms)
    lenses = {split: the_plan.lens(split) for split in dataset.SPLITS}
    distortions = {split: the_plan.distortion(split) for split in dataset.SPLITS}
    nerfstudio = add_frame_extras(dataset.nerfstudio_transforms(intrinsics, stems, poses, lenses, distortions),
                                  stems["train"], extras, with_dot=False)
    if the_plan.config.motion_model() is not None:
        add_motion(out, the_plan, nerfstudio)
    write_json(out / "transforms.json", nerfstudio)
    scene = the_plan.scene
    scene_json = {
        "schema": 1,
        "recipe": scene.name, "seed": scene.seed, "scene": scene.to_json(),
        "bounds": [list(scene.aabb_min), list(scene.aabb_max)],
        "needs": dataclasses.asdict(scene.needs),
        "camera": {"convention": "OpenGL camera-to-world: +X right, +Y up, looks along -Z",
                   "pixel_centres": "(col + 0.5, row + 0.5), row 0 at the top",
                   "layout": the_plan.layout.layout, "radius": the_plan.radius, "lightfield": the_plan.lightfield,
                   **({"lens": {"splits": list(LENS_SPLITS[the_plan.config.lens_splits]),
                                **the_plan.config.lens().to_json(),
                                "note": "colour only; depth, normals and masks are of the pinhole pixel-centre rays"}}
                      if the_plan.config.lens() is not None else {}),
                   **({"distortion": {"splits": list(DISTORTION_SPLITS), "spec": the_plan.config.distortion_model().to_text(),
                                      **the_plan.config.distortion_model().to_json(),
                                      "note": "every per-pixel file of these views (colour, albedo, depth, normals, mask, "
                                              "instance ids) follows the distorted pixel grid; other splits are pinhole "
                                              "(docs/conventions.md, Lens distortion)"}}
                      if the_plan.config.distortion_model() is not None else {}),
                   **({"motion_blur": {"splits": list(DISTORTION_SPLITS), "spec": the_plan.config.motion_model().to_text(),
                                       **the_plan.config.motion_model().to_json(),
                                       "note": "colour integrated over each row's exposure by sub-frames; the transform, "
                                               "depth, normals, masks, ids and albedo are the sharp mid-frame pose's "
                                               "(docs/conventions.md, Motion blur)"}}
                      if the_plan.config.motion_model() is not None else {})},
        "depth": {"distance": "*_distance.exr: Euclidean distance from the camera centre along the pixel-centre ray",
                  "z": "*_zdepth.exr: depth along the optical axis", "miss": 0,
                  "source": "scene.ray_intersect of pixel-centre rays, not the filtered depth AOV"},
        "images": {"png": "8-bit sRGB, straight alpha = coverage", "exr": "linear float32, premultiplied alpha",
                   "spp": the_plan.config.spp, "max_depth": the_plan.config.max_depth, "filter": "box",
                   "albedo": "*_albedo.exr: linear albedo of the first surface, box-filtered, 0 on misses"},
        "instances": {"file": "*_instance.png: 16-bit ids of the pixel-centre ray's shape, 0 = miss",
                      "names": instance_names(scene) + transients.names(the_plan.transients)},
        "noise": noise_summary(out, stems, the_plan.config),
        **({"degradations": degradations.to_json(seed) | {"spread": camera_spread(the_plan.poses["train"])}}
           if degradations.any else {}),
        "variant": the_plan.variant,
        **({"extrapolation": the_plan.extrapolation} if the_plan.extrapolation is not None else {}),
        **({"transients": transients.record(the_plan)} if the_plan.transients else {}),
        "inputs": the_plan.inputs,
        "recipe_sha256": recipe_hash(the_plan.recipe()),
        "versions": {"mitsuba": mitsuba.__version__, "drjit": drjit.__version__, "trimesh": trimesh.__version__,
                     "numpy": np.__version__, "python": platform.python_version(),
                     "nerfgauge": the_plan.versions["nerfgauge"]},
    }
    transients.write_masks(out, the_plan, len(instance_names(scene)))
    write_json(out / "scene.json", scene_json)
    write_json(out / dataset.NERFBASELINES_INFO, dataset.nerfbaselines_info(scene_json))
    write_json(out / holdout.SPARSE_FILE, holdout.sparse_views(poses["train"], stems["train"]))
    files = [p.relative_to(out).as_posix() for p in sorted(out.rglob("*"))
             if p.is_file() and p.name != dataset.MANIFEST and not p.name.startswith(".")]
    dataset.write_manifest(out, files)


def add_motion(out: Path, the_plan: Plan, nerfstudio: dict) -> None:
    """Each moving frame's path ("motion": direction, axis, travel, rotation, start and end
    poses, the shutter and its sub-frame count) in transforms_<split>.json (rewritten) and in
    the nerfstudio frames."""
    blur = the_plan.config.motion_model()
    entries = {}
    for split in DISTORTION_SPLITS:
        name = out / f"transforms_{split}.json"
        document = read_json(name)
        for index, frame in enumerate(document["frames"]):
            path = the_plan.motion_path(split, index)
            entry = {**path.to_json(), **blur.to_json(),
                     "subframes": motion.subframe_count(path, blur, the_plan.intrinsics, the_plan.scene.aabb)}
            frame["motion"] = entries[the_plan.stems[split][index] + ".png"] = entry
        write_json(name, document)
    for frame in nerfstudio["frames"]:
        if frame["file_path"] in entries:
            frame["motion"] = entries[frame["file_path"]]


NOISE_METHOD = ("two independent passes of spp/2 samples (seeds differ); the image is their mean; "
                "Var(mean) = E[(A - B)^2] / 4; sRGB: the transfer function and compositing applied to each pass "
                "before differencing; noise_psnr = 10 log10(1 / mean variance); psnr_ceiling adds the 8-bit PNG's "
                "rounding error (docs/conventions.md, Noise)")


def _noise(path: Path) -> dict:
    record = noise_record(path)  # checked when the view was rendered or found complete: a change since is refused
    if record is None:
        raise InputError(f"{path} is not a noise record nerfgauge wrote; delete it and rerun to render its view again")
    return record


def noise_summary(out: Path, stems: dict, config: GenerateConfig) -> dict:
    """scene.json's "noise": every frame's estimate (from its _noise.json) and per split the
    mean of each frame's dB figure (as PSNR is averaged), spp range, and why there is no
    estimate when there is none."""
    splits = {}
    for split in dataset.SPLITS:
        frames = [{"name": stem, **_noise(out / dataset.frame_files(stem)["noise"])} for stem in stems[split]]
        summary = {"frames": frames}
        if frames:
            summary["spp"] = {"min": min(f["spp"] for f in frames), "max": max(f["spp"] for f in frames),
                              "mean": float(np.mean([f["spp"] for f in frames]))}
            if all(f["noise_psnr"] is not None for f in frames):
                for key in ("noise_psnr", "psnr_ceiling"):
                    summary[key] = {name: float(np.mean([f[key][name] for f in frames])) for name in frames[0][key]}
            else:
                summary["noise_psnr"] = summary["psnr_ceiling"] = None
                summary["reason"] = next(f["reason"] for f in frames if f["noise_psnr"] is None)
        splits[split] = summary
    target = None if config.spp != "auto" else {"noise_psnr": config.noise_psnr, "max_spp": config.max_spp,
                                                 "on": "the worse of srgb_white and srgb_black"}
    return {"method": NOISE_METHOD, "auto": target, "splits": splits}


def generate(config: GenerateConfig, out, *, workers: int = 1, overwrite: bool = False,
             progress: bool = True, scheduler: Optional[str] = None, points: str = "surface") -> dict:
    """Render the dataset into `out`. Returns timing: views rendered, seconds, render seconds.
    `scheduler` (tcp://HOST:PORT or local:N) renders on a dask cluster (generate.distributed).
    points: the initial points of the COLMAP export (generate.points, KIND[:COUNT]); not part
    of the recipe: the export is a function of the rendered dataset and this spec."""
    points_spec = parse_spec(points)
    if points_spec.kind == "sfm":
        require_pycolmap("--points sfm")
        if config.distortion_model() is not None:
            raise InputError("--points sfm matches features with a PINHOLE camera; the train views of --distortion "
                             f"{config.distortion} are not: use --points surface or random")
    arguments.WORKERS.check(workers, "--workers")
    arguments.encodable_path(out, "--out")  # the API's path too: Mitsuba reads the meshes written under it
    if scheduler is not None:
        parse_scheduler(scheduler)
        require_dask()
        if workers != 1:
            raise InputError(f"--workers {workers} and --scheduler {scheduler} both choose where views render; "
                             "give one (local:N starts N dask workers)")
    out = Path(out)
    the_plan = plan(config)
    recipe = the_plan.recipe()
    if not overwrite:
        refuse_stale(out, recipe)
    cluster = contextlib.nullcontext()
    if scheduler is not None:
        cluster = dask_client(scheduler)  # connected before the folder is touched: an unreachable one writes nothing
    with cluster as client, claim_folder(out, "dataset", recipe_hash(recipe), overwrite=overwrite):
        return _generate_claimed(out, the_plan, recipe, workers, progress, client, points_spec)


def _generate_claimed(out: Path, the_plan: Plan, recipe: dict, workers: int, progress: bool, client=None,
                      points="surface") -> dict:
    """The run, while this process holds `out`'s write lock."""
    start = time.perf_counter()
    write_json(out / CONFIG, recipe)  # what the folder is made from (the same bytes when resuming)
    write_meshes(the_plan.scene, out / "meshes")  # before any worker loads them
    todo = pending_views(out, the_plan)
    if todo and (out / dataset.MANIFEST).is_file():
        owned.remove_file(out / dataset.MANIFEST)  # views are missing: the dataset is not complete
    render_seconds = render_views(out, the_plan, todo, workers=workers, progress=progress, client=client)
    finished = bool(todo) or not (out / dataset.MANIFEST).is_file()
    if finished:
        finish(out, the_plan)
    export = None
    lens = the_plan.lens("train")
    if lens is not None and not lens.is_pinhole:
        pass  # no COLMAP camera model states a thin lens: `nerfgauge export colmap` says so in one line
    elif finished or not export_current(out, points):  # after finish: the same code as `nerfgauge export colmap`
        export = export_colmap(out, points)
    return {"views_rendered": len(todo), "seconds": time.perf_counter() - start, "render_seconds": render_seconds,
            "variant": the_plan.variant, "export": export}
