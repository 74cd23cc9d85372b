"""Transient objects (issue 35, item 5): small objects present in some training views
only, with their masks, so robust-loss methods can be scored.

`generate --transients N --transient-fraction F` adds N objects, each a sphere or a cube
(seeded choice) of a seeded random diffuse colour, to round(F * train views) training
views chosen at random (seeded, per object, independently). The rule:

- size: bounding radius TRANSIENT_SIZE x the largest side of the scene's AABB (a cube's
  half side is that / sqrt(3), so the cube fits the same sphere); yaw of a cube random;
- placement: centre uniform in the AABB shrunk by the bounding radius, accepted when no
  point of PLACEMENT_SAMPLES area-weighted samples of the static surfaces (meshes/) and
  no earlier transient lies within CLEARANCE x the bounding radius of it (so it does not
  cut the static geometry, up to the samples' spacing); PLACEMENT_TRIES draws per object,
  then one line: the scene has no free space for it;
- everything is drawn from one generator seeded (seed, 35, 5): the cameras and every
  view's render seed are those of the dataset without transients, so its val and test
  views (which never hold a transient) are byte for byte the same.

A training view renders the static scene plus the transients present in it, so its
colour, depth, normals, hit mask, instance ids and albedo are all the truth of that
image: they show the transients. `train/r_XXX_transient.png` (every training view, 8-bit,
255 where the pixel-centre ray's first hit is a transient, else 0) is read off the
instance ids, whose legend (scene.json "instances") lists the static shapes first, as
before, then the transients. meshes/ and everything scored against them hold the static
scene only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nerfgauge.core import dataset
from nerfgauge.core.errors import InputError
from nerfgauge.core.images import read_png, write_png

MAX_TRANSIENTS = 64
TRANSIENT_SIZE = 0.1  # bounding radius / the AABB's largest side
CLEARANCE = 1.1  # static surface samples stay farther than this x the bounding radius
PLACEMENT_SAMPLES = 20_000
PLACEMENT_TRIES = 500
RNG_TAG = (35, 5)  # issue 35, item 5
MASK_SUFFIX = "_transient.png"
KINDS = ("sphere", "cube")


@dataclass(frozen=True)
class Transient:
    """One transient object: kind "sphere" (radius = size) or "cube" (half side = size,
    turned `yaw` degrees about +Z), centre, linear RGB colour, the train views it is in."""

    name: str
    kind: str
    centre: tuple
    size: float
    yaw: float
    color: tuple
    views: tuple  # train frame indices, ascending

    @property
    def bounding_radius(self) -> float:
        return self.size * (math.sqrt(3) if self.kind == "cube" else 1.0)

    def to_json(self, stems) -> dict:
        return {"name": self.name, "kind": self.kind, "centre": list(self.centre), "size": self.size,
                "size_is": "radius" if self.kind == "sphere" else "half side", "yaw_degrees": self.yaw,
                "color": list(self.color), "views": [stems[i] for i in self.views]}


def check(count, fraction) -> None:
    """InputError for a count or fraction a dataset cannot use."""
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or not 0 <= count <= MAX_TRANSIENTS:
        raise InputError(f"--transients must be an integer from 0 to {MAX_TRANSIENTS}, got {count!r}")
    if (isinstance(fraction, bool) or not isinstance(fraction, (int, float, np.number)) or not math.isfinite(fraction)
            or not 0 < fraction <= 1):
        raise InputError(f"--transient-fraction must be in (0, 1], got {fraction!r}")


def surface_samples(scene, n: int, rng: np.random.Generator) -> np.ndarray:
    """n points [n, 3] area-uniform on the static shapes' ground-truth meshes."""
    triangles = [mesh.vertices[mesh.faces] for mesh in (shape.mesh() for shape in scene.shapes) if len(mesh.faces)]
    if not triangles:
        return np.zeros((0, 3))
    tri = np.concatenate(triangles)  # [F, 3, 3]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(tri), size=n, p=area / area.sum())
    u, v = rng.uniform(size=(2, n))
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    t = tri[pick]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def place(scene, count: int, fraction: float, n_train: int, seed: int) -> tuple:
    """The transients of a dataset (module docstring), a tuple of Transient."""
    check(count, fraction)
    if count == 0:
        return ()
    if n_train == 0:
        raise InputError("--transients needs training views to appear in (--views is 0)")
    rng = np.random.default_rng([int(seed), *RNG_TAG])
    aabb = np.asarray(scene.aabb, np.float64)
    radius = TRANSIENT_SIZE * float((aabb[1] - aabb[0]).max())
    obstacles = surface_samples(scene, PLACEMENT_SAMPLES, rng)  # [n, 3]
    placed, shown = [], max(1, round(fraction * n_train))
    for k in range(count):
        kind = KINDS[int(rng.integers(len(KINDS)))]
        size = radius / math.sqrt(3) if kind == "cube" else radius
        for _ in range(PLACEMENT_TRIES):
            centre = rng.uniform(aabb[0] + radius, np.maximum(aabb[1] - radius, aabb[0] + radius))
            near = np.linalg.norm(obstacles - centre, axis=1).min(initial=np.inf)
            apart = all(np.linalg.norm(centre - np.array(p.centre)) > CLEARANCE * (radius + p.bounding_radius)
                        for p in placed)
            if near > CLEARANCE * radius and apart:
                break
        else:
            raise InputError(f"--transients {count}: found no free place for transient {k} in the scene's bounds "
                             f"after {PLACEMENT_TRIES} tries (each needs a ball of radius {CLEARANCE * radius:.3g} "
                             f"clear of the scene); ask for fewer")
        color = tuple(float(c) for c in rng.uniform(0.1, 0.9, 3))
        yaw = float(rng.uniform(0, 90)) if kind == "cube" else 0.0
        views = tuple(sorted(int(i) for i in rng.choice(n_train, size=shown, replace=False)))
        placed.append(Transient(f"transient_{k}", kind, tuple(float(c) for c in centre), float(size), yaw, color,
                                views))
    return tuple(placed)


