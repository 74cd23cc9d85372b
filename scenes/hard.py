"""Hard cases: scenes built to sit where NeRFs and harnesses fail.

Each recipe isolates one difficulty; the figures quoted in docstrings assume the
defaults (128x128 views, 40-degree field of view, the layout the scene suggests). At the
hemisphere's default radius a pixel spans about 0.03 scene units at the AABB centre.
Layouts are fixed (a hard case must not move with the seed); the seed seeds the renderer.
"""

from __future__ import annotations

import math

from nerfgauge.scenes.description import (
    Box,
    CameraHint,
    Conductor,
    Cylinder,
    Dielectric,
    Diffuse,
    GradientEnvironment,
    PointLight,
    RectangleLight,
    RoughPlastic,
    Sphere,
    Textured,
    Torus,
    build_scene,
)
from nerfgauge.scenes.library import SOFT_SKY

SUNNY_SKY = GradientEnvironment(SOFT_SKY.zenith, SOFT_SKY.horizon, SOFT_SKY.nadir,
                                sun_direction=(0.4, -0.3, 1.0), sun_radiance=(100.0, 100.0, 95.0))
FLOOR_CHECKER = Textured("checker", (0.85, 0.85, 0.85), (0.25, 0.25, 0.3), period=0.5)


def _floor(size: float = 2.4, material=FLOOR_CHECKER) -> Box:
    """A thin plate under the objects: gives reflections and refractions something to show."""
    return Box("floor", (0.0, 0.0, -0.025), (size, size, 0.05), material)


def thin(seed: int):
    """Wires 0.012 across (a third to a half of a pixel) and plates 0.008 thick, which
    vanish edge-on: coverage is fractional and most pixel-centre rays miss them."""
    wire, plate = 0.006, 0.008
    shapes = [
        Cylinder("wire_upright", (-0.6, 0.0, 0.6), wire, 1.2, Diffuse((0.9, 0.2, 0.1))),
        Cylinder("wire_tilted", (0.0, -0.3, 0.6), wire, 1.4, Diffuse((0.1, 0.3, 0.9)), rotation=(0, 50, 30)),
        Cylinder("wire_level", (0.0, 0.5, 0.3), wire, 1.6, Diffuse((0.1, 0.7, 0.2)), rotation=(0, 90, 0)),
        Torus("wire_ring", (0.55, 0.0, 0.6), 0.35, wire, Diffuse((0.9, 0.8, 0.1)), rotation=(70, 0, 20)),
        Box("plate_upright", (0.3, 0.6, 0.45), (0.8, plate, 0.9), Diffuse((0.8, 0.8, 0.8)), rotation=(0, 0, 15)),
        Box("plate_tilted", (-0.45, -0.55, 0.35), (0.7, 0.6, plate), Diffuse((0.7, 0.3, 0.7)), rotation=(35, 0, 0)),
    ]
    return build_scene("thin", seed, shapes, [SOFT_SKY])


def checker_fine(seed: int):
    """Checks of 0.03 and stripes of 0.035 scene units: one to two pixels at the nearest
    views, at the Nyquist limit of the images (aliasing if sampled once per pixel)."""
    fine = Textured("checker", (0.9, 0.9, 0.9), (0.05, 0.05, 0.05), period=0.06)
    stripes = Textured("stripes", (0.9, 0.3, 0.1), (0.1, 0.2, 0.6), period=0.07)
    shapes = [
        _floor(2.0, fine),
        Box("striped_box", (0.4, 0.3, 0.3), (0.6, 0.6, 0.6), stripes, rotation=(0, 0, 30)),
        Cylinder("checker_cylinder", (-0.45, -0.35, 0.4), 0.3, 0.8, fine),
    ]
    return build_scene("checker-fine", seed, shapes, [SOFT_SKY])


def mirror(seed: int):
    """A perfect aluminium mirror sphere and low-roughness (0.02) plastic beside diffuse,
    checkered neighbours under a sky with a sun: reflections move with every view."""
    shapes = [
        _floor(),
        Sphere("mirror_sphere", (-0.4, 0.3, 0.45), 0.45, Conductor("Al", roughness=0.0)),
        Box("gloss_box", (0.5, -0.3, 0.3), (0.6, 0.6, 0.6), RoughPlastic((0.1, 0.2, 0.7), roughness=0.02),
            rotation=(0, 0, 20)),
        Sphere("gloss_sphere", (0.5, 0.6, 0.25), 0.25, RoughPlastic((0.8, 0.1, 0.1), roughness=0.02)),
        Cylinder("matte_cylinder", (-0.5, -0.6, 0.3), 0.2, 0.6, Diffuse((0.1, 0.7, 0.2))),
    ]
    return build_scene("mirror", seed, shapes, [SUNNY_SKY])


