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
from nerfgauge.scenes.hard import SUNNY_SKY
from nerfgauge.scenes.library import SOFT_SKY

ROOM_HALF = 4.0  # the room is 8 x 8 x 3: its walls reach 10x beyond the cameras' cluster
ROOM_HEIGHT = 3.0
WALL = 0.1


def _walls(half_x: float, half_y: float, height: float, north, south, east, west) -> list:
    """Four walls WALL thick standing on z = 0 around the floor [-half_x, half_x] x
    [-half_y, half_y], `height` high (north and south reach over the corners), in these
    materials: north, south, east, west, in that order."""
    return [Box("wall_north", (0.0, half_y + WALL / 2, height / 2), (2 * half_x + 2 * WALL, WALL, height), north),
            Box("wall_south", (0.0, -half_y - WALL / 2, height / 2), (2 * half_x + 2 * WALL, WALL, height), south),
            Box("wall_east", (half_x + WALL / 2, 0.0, height / 2), (WALL, 2 * half_y, height), east),
            Box("wall_west", (-half_x - WALL / 2, 0.0, height / 2), (WALL, 2 * half_y, height), west)]


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
        *_walls(h, h, z, Textured("stripes", (0.8, 0.3, 0.2), (0.9, 0.85, 0.7), period=0.6),
                Textured("checker", (0.2, 0.4, 0.8), (0.9, 0.9, 0.9), period=0.7),
                Textured("stripes", (0.2, 0.6, 0.3), (0.85, 0.85, 0.6), period=0.5), Diffuse((0.7, 0.6, 0.3))),
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


# --- issue 52: captures for checking where the parametrisation rule is unsure --------------
# Written before any was rendered or trained, to stress the rule where its margins say it
# is unsure (nerf.parametrisation.parametrisation_doubt); nothing is tuned on them.

YARD_HALF = (5.0, 3.5)  # a 10 x 7 yard: its walls reach about 12x beyond the cameras' cluster
YARD_WALL = 2.5


def courtyard(seed: int):
    """An interior open to the sky, seen from inside: a 10 x 7 yard walled 2.5 high and
    with no roof, a fountain, two trees, a bench and a crate in it, under a sunny sky.
    Cameras stand in a 0.4-wide cluster at its centre and look outwards (layout "inside",
    -15 to 20 degrees): the walls fill most of each view, the sky shows above them. The
    box ends at the walls, so everything but the sky lies within it."""
    hx, hy = YARD_HALF
    z = YARD_WALL
    shapes = [
        Box("ground", (0.0, 0.0, -WALL / 2), (2 * hx, 2 * hy, WALL),
            Textured("checker", (0.7, 0.65, 0.55), (0.45, 0.4, 0.35), period=1.0)),
        *_walls(hx, hy, z, Textured("stripes", (0.75, 0.45, 0.3), (0.9, 0.8, 0.65), period=0.7),
                Textured("checker", (0.55, 0.6, 0.7), (0.85, 0.85, 0.8), period=0.9),
                Textured("stripes", (0.4, 0.55, 0.35), (0.85, 0.8, 0.6), period=0.6), Diffuse((0.8, 0.7, 0.45))),
        Torus("fountain", (2.5, 1.2, 0.25), 0.6, 0.15, Diffuse((0.6, 0.6, 0.65))),
        Cylinder("trunk_a", (-2.8, 1.8, 0.9), 0.12, 1.8, Diffuse((0.4, 0.25, 0.1))),
        Sphere("crown_a", (-2.8, 1.8, 1.85), 0.65, Textured("checker", (0.2, 0.5, 0.15), (0.35, 0.65, 0.2), period=0.35)),
        Cylinder("trunk_b", (3.2, -1.9, 0.8), 0.1, 1.6, Diffuse((0.4, 0.25, 0.1))),
        Sphere("crown_b", (3.2, -1.9, 1.8), 0.6, Diffuse((0.25, 0.55, 0.2))),
        Box("bench", (-1.5, -2.3, 0.25), (1.6, 0.5, 0.5), Diffuse((0.55, 0.35, 0.2)), rotation=(0, 0, 10)),
        Box("crate", (-3.6, -1.0, 0.35), (0.7, 0.7, 0.7), Textured("stripes", (0.9, 0.8, 0.3), (0.3, 0.3, 0.6),
                                                                   period=0.25), rotation=(0, 0, 30)),
    ]
    cameras = CameraHint("inside", elevation=(-15.0, 20.0), spread=0.2)
    return build_scene("courtyard", seed, shapes, [SUNNY_SKY],
                       aabb=((-hx - WALL, -hy - WALL, -WALL), (hx + WALL, hy + WALL, z + WALL)), cameras=cameras)


