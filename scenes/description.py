"""A scene as plain data: shapes, materials, lights, bounds and what it needs modelled.

Nothing here knows a renderer. `generate/` turns a `Scene` into Mitsuba objects; `nerf/`
reads `needs` (through the dataset's scene.json) to decide what to model.

World convention: right-handed, +Z up, scene units. Angles in degrees.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Optional, Union

import numpy as np
from nerfgauge.scenes import meshes

from nerfgauge.core import validate

Vec3 = tuple[float, float, float]

BACKGROUNDS = ("transparent", "environment")


# --- materials ------------------------------------------------------------------------


@dataclass(frozen=True)
class Diffuse:
    """Lambertian, constant albedo (linear RGB)."""

    color: Vec3
    view_dependent = False


@dataclass(frozen=True)
class Textured:
    """Lambertian whose albedo is a repeating tile, `period` scene units across.

    pattern: "checker" (2x2 tile), "stripes" (1x2 tile) or "noise" (8x8 tile of a seeded
    blend of the two colours). Looked up with nearest filtering, so edges stay sharp.
    """

    pattern: str
    color0: Vec3
    color1: Vec3
    period: float
    seed: int = 0
    view_dependent = False

    def tile(self) -> np.ndarray:
        """The repeating tile as linear RGB. Returns [rows, cols, 3] float32."""
        c0, c1 = np.asarray(self.color0, np.float32), np.asarray(self.color1, np.float32)
        if self.pattern == "checker":
            mask = np.array([[0, 1], [1, 0]], np.float32)
        elif self.pattern == "stripes":
            mask = np.array([[0, 1]], np.float32)
        elif self.pattern == "noise":
            mask = np.random.default_rng(self.seed).random((8, 8)).astype(np.float32)
        else:
            raise ValueError(f"unknown texture pattern {self.pattern!r}")
        return c0 * (1 - mask[..., None]) + c1 * mask[..., None]

    @property
    def finest_period(self) -> float:
        """Smallest repeating detail in scene units (one tile cell)."""
        rows, cols, _ = self.tile().shape
        return self.period / max(rows, cols)


@dataclass(frozen=True)
class RoughPlastic:
    """Diffuse base under a GGX-rough dielectric coat: highlights move with the view."""

    color: Vec3
    roughness: float = 0.1
    view_dependent = True


@dataclass(frozen=True)
class Conductor:
    """Metal (Mitsuba's named conductors: "Au", "Cu", "Al", ...). roughness 0 is a mirror."""

    metal: str = "Au"
    roughness: float = 0.15
    view_dependent = True


@dataclass(frozen=True)
class Dielectric:
    """Smooth glass: depth is ambiguous (the surface or what is seen through it)."""

    ior: float = 1.5
    view_dependent = True


Material = Union[Diffuse, Textured, RoughPlastic, Conductor, Dielectric]


# --- shapes ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Sphere:
    """Analytic sphere (rendered exactly; its ground-truth mesh is an icosphere)."""

    name: str
    center: Vec3
    radius: float
    material: Material
    emission: Optional[Vec3] = None

    def mesh(self) -> meshes.MeshData:
        return meshes.icosphere(self.center, self.radius)

    def uv_extent(self) -> tuple[float, float]:
        """Scene units spanned by one unit of u and of v (Mitsuba's sphere uv)."""
        return (2 * math.pi * self.radius, math.pi * self.radius)


class _PosedMesh:
    """Shapes built as a local mesh, rotated then moved to `center`; uv in scene units."""

    def mesh(self) -> meshes.MeshData:
        return self.local_mesh().transformed(meshes.pose(self.center, self.rotation))

    def uv_extent(self) -> tuple[float, float]:
        return (1.0, 1.0)


@dataclass(frozen=True)
class Box(_PosedMesh):
    name: str
    center: Vec3
    size: Vec3
    material: Material
    rotation: Vec3 = (0.0, 0.0, 0.0)
    emission: Optional[Vec3] = None

    def local_mesh(self) -> meshes.MeshData:
        return meshes.box(self.size)


@dataclass(frozen=True)
class Cylinder(_PosedMesh):
    """Capped cylinder of `height` along its local +Z, centred on `center`."""

    name: str
    center: Vec3
    radius: float
    height: float
    material: Material
    rotation: Vec3 = (0.0, 0.0, 0.0)
    emission: Optional[Vec3] = None

    def local_mesh(self) -> meshes.MeshData:
        return meshes.capped_cylinder(self.radius, self.height)


@dataclass(frozen=True)
class Torus(_PosedMesh):
    """Torus around its local +Z axis: ring radius `major`, tube radius `minor`."""

    name: str
    center: Vec3
    major: float
    minor: float
    material: Material
    rotation: Vec3 = (0.0, 0.0, 0.0)
    emission: Optional[Vec3] = None

    def local_mesh(self) -> meshes.MeshData:
        return meshes.torus(self.major, self.minor)


@dataclass(frozen=True)
class TriangleMesh:
    """A triangle mesh already in world coordinates (e.g. a user's file, scaled)."""

    name: str
    data: meshes.MeshData = field(repr=False)
    material: Material = Diffuse((0.6, 0.6, 0.6))
    source: str = ""
    emission: Optional[Vec3] = None

    def mesh(self) -> meshes.MeshData:
        return self.data

    def uv_extent(self) -> tuple[float, float]:
        return (1.0, 1.0)


Shape = Union[Sphere, Box, Cylinder, Torus, TriangleMesh]


# --- lights ---------------------------------------------------------------------------


@dataclass(frozen=True)
class ConstantEnvironment:
    radiance: Vec3


@dataclass(frozen=True)
class GradientEnvironment:
    """Sky that blends zenith -> horizon -> nadir with elevation (smooth, low noise),
    with an optional sun: a disc of `sun_radiance` within `sun_angle` degrees of
    `sun_direction`, which gives glossy materials a sharp highlight."""

    zenith: Vec3
    horizon: Vec3
    nadir: Vec3
    sun_direction: Optional[Vec3] = None
    sun_radiance: Vec3 = (0.0, 0.0, 0.0)
    sun_angle: float = 3.0

    def radiance(self, directions: np.ndarray) -> np.ndarray:
        """Radiance arriving from unit world `directions` [..., 3]. Returns [..., 3] float32."""
        d = np.asarray(directions, np.float64)
        up = np.clip(d[..., 2:3], 0, 1)
        down = np.clip(-d[..., 2:3], 0, 1)
        z, h, n = (np.asarray(c, np.float64) for c in (self.zenith, self.horizon, self.nadir))
        out = h * (1 - up - down) + z * up + n * down
        if self.sun_direction is not None:
            sun = np.asarray(self.sun_direction, np.float64)
            sun = sun / np.linalg.norm(sun)
            in_disc = (d @ sun) >= math.cos(math.radians(self.sun_angle))
            out = np.where(in_disc[..., None], np.asarray(self.sun_radiance, np.float64), out)
        return out.astype(np.float32)


@dataclass(frozen=True)
class PointLight:
    position: Vec3
    intensity: Vec3


@dataclass(frozen=True)
class RectangleLight:
    """One-sided emitting rectangle at `center`, facing along `normal`."""

    center: Vec3
    size: tuple[float, float]
    normal: Vec3
    radiance: Vec3


Light = Union[ConstantEnvironment, GradientEnvironment, PointLight, RectangleLight]


# --- the scene ------------------------------------------------------------------------


@dataclass(frozen=True)
class CameraHint:
    """Where a scene wants its cameras when the user leaves `--layout auto`.

    A plain suggestion in scene units; `generate/` owns the layouts and reads it.
    layout: a layout name ("hemisphere", "forward", "inside", ...). radius: camera distance
    from the AABB centre (None: fit the AABB in view). elevation: (min, max) degrees.
    eye, target: for "forward", the centre of the camera cluster and the point every
    camera faces. spread: for "forward", the cluster's radius; for "inside", the half-size
    of the box around the AABB centre the cameras stand in.
    """

    layout: str
    radius: Optional[float] = None
    elevation: Optional[tuple] = None
    eye: Optional[Vec3] = None
    target: Optional[Vec3] = None
    spread: Optional[float] = None


@dataclass(frozen=True)
class Needs:
    """What a radiance field must model for this scene.

    view_dependent: some material's appearance changes with the view direction.
    background: "transparent" (alpha = coverage) or "environment" (visible sky).
    finest_texture_period: smallest texture detail in scene units, None if untextured.
    """

    view_dependent: bool
    background: str
    finest_texture_period: Optional[float]


@dataclass(frozen=True)
class Scene:
    name: str
    seed: int
    shapes: tuple
    lights: tuple
    aabb_min: Vec3
    aabb_max: Vec3
    needs: Needs
    params: dict = field(default_factory=dict)
    cameras: Optional[CameraHint] = None

    @property
    def aabb(self) -> np.ndarray:
        """[2, 3]: min and max corner."""
        return np.array([self.aabb_min, self.aabb_max], dtype=np.float64)

    def to_json(self) -> dict:
        """A JSON-able description (meshes summarised, not inlined)."""
        return {
            "name": self.name,
            "seed": self.seed,
            "params": self.params,
            "aabb": [list(self.aabb_min), list(self.aabb_max)],
            "needs": asdict(self.needs),
            "shapes": [_shape_json(s) for s in self.shapes],
            "lights": [{"type": type(l).__name__, **asdict(l)} for l in self.lights],
            "cameras": None if self.cameras is None else asdict(self.cameras),
        }


def _shape_json(shape) -> dict:
    out = {"type": type(shape).__name__}
    for f in fields(shape):
        value = getattr(shape, f.name)
        if f.name == "data":
            out["vertices"], out["faces"] = len(value.vertices), len(value.faces)
        elif f.name == "material":
            out["material"] = {"type": type(value).__name__, **asdict(value)}
        else:
            out[f.name] = value
    return out


def check_emitters(name, shapes, lights) -> None:
    """Every radiance a scene emits (lights, emissive shapes) below validate.MAX_RADIANCE,
    checked as the scene is built, before anything is rendered (InputError otherwise)."""
    for light in lights:
        for key in ("radiance", "intensity", "zenith", "horizon", "nadir", "sun_radiance"):
            value = getattr(light, key, None)
            if value is not None and not callable(value):
                validate.radiance(value, f"scene {name}: {type(light).__name__} {key}")
    for shape in shapes:
        if getattr(shape, "emission", None) is not None:
            validate.radiance(shape.emission, f"scene {name}: shape {shape.name} emission")


def build_scene(name, seed, shapes, lights, *, background="transparent", aabb=None,
                params=None, padding=0.05, cameras: Optional[CameraHint] = None) -> Scene:
    """Assemble a Scene, deriving `needs` from the materials and the AABB from the shapes.

    aabb: optional ((xmin, ymin, zmin), (xmax, ymax, zmax)); by default the shapes'
    bounds grown by `padding` times the largest extent on every side.
    """
    if background not in BACKGROUNDS:
        raise ValueError(f"background must be one of {BACKGROUNDS}, got {background!r}")
    names = [s.name for s in shapes]
    if len(set(names)) != len(names):
        raise ValueError(f"shape names must be unique, got {names}")
    if aabb is None:
        if not shapes:
            raise ValueError("a scene without shapes needs an explicit aabb")
        corners = np.concatenate([s.mesh().bounds() for s in shapes])
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        pad = padding * float((hi - lo).max())
        aabb = (lo - pad, hi + pad)
    check_emitters(name, shapes, lights)
    lo, hi = (tuple(float(x) for x in corner) for corner in aabb)
    periods = [s.material.finest_period for s in shapes if isinstance(s.material, Textured)]
    needs = Needs(
        view_dependent=any(s.material.view_dependent for s in shapes),
        background=background,
        finest_texture_period=min(periods) if periods else None,
    )
    return Scene(name, int(seed), tuple(shapes), tuple(lights), lo, hi, needs, dict(params or {}), cameras)
