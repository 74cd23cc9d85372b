"""Ground-truth alpha is each pixel's exact coverage, recomputed from the scene description
alone.

A `primitives` dataset's PNGs store alpha = the share of the pixel's square that the objects
cover (docs/conventions.md, "Pixel footprint": a box filter over the pixel; the background is
transparent). Here that share is computed without Mitsuba and without nerfgauge's camera
code: the cameras come from transforms_test.json as any NeRF-synthetic reader takes them
(pixel (row i, col j) is the square [j, j + 1) x [i, i + 1) of film coordinates; the camera
looks along -z with y up), the objects from the recipe (`scenes.library.primitives`), placed as
the generator places them (`scenes.meshes.pose`: rotate by Rz Ry Rx, then move to the centre;
a procedural scene is written in its own units, with no normalisation, which scene.json's
params confirm), and every ray is intersected analytically in numpy: a sphere by its
quadratic, the box as three slabs, the cylinder as the quadratic of its side and the slab
between its caps. A wrong pose or field of view in the export, a misplaced mesh, a film filter
other than the box, a background that counts as opaque or an alpha channel rounded the wrong
way each shows up as a difference that the tolerances below, derived from the sampling maths
alone, do not allow.

The checks: pixels certainly covered are 255 and pixels certainly empty are 0, exactly; on
every partial pixel alpha is within 5 sigma of its coverage; and over each object's edge
pixels the mean of alpha - coverage is zero within 4 standard errors (a sphere 1% too large
fails it) and its mean square is no more than the sampling noise's (a box turned a few degrees,
whose errors cancel in the mean, fails that).

The one object Mitsuba does not draw exactly is the cylinder: the generator writes it as a
prism on a regular polygon whose vertices lie on the circle (`scenes.meshes.capped_cylinder`),
so it lies between the analytic cylinder and the one inscribed in its flat faces (radius
r cos(pi / segments)), and so does its coverage. Each object is therefore an outer and an
inner analytic body (one and the same for the spheres and the box), and the rendered coverage
lies between theirs.
"""

from __future__ import annotations

import inspect
import json
import math
from dataclasses import asdict
from functools import partial

import numpy as np
import pytest
from PIL import Image

from nerfgauge.scenes import make_scene
from nerfgauge.scenes import meshes
from nerfgauge.scenes.description import Box, Cylinder, Sphere

# Not square: a field of view spread over the wrong axis (Mitsuba's fov_axis) would show.
WIDTH, HEIGHT = 64, 40
TEST_VIEWS = 4
# Two passes of 144 samples, each a 12 x 12 multi-jittered grid (generate.render.sample_chunks).
SPP = 288
# Which pixels are certainly empty, certainly covered or partial: a fixed grid of the cell
# centres of S x S cells per pixel (deterministic, so choosing pixels by it biases nothing).
CLASSIFY_CELLS = 16
# The coverage that partial pixels are compared with: one uniform random ray in each of
# S x S cells, independent of the classification grid. Its expectation is the exact coverage
# c; a grid of cell centres is not unbiased (an edge parallel to a row of centres is off by
# up to 1 / (2 S), and the box's and the cylinder's vertical edges are nearly that), and a
# bias would not shrink with the number of pixels as the checks' bounds do.
ESTIMATE_CELLS = 32
ESTIMATE_SEED = 20260101
# PNG alpha is round(255 a): off by at most half a step, not necessarily with mean zero.
ROUNDING = 0.5 / 255
# Standard deviation of (PNG alpha - estimated coverage) on one pixel, at most. The
# renderer's alpha is the mean of SPP hit indicators at positions uniform over the pixel:
# Var <= c (1 - c) / SPP, the bound for independent samples (each pass is stratified into
# 12 x 12 cells: one independent point a cell provably lowers the variance, and Mitsuba's
# correlated multi-jitter is built to lower it further). The estimate's one ray
# in each of S^2 = ESTIMATE_CELLS^2 cells, cell k covered c_k: Var = sum_k c_k (1 - c_k) / S^4
# <= c (1 - c) / S^2 (x (1 - x) is concave). The two are independent and c (1 - c) <= 1/4.
SIGMA_MAX = math.sqrt(0.25 / SPP + 0.25 / ESTIMATE_CELLS**2)  # 0.0335
# No pixel beyond 5 sigma: under a normal tail 6e-7 a pixel, below 1e-3 over the few hundred
# pixels tested, and SIGMA_MAX already over-states the stratified sampler's noise.
PIXEL_SIGMAS = 5
# An object's mean over its N edge pixels: 4 standard errors, a normal tail of 6e-5.
MEAN_SIGMAS = 4
MIN_EDGE_PIXELS = 80  # per object over the test views: the mean checks must have something to average