def close_up(seed: int):
    """A forward-facing close-up: cameras within 0.04 of (0, 0, 0.3), all facing +Y, at
    content 0.25-0.55 away (a die-sized block, a marble, a spool) in front of a textured
    card 0.7 away that fills the view. The box's far side is about 5x as far as its near
    side: little depth for log depth to spread its cells over."""
    shapes = [
        Box("card", (0.0, 0.72, 0.3), (1.6, 0.02, 1.2),
            Textured("checker", (0.85, 0.8, 0.7), (0.35, 0.4, 0.5), period=0.08)),
        Sphere("marble", (-0.06, 0.27, 0.27), 0.03, Diffuse((0.85, 0.2, 0.1))),
        Box("block", (0.08, 0.4, 0.28), (0.08, 0.08, 0.08),
            Textured("stripes", (0.9, 0.85, 0.2), (0.2, 0.3, 0.7), period=0.03), rotation=(0, 0, 30)),
        Cylinder("spool", (-0.1, 0.52, 0.33), 0.05, 0.14, Diffuse((0.2, 0.6, 0.35))),
    ]
    cameras = CameraHint("forward", eye=(0.0, 0.0, 0.3), target=(0.0, 1.0, 0.3), spread=0.04)
    return build_scene("close-up", seed, shapes, [SOFT_SKY, PointLight((0.3, -0.2, 0.8), (0.6, 0.6, 0.6))],
                       aabb=((-0.8, 0.14, -0.35), (0.8, 0.75, 0.95)), cameras=cameras)


def far_ground(seed: int):
    """An orbit whose ground reaches far: objects about 1 across on a checker ground 30
    wide, orbit cameras 2.2 from them at 20 degrees looking at them, so the box (the
    ground's) reaches about 6x beyond the cameras, under the 8x where the rule turns to
    contraction; beyond the ground, sky. Every camera stands inside the box."""
    shapes = [
        Box("ground", (0.0, 0.0, -0.05), (30.0, 30.0, 0.1), Textured("checker", (0.8, 0.75, 0.65),
                                                                      (0.4, 0.45, 0.35), period=0.6)),
        Sphere("ball", (0.35, 0.3, 0.3), 0.3, Textured("stripes", (0.85, 0.3, 0.1), (0.95, 0.9, 0.8), period=0.15)),
        Box("crate", (-0.35, -0.2, 0.25), (0.45, 0.45, 0.5), Diffuse((0.3, 0.45, 0.75)), rotation=(0, 0, 25)),
        Cylinder("post", (-0.2, 0.45, 0.35), 0.1, 0.7, Diffuse((0.2, 0.65, 0.3))),
    ]
    cameras = CameraHint("orbit", radius=2.2, elevation=(20.0, 20.0), target=(0.0, 0.0, 0.3))
    return build_scene("far-ground", seed, shapes, [SUNNY_SKY], aabb=((-15.0, -15.0, -0.1), (15.0, 15.0, 2.5)),
                       cameras=cameras)