def present(transients, split: str, index: int) -> tuple:
    """Names of the transients in frame `index` of `split` (none outside train)."""
    return tuple(t.name for t in transients if split == "train" and index in t.views)


def names(transients) -> list:
    """The legend entries after the static shapes' (scene.json "instances")."""
    return [t.name for t in transients]


def shape_dict(mi, transient: Transient) -> dict:
    bsdf = {"type": "twosided", "bsdf": {"type": "diffuse",
                                         "reflectance": {"type": "rgb", "value": list(transient.color)}}}
    if transient.kind == "sphere":
        return {"type": "sphere", "center": list(transient.centre), "radius": transient.size, "bsdf": bsdf}
    c, s = math.cos(math.radians(transient.yaw)), math.sin(math.radians(transient.yaw))
    to_world = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]) @ np.diag([transient.size] * 3 + [1.0])
    to_world[:3, 3] = transient.centre
    return {"type": "cube", "to_world": mi.ScalarTransform4f(to_world.tolist()), "bsdf": bsdf}


_SCENES = {}  # per process: {names present: (Mitsuba scene, aov integrator, legend)} of the last static scene


def scene_for_view(mi, scene, out: Path, the_plan, split: str, index: int) -> tuple:
    """(Mitsuba scene, integrator, legend) to render frame `index` of `split` with: the
    static `scene` and (None, None) (render_view's own) when no transient is in the view,
    else the static scene plus those transients, loaded once per process and set, with the
    legend of the static shapes followed by every transient (ids stable across views)."""
    shown = present(the_plan.transients, split, index)
    if not shown:
        return scene, None, None
    from nerfgauge.generate.mitsuba_scene import scene_dict  # mitsuba: loaded by the caller already
    from nerfgauge.generate.render import aov_integrator, instance_legend  # as above

    if _SCENES.get("static") is not scene:
        _SCENES.clear()
        _SCENES["static"] = scene
    if shown not in _SCENES:
        mesh_paths = {path.stem: path for path in (Path(out) / "meshes").glob("*.ply")}
        entries = scene_dict(mi, the_plan.scene, mesh_paths, the_plan.config.max_depth)
        for transient in the_plan.transients:
            if transient.name in shown:
                entries[transient.name] = shape_dict(mi, transient)
        loaded = mi.load_dict(entries, optimize=False)
        legend = instance_legend(scene) + tuple(names(the_plan.transients))
        _SCENES[shown] = (loaded, aov_integrator(mi), legend)
    return _SCENES[shown]


def mask_path(out: Path, stem: str) -> Path:
    return Path(out) / f"{stem}{MASK_SUFFIX}"


def write_masks(out: Path, the_plan, static_count: int) -> None:
    """Every training view's transient mask from its instance ids (ids above the static
    shapes' are transients): 255 where the pixel-centre ray's first hit is a transient."""
    if not the_plan.transients:
        return
    for stem in the_plan.stems["train"]:
        ids = np.rint(read_png(out / dataset.frame_files(stem)["instance"]).astype(np.float64) * 65535.0)
        write_png(mask_path(out, stem), np.where(ids > static_count, 255, 0).astype(np.uint8))


def record(the_plan) -> dict:
    """scene.json's "transients" (present only when the dataset has some)."""
    stems = the_plan.stems["train"]
    config = the_plan.config
    return {"count": config.transients, "fraction": config.transient_fraction,
            "objects": [t.to_json(stems) for t in the_plan.transients],
            "mask": f"train/r_XXX{MASK_SUFFIX}: 255 where the pixel-centre ray's first hit is a transient, else 0 "
                    "(every training view; val and test views hold no transient)",
            "truth": "training views' colour, depth, normals, hit mask, instance ids and albedo show the transients "
                     "as rendered; meshes/ hold the static scene only",
            "rule": __doc__.split("The rule:")[1].split("A training view")[0].strip()}