def depth_range(seed: int):
    """A forward-facing capture (cameras within 0.02 of the origin, all facing +Y) of a
    pebble whose nearest point is 0.2 away and a boulder 50 away: near/far ratio 250.

    The AABB starts just in front of the cameras and reaches past the boulder, so a grid
    over it spends most of its cells on empty space and has cells far coarser than the
    pebble: this is where uniform grids fail.
    """
    shapes = [
        Sphere("pebble", (-0.06, 0.235, -0.02), 0.035, Diffuse((0.9, 0.5, 0.1))),
        Box("crate", (0.6, 3.0, -0.3), (0.5, 0.5, 0.5), Diffuse((0.2, 0.4, 0.8)), rotation=(0, 0, 30)),
        Sphere("boulder", (6.0, 58.0, 0.0), 8.0, Textured("checker", (0.8, 0.8, 0.75), (0.3, 0.3, 0.3), period=4.0)),
    ]
    cameras = CameraHint("forward", eye=(0.0, 0.0, 0.0), target=(0.0, 1.0, 0.0), spread=0.02)
    return build_scene("depth-range", seed, shapes, [SOFT_SKY], aabb=((-3.0, 0.15, -9.0), (15.0, 67.0, 9.0)),
                       cameras=cameras, params={"near": 0.2, "far": 50.0})


def hdr(seed: int):
    """An emitting sphere (radiance 40), a visible rectangle light (25) and their sharp
    highlights on glossy plastic: linear values far above 1 that the 8-bit PNGs clip.
    No sky, so the emitters can be seen directly while misses stay transparent."""
    shapes = [
        _floor(2.4, Diffuse((0.5, 0.5, 0.5))),
        Sphere("lamp", (0.0, 0.0, 0.75), 0.12, Diffuse((0.0, 0.0, 0.0)), emission=(40.0, 36.0, 30.0)),
        Sphere("gloss_red", (-0.55, 0.45, 0.3), 0.3, RoughPlastic((0.7, 0.1, 0.1), roughness=0.05)),
        Sphere("gloss_blue", (0.55, -0.45, 0.3), 0.3, RoughPlastic((0.1, 0.2, 0.8), roughness=0.05)),
        Box("matte_box", (0.5, 0.5, 0.25), (0.4, 0.4, 0.5), Diffuse((0.8, 0.8, 0.8))),
    ]
    lights = [RectangleLight((-0.6, -0.6, 0.9), (0.5, 0.3), (0.5, 0.5, -0.3), (25.0, 25.0, 25.0)),
              PointLight((1.5, -1.5, 2.5), (6.0, 6.0, 6.0))]
    return build_scene("hdr", seed, shapes, lights)


def glass(seed: int):
    """Smooth glass (IOR 1.5) sphere and block over a checker floor: the surface depth is
    exact but the colour comes from what lies behind or is reflected."""
    shapes = [
        _floor(),
        Sphere("glass_sphere", (-0.35, 0.2, 0.45), 0.45, Dielectric(1.5)),
        Box("glass_block", (0.55, -0.35, 0.3), (0.4, 0.4, 0.6), Dielectric(1.5), rotation=(0, 0, 25)),
        Box("red_block", (0.5, 0.6, 0.2), (0.3, 0.3, 0.4), Diffuse((0.8, 0.1, 0.1))),
    ]
    return build_scene("glass", seed, shapes, [SUNNY_SKY])


def empty(seed: int):
    """Nothing but the (hidden) sky: every pixel is a miss. Depth metrics have no pixels
    to score, the mask is empty, and a NeRF must learn zero density everywhere."""
    return build_scene("empty", seed, [], [SOFT_SKY], aabb=((-1.0, -1.0, 0.0), (1.0, 1.0, 1.0)))


def tiny(seed: int):
    """One sphere 0.08 across in a 2x2x1 AABB: 2-3 pixels across, a handful of pixels in
    each view; the mean over a view is nearly all background."""
    shapes = [Sphere("speck", (0.1, -0.05, 0.4), 0.04, Diffuse((0.9, 0.2, 0.1)))]
    return build_scene("tiny", seed, shapes, [SOFT_SKY], aabb=((-1.0, -1.0, 0.0), (1.0, 1.0, 1.0)))