def skylight_room(seed: int):
    """A room like `room` (8 x 8 x 3, cameras in a 0.4-wide cluster at its centre looking
    outwards) with a 1.2 x 1.2 skylight in its ceiling off to the east, through which some
    views see sky: under 1% of the pixels (0.8% of 40 train views), so the capture sits below the
    99.9% opaque that would make it closed. Lit by a lamp inside and the sky."""
    h, z = ROOM_HALF, ROOM_HEIGHT
    x0, x1, y0, y1 = 1.6, 2.8, -0.6, 0.6  # the skylight
    ceiling = Diffuse((0.85, 0.85, 0.85))
    top = z + WALL / 2
    shapes = [
        Box("floor", (0.0, 0.0, -WALL / 2), (2 * h, 2 * h, WALL),
            Textured("checker", (0.75, 0.7, 0.6), (0.3, 0.3, 0.35), period=0.9)),
        Box("ceiling_west", ((-h + x0) / 2, 0.0, top), (x0 + h, 2 * h, WALL), ceiling),
        Box("ceiling_east", ((x1 + h) / 2, 0.0, top), (h - x1, 2 * h, WALL), ceiling),
        Box("ceiling_north", ((x0 + x1) / 2, (y1 + h) / 2, top), (x1 - x0, h - y1, WALL), ceiling),
        Box("ceiling_south", ((x0 + x1) / 2, (-h + y0) / 2, top), (x1 - x0, y0 + h, WALL), ceiling),
        *_walls(h, h, z, Textured("checker", (0.3, 0.5, 0.7), (0.85, 0.85, 0.85), period=0.6),
                Diffuse((0.75, 0.55, 0.35)), Textured("stripes", (0.7, 0.25, 0.25), (0.9, 0.85, 0.75), period=0.5),
                Textured("stripes", (0.25, 0.55, 0.3), (0.85, 0.85, 0.65), period=0.7)),
        Box("shelf", (-2.8, 2.6, 1.0), (1.4, 0.5, 2.0), Diffuse((0.45, 0.3, 0.2))),
        Sphere("globe", (1.9, -2.2, 0.5), 0.5, Textured("checker", (0.2, 0.3, 0.8), (0.9, 0.9, 0.85), period=0.35)),
        Cylinder("column", (-2.0, -2.4, 1.5), 0.25, 3.0, Diffuse((0.8, 0.78, 0.72))),
    ]
    lights = [SOFT_SKY, PointLight((-0.5, 0.5, 2.5), (25.0, 25.0, 23.0))]
    cameras = CameraHint("inside", elevation=(-10.0, 30.0), spread=0.2)
    return build_scene("skylight-room", seed, shapes, lights,
                       aabb=((-h - WALL, -h - WALL, -WALL), (h + WALL, h + WALL, z + WALL)), cameras=cameras)


# the issue 52 captures, in the order docs/results.md lists them (`nerfgauge bench parametrisation`)
TRIAL_CHECK_SCENES = ("courtyard", "close-up", "far-ground", "skylight-room")

# name -> (recipe, one-line description), listed by `nerfgauge scenes`
CHECK_RECIPES = {
    "room": (room, "rule check, not in bench hard: a closed room seen from inside (no ray leaves it)"),
    "far-object": (far_object, "rule check, not in bench hard: a 0.7-wide object seen from 4 away"),
    "forward-near": (forward_near, "rule check, not in bench hard: forward-facing capture of content 0.45-2.5 away"),
    "courtyard": (courtyard, "rule check, in no bench: a walled yard open to the sky, seen from a cluster at its centre"),
    "close-up": (close_up, "rule check, in no bench: forward-facing close-up of content 0.25-0.7 away"),
    "far-ground": (far_ground, "rule check, in no bench: orbit around objects on a ground reaching 6x beyond the cameras"),
    "skylight-room": (skylight_room, "rule check, in no bench: a room seen from inside with a skylight (0.1-1% sky)"),
}