# 5 s on llvm_ad_rgb, 7 s on scalar_rgb (2 cores; the dataset all but the analytic coverage's
# second): past conftest's FAST_LIMIT.
pytestmark = pytest.mark.slow


# --- cameras and rays, as a NeRF-synthetic reader takes them -------------------------------------


def read_test_views(root):
    """[(c2w [4, 4], alpha [H, W] float on [0, 1])] of the test split, and the intrinsics
    (fl_x, fl_y, cx, cy) from transforms_test.json."""
    meta = json.loads((root / "transforms_test.json").read_text())
    intrinsics = tuple(float(meta[key]) for key in ("fl_x", "fl_y", "cx", "cy"))
    views = []
    for frame in meta["frames"]:
        rgba = np.asarray(Image.open(root / (frame["file_path"] + ".png")))
        assert rgba.shape == (meta["h"], meta["w"], 4), rgba.shape
        views.append((np.array(frame["transform_matrix"], np.float64), rgba[..., 3] / 255.0))
    return views, intrinsics


def film_directions(c2w, intrinsics, u, v):
    """World directions (not unit) of the rays through film points (u, v), in pixels with
    (0, 0) the top-left corner of the image: u, v [...] -> [..., 3]."""
    fl_x, fl_y, cx, cy = intrinsics
    camera = np.stack([(u - cx) / fl_x, -(v - cy) / fl_y, -np.ones_like(u)], -1)  # rows grow downwards, y up
    return camera @ c2w[:3, :3].T


# --- the objects, analytically -----------------------------------------------------------------


def rotation_xyz_degrees(degrees_xyz):
    """Local-to-world rotation Rz @ Ry @ Rx for Euler angles in degrees, the generator's
    convention (scenes.meshes.rotation_matrix). Returns [3, 3]."""
    ax, ay, az = np.radians(degrees_xyz)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def to_local(origin, directions, centre, degrees_xyz):
    """A ray bundle in a body's own frame: origin [3], directions [..., 3] -> the same shapes.
    World = R local + centre, so local = R^T (world - centre), x @ R for row vectors."""
    rotation = rotation_xyz_degrees(degrees_xyz)
    return (origin - np.asarray(centre)) @ rotation, directions @ rotation


