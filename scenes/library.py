"""The built-in procedural scenes. Each recipe is a pure function of an explicit seed."""

from __future__ import annotations

import numpy as np
from nerfgauge.scenes.description import (
    Box,
    Conductor,
    Cylinder,
    Diffuse,
    GradientEnvironment,
    PointLight,
    RoughPlastic,
    Sphere,
    Textured,
    Torus,
    build_scene,
)

# A soft sky: bright zenith, neutral horizon, dark ground bounce. Smooth light keeps Monte
# Carlo noise low, so the ground truth is not limited by render noise.
SOFT_SKY = GradientEnvironment(zenith=(1.0, 1.0, 1.05), horizon=(0.75, 0.75, 0.75), nadir=(0.25, 0.25, 0.25))


def primitives(seed: int):
    """Four diffuse objects: red sphere, blue box, green capped cylinder, checker sphere.

    The layout is fixed (the default scene must not move with the seed); the seed is
    recorded and only seeds the renderer.
    """
    shapes = [
        Sphere("red_sphere", (-0.55, 0.5, 0.4), 0.4, Diffuse((0.8, 0.1, 0.1))),
        Box("blue_box", (0.55, 0.5, 0.3), (0.6, 0.6, 0.6), Diffuse((0.1, 0.2, 0.8)), rotation=(0, 0, 25)),
        Cylinder("green_cylinder", (0.55, -0.5, 0.4), 0.3, 0.8, Diffuse((0.1, 0.65, 0.15))),
        Sphere("checker_sphere", (-0.55, -0.5, 0.4), 0.4,
               Textured("checker", (0.9, 0.9, 0.9), (0.1, 0.1, 0.1), period=0.5)),
    ]
    return build_scene("primitives", seed, shapes, [SOFT_SKY])


def glossy(seed: int):
    """View-dependent materials: rough plastic sphere and box, rough gold torus, a
    near-mirror aluminium sphere, under a sky with a sun and a point light."""
    shapes = [
        Sphere("plastic_sphere", (-0.55, 0.5, 0.4), 0.4, RoughPlastic((0.7, 0.1, 0.1), roughness=0.08)),
        Torus("gold_torus", (0.55, 0.5, 0.25), 0.3, 0.12, Conductor("Au", roughness=0.15), rotation=(60, 0, 0)),
        Box("plastic_box", (0.55, -0.5, 0.3), (0.5, 0.5, 0.6), RoughPlastic((0.1, 0.3, 0.8), roughness=0.15),
            rotation=(0, 0, -20)),
        Sphere("steel_sphere", (-0.55, -0.5, 0.4), 0.4, Conductor("Al", roughness=0.05)),
    ]
    sky_with_sun = GradientEnvironment(SOFT_SKY.zenith, SOFT_SKY.horizon, SOFT_SKY.nadir,
                                       sun_direction=(0.4, -0.3, 1.0), sun_radiance=(100.0, 100.0, 95.0))
    lights = [sky_with_sun, PointLight((2.0, -2.0, 3.0), (4.0, 4.0, 4.0))]
    return build_scene("glossy", seed, shapes, lights)


def random_objects(seed: int, count: int | None = None):
    """3-6 objects (shape, material, size and pose drawn from the seed) on a 3x3 grid."""
    rng = np.random.default_rng(seed)
    count = int(rng.integers(3, 7)) if count is None else count
    cells = rng.permutation(9)[:count]
    shapes = []
    for index, cell in enumerate(cells):
        x, y = (cell % 3 - 1) * 0.7, (cell // 3 - 1) * 0.7
        size = float(rng.uniform(0.18, 0.3))
        color = tuple(float(c) for c in rng.uniform(0.1, 0.9, 3))
        material = _random_material(rng, color, size)
        kind = rng.choice(["sphere", "box", "cylinder", "torus"])
        rotation = (float(rng.uniform(0, 90)), 0.0, float(rng.uniform(0, 360)))
        name = f"{kind}_{index}"
        if kind == "sphere":
            shapes.append(Sphere(name, (x, y, size), size, material))
        elif kind == "box":
            shapes.append(Box(name, (x, y, size), (size * 1.6,) * 3, material, rotation=(0, 0, rotation[2])))
        elif kind == "cylinder":
            shapes.append(Cylinder(name, (x, y, size), size * 0.8, size * 2, material, rotation=rotation))
        else:
            shapes.append(Torus(name, (x, y, size), size, size * 0.35, material, rotation=rotation))
    return build_scene("random", seed, shapes, [SOFT_SKY], params={"count": count})


def _random_material(rng, color, size):
    kind = rng.choice(["diffuse", "diffuse", "textured", "plastic", "conductor"])
    if kind == "textured":
        pattern = str(rng.choice(["checker", "stripes", "noise"]))
        return Textured(pattern, color, (0.95, 0.95, 0.95), period=size, seed=int(rng.integers(2**31)))
    if kind == "plastic":
        return RoughPlastic(color, roughness=float(rng.uniform(0.05, 0.3)))
    if kind == "conductor":
        return Conductor(str(rng.choice(["Au", "Cu", "Al"])), roughness=float(rng.uniform(0.05, 0.3)))
    return Diffuse(color)
