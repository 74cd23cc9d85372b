"""Scenes for checking rules, not for tuning them: captures nobody tuned the automatic
choices on (issue 34). They are NOT in `nerfgauge bench hard` and no setting was chosen by
measuring on them; they exist so a rule (which parametrisation, what resolution) can be
checked on a capture it was not fitted to (tests/test_parametrisation.py, BENCHMARKS.md
"Parametrisation by what the capture is").

Layouts are fixed (the seed seeds the renderer only), as in scenes/hard.py.
"""

from __future__ import annotations

from nerfgauge.scenes.description import (
    Box,
    CameraHint,
    Cylinder,
    Diffuse,
    PointLight,
    RectangleLight,
    Sphere,
    Textured,
    Torus,
    build_scene,
)
from nerfgauge.scenes.library import SOFT_SKY

ROOM_HALF = 4.0  # the room is 8 x 8 x 3: its walls reach 10x beyond the cameras' cluster
ROOM_HEIGHT = 3.0
WALL = 0.1


def room(seed: int):
    """A closed room (8 x 8 x 3, floor, ceiling and four walls, each textured differently,
    and five pieces of furniture), lit by two lamps inside it, photographed from within:
    cameras stand in a 0.4-wide cluster at the room's centre and look outwards (layout
    "inside"). No ray leaves the room: every pixel of every view is opaque, and all
    content lies within the box at 0.5 to 5.7 from the cameras."""
    h, z = ROOM_HALF, ROOM_HEIGHT
    shapes = [
        Box("floor", (0.0, 0.0, -WALL / 2), (2 * h, 2 * h, WALL),
            Textured("checker", (0.8, 0.75, 0.65), (0.35, 0.3, 0.25), period=0.8)),
        Box("ceiling", (0.0, 0.0, z + WALL / 2), (2 * h, 2 * h, WALL), Diffuse((0.85, 0.85, 0.85))),
        Box("wall_north", (0.0, h + WALL / 2, z / 2), (2 * h + 2 * WALL, WALL, z),
            Textured("stripes", (0.8, 0.3, 0.2), (0.9, 0.85, 0.7), period=0.6)),
        Box("wall_south", (0.0, -h - WALL / 2, z / 2), (2 * h + 2 * WALL, WALL, z),
            Textured("checker", (0.2, 0.4, 0.8), (0.9, 0.9, 0.9), period=0.7)),
        Box("wall_east", (h + WALL / 2, 0.0, z / 2), (WALL, 2 * h, z),
            Textured("stripes", (0.2, 0.6, 0.3), (0.85, 0.85, 0.6), period=0.5)),
        Box("wall_west", (-h - WALL / 2, 0.0, z / 2), (WALL, 2 * h, z), Diffuse((0.7, 0.6, 0.3))),
        Box("table", (1.6, 1.2, 0.4), (1.2, 0.7, 0.8), Diffuse((0.5, 0.3, 0.15)), rotation=(0, 0, 15)),
        Sphere("ball", (-1.8, 1.5, 0.45), 0.45, Textured("checker", (0.9, 0.9, 0.2), (0.1, 0.1, 0.5), period=0.3)),
        Cylinder("pillar", (-2.2, -2.0, 1.5), 0.3, 3.0, Diffuse((0.75, 0.75, 0.8))),
        Box("cabinet", (2.9, -2.4, 0.9), (0.8, 1.6, 1.8), Diffuse((0.3, 0.5, 0.45))),
        Torus("ring", (0.0, -2.8, 1.2), 0.5, 0.12, Diffuse((0.8, 0.15, 0.5)), rotation=(90, 0, 0)),
    ]
    lights = [PointLight((0.5, 0.5, 2.6), (30.0, 30.0, 28.0)),
              RectangleLight((-1.0, -1.0, z - 0.01), (1.0, 1.0), (0.0, 0.0, -1.0), (6.0, 6.0, 6.0))]
    cameras = CameraHint("inside", elevation=(-20.0, 20.0), spread=0.2)
    return build_scene("room", seed, shapes, lights, aabb=((-h - WALL, -h - WALL, -WALL), (h + WALL, h + WALL, z + WALL)),
                       cameras=cameras)


def far_object(seed: int):
    """A small object (a 0.7-wide cluster: sphere, ring, block) seen from far: hemisphere
    cameras 4 away, so the object spans about a sixth of the view (10-15 pixels at 64 px)
    and the AABB is a small box far from every camera."""
    shapes = [
        Sphere("bead", (0.0, 0.0, 0.18), 0.18, Diffuse((0.85, 0.2, 0.1))),
        Torus("ring", (0.0, 0.0, 0.18), 0.3, 0.045, Diffuse((0.1, 0.5, 0.85)), rotation=(60, 0, 30)),
        Box("block", (0.18, -0.18, 0.075), (0.18, 0.18, 0.15),
            Textured("checker", (0.9, 0.9, 0.9), (0.1, 0.1, 0.1), period=0.09)),
    ]
    cameras = CameraHint("hemisphere", radius=4.0, elevation=(10.0, 70.0))
    return build_scene("far-object", seed, shapes, [SOFT_SKY], cameras=cameras)


def forward_near(seed: int):
    """A forward-facing capture (cameras within 0.1 of (0, 0, 0.5), all facing +Y) of near
    content: a sphere 0.45 away, a block at 1.1, a post at 1.7 and a textured backdrop at
    2.5 that fills the view. Depth ratio about 5, not the 250 of `depth-range`."""
    shapes = [
        Box("backdrop", (0.0, 2.55, 0.5), (6.0, 0.1, 4.0),
            Textured("checker", (0.85, 0.85, 0.8), (0.3, 0.35, 0.45), period=0.4)),
        Sphere("near_ball", (-0.2, 0.6, 0.4), 0.15, Diffuse((0.85, 0.25, 0.1))),
        Box("block", (0.45, 1.3, 0.25), (0.4, 0.4, 0.5), Textured("stripes", (0.9, 0.8, 0.2), (0.2, 0.3, 0.7),
                                                                  period=0.15), rotation=(0, 0, 25)),
        Cylinder("post", (-0.6, 1.8, 0.5), 0.12, 1.0, Diffuse((0.2, 0.7, 0.3))),
    ]
    cameras = CameraHint("forward", eye=(0.0, 0.0, 0.5), target=(0.0, 1.0, 0.5), spread=0.1)
    return build_scene("forward-near", seed, shapes, [SOFT_SKY, PointLight((0.5, -0.5, 2.0), (3.0, 3.0, 3.0))],
                       aabb=((-3.0, 0.3, -1.5), (3.0, 2.6, 2.5)), cameras=cameras)


# name -> (recipe, one-line description), listed by `nerfgauge scenes`
CHECK_RECIPES = {
    "room": (room, "rule check, not in bench hard: a closed room seen from inside (no ray leaves it)"),
    "far-object": (far_object, "rule check, not in bench hard: a 0.7-wide object seen from 4 away"),
    "forward-near": (forward_near, "rule check, not in bench hard: forward-facing capture of content 0.45-2.5 away"),
}