def slab_interval(origin, directions, half):
    """Ray parameters t where |origin + t d| <= half on one axis: origin scalar, directions
    [...] -> (t_low, t_high) [...], an empty interval (inf, -inf) when it never is."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - origin) / directions, (half - origin) / directions
    parallel = directions == 0
    inside = abs(origin) <= half
    low = np.where(parallel, -np.inf if inside else np.inf, np.minimum(t1, t2))
    high = np.where(parallel, np.inf if inside else -np.inf, np.maximum(t1, t2))
    return low, high


def disc_interval(a, b, c):
    """Ray parameters t where a t^2 + 2 b t + c <= 0 (a >= 0; a convex body's quadratic):
    [...] each -> (t_low, t_high) [...], empty (inf, -inf) where there is none."""
    discriminant = b * b - a * c
    root = np.sqrt(np.maximum(discriminant, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        low, high = (-b - root) / a, (-b + root) / a
    meets = discriminant >= 0
    along_axis = a == 0  # a ray parallel to a cylinder's axis: inside it everywhere or nowhere
    low = np.where(along_axis, np.where(c <= 0, -np.inf, np.inf), np.where(meets, low, np.inf))
    high = np.where(along_axis, np.where(c <= 0, np.inf, -np.inf), np.where(meets, high, -np.inf))
    return low, high


def ahead(low, high):
    """A ray meets a convex body at some t > 0 (the cameras are outside every body)."""
    return (low <= high) & (high > 0)


def hits_sphere(origin, directions, centre, radius):
    """Whether rays origin + t d, t > 0, meet the ball: origin [3], directions [..., 3] -> [...] bool."""
    offset = origin - np.asarray(centre)
    a = np.einsum("...k,...k", directions, directions)
    b = directions @ offset
    return ahead(*disc_interval(a, b, offset @ offset - radius**2))


def hits_box(origin, directions, centre, size, degrees_xyz):
    """Whether the rays meet the box: three slabs of its own frame (slab method)."""
    local_origin, local_directions = to_local(origin, directions, centre, degrees_xyz)
    low, high = np.full(directions.shape[:-1], -np.inf), np.full(directions.shape[:-1], np.inf)
    for axis in range(3):
        axis_low, axis_high = slab_interval(local_origin[axis], local_directions[..., axis], size[axis] / 2)
        low, high = np.maximum(low, axis_low), np.minimum(high, axis_high)
    return ahead(low, high)


def hits_cylinder(origin, directions, centre, radius, height, degrees_xyz):
    """Whether the rays meet the capped cylinder around its local +Z: the side's quadratic in
    x, y, intersected with the slab |z| <= height / 2 between the caps."""
    local_origin, local_directions = to_local(origin, directions, centre, degrees_xyz)
    dx, dy = local_directions[..., 0], local_directions[..., 1]
    ox, oy = local_origin[0], local_origin[1]
    side_low, side_high = disc_interval(dx * dx + dy * dy, ox * dx + oy * dy, ox * ox + oy * oy - radius**2)
    cap_low, cap_high = slab_interval(local_origin[2], local_directions[..., 2], height / 2)
    return ahead(np.maximum(side_low, cap_low), np.minimum(side_high, cap_high))


def cylinder_segments() -> int:
    """The number of flat faces round the rendered cylinder: capped_cylinder's default, which
    Cylinder.local_mesh (the mesh the generator writes and Mitsuba loads) leaves as it is."""
    return inspect.signature(meshes.capped_cylinder).parameters["segments"].default


def analytic_bodies(shape):
    """(outer, inner): functions (origin [3], directions [..., 3]) -> hit [...] bool of the
    smallest analytic body containing what Mitsuba draws for `shape`, and the largest one
    inside it. A sphere is Mitsuba's analytic sphere and a box mesh is exact: both the same."""
    if isinstance(shape, Sphere):
        body = partial(hits_sphere, centre=shape.center, radius=shape.radius)
        return body, body
    if isinstance(shape, Box):
        body = partial(hits_box, centre=shape.center, size=shape.size, degrees_xyz=shape.rotation)
        return body, body
    if isinstance(shape, Cylinder):
        # The prism's vertices lie on the circle; its flat faces are at r cos(pi / segments).
        apothem = shape.radius * math.cos(math.pi / cylinder_segments())
        return tuple(partial(hits_cylinder, centre=shape.center, radius=radius, height=shape.height,
                             degrees_xyz=shape.rotation) for radius in (shape.radius, apothem))
    raise TypeError(f"no analytic body for {type(shape).__name__}")


# --- coverage ------------------------------------------------------------------------------------


def body_hits(c2w, intrinsics, bodies, u, v):
    """Hits of the rays through film points (u, v) [P, R] by each body: [B, P, R] bool. A
    body listed twice (an object whose inner and outer bodies are one) is intersected once."""
    directions, origin = film_directions(c2w, intrinsics, u, v), c2w[:3, 3]
    done = {}
    for body in bodies:
        if id(body) not in done:
            done[id(body)] = body(origin, directions)
    return np.stack([done[id(body)] for body in bodies])


def cell_centres(rows, cols, cells):
    """Film points (u, v) [P, cells^2] at the centres of a cells x cells grid over each pixel
    (row, col) [P]; pixels outside the image are rays all the same."""
    offsets = (np.arange(cells) + 0.5) / cells
    du, dv = (grid.ravel() for grid in np.meshgrid(offsets, offsets))
    return cols[:, None] + du[None], rows[:, None] + dv[None]


def jittered_cells(rows, cols, cells, rng):
    """Film points (u, v) [P, cells^2]: one uniform random point in each cell of a
    cells x cells grid over each pixel (row, col) [P]."""
    corners = np.arange(cells) / cells
    du, dv = (grid.ravel() for grid in np.meshgrid(corners, corners))
    u = cols[:, None] + du[None] + rng.random((len(cols), cells * cells)) / cells
    v = rows[:, None] + dv[None] + rng.random((len(rows), cells * cells)) / cells
    return u, v


def block_all(per_pixel, height, width):
    """For each pixel of the image, whether `per_pixel` holds on all of its 3 x 3 block:
    per_pixel [(height + 2) * (width + 2)] bool over the image padded by one pixel -> [height, width]."""
    padded = per_pixel.reshape(height + 2, width + 2)
    out = np.ones((height, width), bool)
    for di in range(3):
        for dj in range(3):
            out &= padded[di:di + height, dj:dj + width]
    return out


def compare_view(c2w, intrinsics, alpha, shapes, rng):
    """One view's pixels, classified and compared. alpha [H, W] on [0, 1].

    Returns dict: full [H, W] and empty [H, W] bool (certainly covered / certainly empty),
    and for the partial pixels (the cell-centre grid sees some rays hit and some miss):
    rows, cols [P], alpha [P], coverage_outer, coverage_inner [P] (the estimated coverage by
    the outer and the inner bodies, with the same rays), owner [P] (index into `shapes` of
    the one object whose silhouette crosses the pixel, -1 where several do)."""
    height, width = alpha.shape
    bodies = [body for shape in shapes for body in analytic_bodies(shape)]  # outer, inner, outer, ...
    rows, cols = (grid.ravel() for grid in np.meshgrid(np.arange(-1, height + 1), np.arange(-1, width + 1),
                                                       indexing="ij"))
    centre_hits = body_hits(c2w, intrinsics, bodies, *cell_centres(rows, cols, CLASSIFY_CELLS))
    centre_outer, centre_inner = centre_hits[0::2], centre_hits[1::2]  # [K, P, S^2] each
    # Certainly covered: every cell centre of the 3 x 3 block inside one object's (inner)
    # silhouette. A silhouette is convex (the projection of a convex body), so it then holds
    # the centres' convex hull, which contains the middle pixel with a margin of nearly a pixel.
    full = np.zeros((height, width), bool)
    for k in range(len(shapes)):
        full |= block_all(centre_inner[k].all(axis=1), height, width)
    # Certainly empty: no cell centre of the block in any (outer) silhouette. A convex
    # silhouette reaching into the pixel at x, holding a disc of radius rho at distance D from
    # x, holds the cone from x to that disc; inside the block (a pixel round x) the cone holds a
    # disc of radius about rho / D, and any disc wider than a cell's diagonal (sqrt(2) / 16
    # pixel) holds a cell centre. Each object here is several pixels across and at most about
    # twice as long as it is wide: rho / D >= 1/4, far above the 0.044 pixel needed.
    empty = block_all(~centre_outer.any(axis=(0, 2)), height, width)

    inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
    covered = centre_outer.any(axis=0).mean(axis=1)  # union coverage by the cell centres, [P]
    partial = inside & (covered > 0) & (covered < 1)
    touched = centre_outer[:, partial].any(axis=2)  # [K, P']: which silhouettes reach into the pixel
    owner = np.where(touched.sum(axis=0) == 1, touched.argmax(axis=0), -1)
    rows, cols = rows[partial], cols[partial]
    # Fresh rays, independent of the classification: their coverage is unbiased on the chosen
    # pixels. Inner and outer bodies see the same rays, so inner coverage <= outer coverage.
    estimate = body_hits(c2w, intrinsics, bodies, *jittered_cells(rows, cols, ESTIMATE_CELLS, rng))
    return {"full": full, "empty": empty, "rows": rows, "cols": cols, "alpha": alpha[rows, cols],
            "coverage_outer": estimate[0::2].any(axis=0).mean(axis=1),
            "coverage_inner": estimate[1::2].any(axis=0).mean(axis=1), "owner": owner}


# --- the dataset and its comparison ------------------------------------------------------------


def placement(shape_json):
    """What puts a shape where it is (type, name, centre, extent, rotation) out of its JSON:
    scene.json's entry, or the recipe's dataclass written the same way."""
    keys = ("type", "name", "center", "radius", "size", "height", "rotation")
    return {key: value for key, value in shape_json.items() if key in keys}


@pytest.fixture(scope="module")
def compared(make_dataset, tmp_path_factory):
    """The test views of a small primitives dataset, each compared with the analytic coverage."""
    root = make_dataset(tmp_path_factory.mktemp("alpha") / "primitives", views=1, val_views=0,
                        test_views=TEST_VIEWS, width=WIDTH, height=HEIGHT, spp=SPP)
    written = json.loads((root / "scene.json").read_text())
    assert written["images"]["filter"] == "box" and written["images"]["spp"] == SPP
    assert written["needs"]["background"] == "transparent"
    # The world frame: a procedural scene in its own units (no to_scene normalisation), the
    # objects as the recipe places them.
    assert "to_scene" not in written["scene"]["params"]
    shapes = make_scene("primitives", written["seed"]).shapes
    recipe = json.loads(json.dumps([{"type": type(shape).__name__} | asdict(shape) for shape in shapes]))
    assert [placement(shape) for shape in written["scene"]["shapes"]] == [placement(shape) for shape in recipe]

    views, intrinsics = read_test_views(root)
    assert len(views) == TEST_VIEWS
    rng = np.random.default_rng(ESTIMATE_SEED)
    return shapes, [compare_view(c2w, intrinsics, alpha, shapes, rng) for c2w, alpha in views], views


def edge_pixels(compared):
    """All views' partial pixels, concatenated: dict of [N] arrays (see compare_view)."""
    _, results, _ = compared
    keys = ("alpha", "coverage_outer", "coverage_inner", "owner")
    return {key: np.concatenate([result[key] for result in results]) for key in keys}


def test_certainly_covered_pixels_are_opaque_and_certainly_empty_ones_transparent(compared):
    """Where the analytic silhouettes cover the whole pixel every sample hits, so alpha is
    exactly 255; where none reaches into it, none does, so alpha is exactly 0 (the sky the
    path tracer still lights with is hidden from camera rays)."""
    _, results, views = compared
    for (_, alpha), result in zip(views, results):
        assert result["full"].sum() > 50 and result["empty"].sum() > 500  # the objects fill part of each view
        assert (alpha[result["full"]] == 1.0).all(), np.sort(alpha[result["full"]])[:5]
        assert (alpha[result["empty"]] == 0.0).all(), np.sort(alpha[result["empty"]])[-5:]


def test_every_edge_pixel_is_within_five_sigma_of_its_coverage(compared):
    """Each partial pixel on its own: its noise has sd at most SIGMA_MAX, so alpha lies within
    PIXEL_SIGMAS * SIGMA_MAX (plus the rounding) of the coverage interval."""
    pixels = edge_pixels(compared)
    # The rendered coverage lies in [inner, outer] (the same body for all but the cylinder):
    # alpha may fall short of the outer coverage, or exceed the inner one, by noise and rounding.
    slack = PIXEL_SIGMAS * SIGMA_MAX + ROUNDING
    above = pixels["alpha"] - pixels["coverage_outer"]
    below = pixels["coverage_inner"] - pixels["alpha"]
    worst = max(above.max(), below.max())
    assert worst <= slack, f"a pixel's alpha is {worst:.3f} from its coverage interval; allowed {slack:.3f}"


@pytest.mark.parametrize("name", ["red_sphere", "blue_box", "green_cylinder", "checker_sphere"])
def test_an_objects_edge_pixels_have_no_coverage_bias(compared, name):
    """Over the pixels crossed by exactly this object's silhouette, alpha - coverage has mean
    zero and the spread of the sampling noise (a wrong size moves the mean; a wrong rotation
    moves opposite edges opposite ways, and shows in the spread)."""
    shapes, _, _ = compared
    pixels = edge_pixels(compared)
    mine = pixels["owner"] == [shape.name for shape in shapes].index(name)
    count = int(mine.sum())
    assert count >= MIN_EDGE_PIXELS, f"{name}: only {count} edge pixels"
    alpha, outer, inner = pixels["alpha"][mine], pixels["coverage_outer"][mine], pixels["coverage_inner"][mine]

    # Mean: alpha - outer has expectation in [-(outer - inner), 0] (the rendered body between
    # the two) plus the rounding's at most ROUNDING, and a standard error of at most
    # SIGMA_MAX / sqrt(N) (the pixels' noises are independent).
    spread = MEAN_SIGMAS * SIGMA_MAX / math.sqrt(count) + ROUNDING
    excess = float(np.mean(alpha - outer))
    shortfall = float(np.mean(alpha - inner))
    assert excess <= spread and shortfall >= -spread, (
        f"{name}: mean(alpha - coverage) is {excess:+.4f} (outer body) and {shortfall:+.4f} (inner), "
        f"allowed +-{spread:.4f} over {count} pixels")

    # Spread: d = alpha - (inner + outer) / 2 is zero-mean noise (sd <= SIGMA_MAX) plus the
    # rounding plus at most half the inner-outer gap, so E[d^2] <= m = (SIGMA_MAX + ROUNDING +
    # gap)^2 (Minkowski). Its fourth moment is at most about 3 m^2 (a mean of many bounded
    # draws is near normal, whose fourth moment is 3 sigma^4), so the mean of d^2 over N pixels
    # has a standard error of at most sqrt(3 / N) m.
    gap = float(np.max(outer - inner)) / 2
    m = (SIGMA_MAX + ROUNDING + gap) ** 2
    mean_square = float(np.mean((alpha - (inner + outer) / 2) ** 2))
    allowed = m * (1 + MEAN_SIGMAS * math.sqrt(3 / count))
    assert mean_square <= allowed, (
        f"{name}: rms(alpha - coverage) is {math.sqrt(mean_square):.4f}, allowed {math.sqrt(allowed):.4f} "
        f"over {count} pixels")