def inside(seed: int):
    """A ring of eight objects on a checker floor, photographed from within the ring:
    cameras stand inside the AABB (layout "inside") and look outwards, so rays start
    inside the grid and see content at every distance from 0.6 to 2.5."""
    shapes = [_floor(4.4)]
    kinds = [(Box, Diffuse((0.8, 0.2, 0.1))), (Cylinder, Diffuse((0.1, 0.6, 0.2))),
             (Sphere, Textured("stripes", (0.9, 0.9, 0.2), (0.2, 0.2, 0.8), period=0.3)),
             (Box, Textured("checker", (0.9, 0.9, 0.9), (0.2, 0.1, 0.1), period=0.4))]
    for index in range(8):
        angle = 2 * math.pi * index / 8
        centre = (1.6 * math.cos(angle), 1.6 * math.sin(angle), 0.35)
        shape, material = kinds[index % 4]
        name = f"{shape.__name__.lower()}_{index}"
        if shape is Box:
            shapes.append(Box(name, centre, (0.5, 0.5, 0.7), material, rotation=(0, 0, math.degrees(angle))))
        elif shape is Cylinder:
            shapes.append(Cylinder(name, centre, 0.25, 0.7, material))
        else:
            shapes.append(Sphere(name, centre, 0.35, material))
    cameras = CameraHint("inside", elevation=(-20.0, 10.0), spread=0.3)
    return build_scene("inside", seed, shapes, [SOFT_SKY], cameras=cameras)


def far_reaching(seed: int):
    """Objects about 1 across at the centre, seen by orbit cameras 3.2 away, in a textured
    world that reaches 50-100 times further: a checker ground 200 wide (to the horizon
    at this elevation) and striped and checked hills 55-95 away all around. Every camera
    stands inside the AABB and every ray that is not skyward ends on far content: a grid
    over the AABB has metre-sized cells at the objects; a contracted grid does not."""
    shapes = [
        Box("ground", (0.0, 0.0, -0.05), (200.0, 200.0, 0.1), Textured("checker", (0.75, 0.7, 0.6),
                                                                        (0.35, 0.4, 0.3), period=1.0)),
        Sphere("ball", (-0.45, 0.25, 0.35), 0.35, Diffuse((0.85, 0.25, 0.1))),
        Box("crate", (0.4, -0.3, 0.3), (0.5, 0.5, 0.6), Textured("stripes", (0.9, 0.9, 0.3), (0.2, 0.3, 0.7),
                                                                  period=0.15), rotation=(0, 0, 20)),
        Cylinder("post", (0.35, 0.55, 0.4), 0.15, 0.8, Diffuse((0.2, 0.7, 0.3))),
    ]
    hill_materials = [Textured("stripes", (0.3, 0.55, 0.25), (0.55, 0.45, 0.3), period=6.0),
                      Textured("checker", (0.6, 0.6, 0.65), (0.3, 0.3, 0.4), period=8.0)]
    for index in range(8):
        angle = 2 * math.pi * (index + 0.3) / 8
        distance = 55.0 + 40.0 * ((index * 5) % 8) / 7
        shapes.append(Sphere(f"hill_{index}", (distance * math.cos(angle), distance * math.sin(angle), -6.0),
                             14.0 + 2.0 * (index % 3), hill_materials[index % 2]))
    cameras = CameraHint("orbit", radius=3.2, elevation=(12.0, 12.0), target=(0.0, 0.0, 0.35))
    return build_scene("far-reaching", seed, shapes, [SOFT_SKY], aabb=((-100.0, -100.0, -1.0), (100.0, 100.0, 30.0)),
                       cameras=cameras)


# name -> (recipe, one-line description), listed by `nerfgauge scenes`
HARD_RECIPES = {
    "thin": (thin, "hard: wires and plates thinner than a pixel at some views"),
    "checker-fine": (checker_fine, "hard: checks and stripes at the images' Nyquist limit"),
    "mirror": (mirror, "hard: a perfect mirror sphere and 0.02-rough plastic (strong view dependence)"),
    "depth-range": (depth_range, "hard: forward-facing, a pebble 0.2 away and a boulder 50 away (ratio 250)"),
    "hdr": (hdr, "hard: visible emitters and highlights far above 1 (no sky)"),
    "glass": (glass, "hard: smooth glass sphere and block (depth ambiguous)"),
    "empty": (empty, "hard: nothing but background (no hit pixels)"),
    "tiny": (tiny, "hard: one sphere a few pixels across"),
    "far-reaching": (far_reaching, "hard: orbit cameras around objects in a textured world 50-100x their size"),
    "inside": (inside, "hard: cameras inside the AABB looking out at a ring of objects"),
}
