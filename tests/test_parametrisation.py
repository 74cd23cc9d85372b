"""Scene parametrisations (nerf/parametrisation.py): the maps, their choice, and the grid
field and marching built on them."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from nerfgauge.core.errors import InputError
from nerfgauge.nerf.config import TrainConfig
from nerfgauge.nerf.parametrisation import (
    LOG_DEPTH_SCALE,
    Space,
    check_targets,
    choose_parametrisation,
    contract,
    contract_jacobian,
    log_perspective,
    log_perspective_inverse,
    log_perspective_jacobian,
    make_space,
    uncontract,
)

coordinate = st.floats(-50.0, 50.0, allow_nan=False)
point = st.tuples(coordinate, coordinate, coordinate)


@settings(max_examples=60, deadline=None)
@given(point)
def test_contraction_round_trips(p):
    y = torch.tensor([p], dtype=torch.float64)
    assert torch.allclose(uncontract(contract(y)), y, rtol=1e-9, atol=1e-9)
    assert float(contract(y).norm()) < 2.0


@settings(max_examples=40, deadline=None)
@given(point, point)
def test_contraction_is_monotone_along_rays(origin, direction):
    d = torch.tensor(direction, dtype=torch.float64)
    if float(d.norm()) < 1e-3:
        return
    d = d / d.norm()
    o = torch.tensor(origin, dtype=torch.float64)
    t = torch.linspace(0, 1e4, 2001, dtype=torch.float64)
    c = contract(o + t[:, None] * d)
    # distance travelled in the contracted space never goes backwards: consecutive points
    # are distinct and the contracted curve has no reversal (dot of successive steps >= 0)
    steps = c[1:] - c[:-1]
    assert bool(((steps[1:] * steps[:-1]).sum(-1) >= -1e-12).all())


def test_contraction_is_finite_at_infinity():
    big = torch.tensor([[1e30, -1e30, 3e29], [float("1e300"), 0, 0]], dtype=torch.float64)
    c = contract(big)
    assert torch.isfinite(c).all() and bool((c.norm(dim=-1) <= 2).all())
    assert torch.allclose(c.norm(dim=-1), torch.full((2,), 2.0, dtype=torch.float64))


@settings(max_examples=40, deadline=None)
@given(point)
def test_contraction_jacobian_matches_finite_differences(p):
    y = torch.tensor([p], dtype=torch.float64)
    if abs(float(y.norm()) - 1) < 1e-3:  # the kink of the piecewise map
        return
    eps = 1e-6 * max(1.0, float(y.norm()))
    numeric = torch.stack([(contract(y + eps * e) - contract(y - eps * e))[0] / (2 * eps)
                           for e in torch.eye(3, dtype=torch.float64)], dim=1)
    assert torch.allclose(contract_jacobian(y)[0], numeric, atol=1e-6)


depth = st.floats(0.01, 500.0)
across = st.floats(-5.0, 5.0)


@settings(max_examples=60, deadline=None)
@given(across, across, depth)
def test_log_perspective_round_trips_and_jacobian(a, b, z):
    p = torch.tensor([[a * z, b * z, z]], dtype=torch.float64)
    g = log_perspective(p)
    assert torch.isfinite(g).all()
    assert torch.allclose(log_perspective_inverse(g), p, rtol=1e-9, atol=1e-12)
    eps = 1e-6 * z
    numeric = torch.stack([(log_perspective(p + eps * e) - log_perspective(p - eps * e))[0] / (2 * eps)
                           for e in torch.eye(3, dtype=torch.float64)], dim=1)
    assert torch.allclose(log_perspective_jacobian(p)[0], numeric, rtol=1e-5, atol=1e-6 / z)


def test_log_perspective_is_monotone_along_forward_rays_and_finite_near():
    # a ray leaving the camera forward: its log depth only grows, and the near plane is finite
    d = torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64)
    t = torch.linspace(1e-4, 1e4, 5000, dtype=torch.float64)
    g = log_perspective(t[:, None] * d)
    assert torch.isfinite(g).all()
    assert bool((g[1:, 2] > g[:-1, 2]).all())
    assert torch.allclose(g[:, 0], torch.full_like(g[:, 0], 0.3))  # a ray through the centre keeps its angle


def _camera(eye, target):
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    f = target - eye
    f /= np.linalg.norm(f)
    up = np.array([0.0, 0.0, 1.0]) if abs(f[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = r, u, -f, eye
    return c2w


def test_choice_follows_cameras_and_bounds():
    aabb = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    orbit = np.stack([_camera((3 * math.cos(a), 3 * math.sin(a), 1.0), (0, 0, 0)) for a in np.linspace(0, 6, 8)])
    assert choose_parametrisation(None, aabb, orbit)[0] == "bounded"
    inside = np.stack([_camera((0.1 * math.cos(a), 0.1 * math.sin(a), 0.0), (math.cos(a), math.sin(a), 0))
                       for a in np.linspace(0, 6, 8)])
    assert choose_parametrisation(None, aabb, inside)[0] == "contracted"
    forward = np.stack([_camera((x, -3.0, 0.0), (x, 0.0, 0.0)) for x in (-0.05, 0.0, 0.05)])
    kind, reason = choose_parametrisation(None, aabb, forward)
    assert kind == "forward" and "forward-facing" in reason
    assert choose_parametrisation("contracted", aabb, forward) == ("contracted", "set on the command line")


def test_bad_inputs_are_one_line():
    aabb = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    with pytest.raises(InputError, match="unknown parametrisation 'ndcx'"):
        choose_parametrisation("ndcx", aabb, np.stack([_camera((3, 0, 0), (0, 0, 0))]))
    with pytest.raises(InputError, match="unknown parametrisation"):
        TrainConfig(dataset="d", steps=1, parametrisation="sphere").validate()
    away = np.stack([_camera((3, 0, 0), (6, 0, 0)), _camera((0, 3, 0), (0, 6, 0))])
    with pytest.raises(InputError, match="contain no camera target") as error:
        check_targets(aabb, away)
    assert "\n" not in str(error.value)
    check_targets(aabb, np.stack([_camera((3, 0, 0), (0, 0, 0))]))  # looks at it: accepted


def _forward_space():
    aabb = np.array([[-3.0, 0.15, -3.0], [3.0, 60.0, 3.0]])
    c2w = np.stack([_camera((x, 0.0, 0.0), (x, 1.0, 0.0)) for x in (-0.01, 0.0, 0.01)])
    return make_space("forward", aabb, c2w)


def test_forward_depth_is_world_distance_along_the_ray():
    """An analytic forward-facing case: an opaque wall at y = Y in front of the cameras,
    density written into the grid through the map; the rendered depth is the world
    distance to the wall along each ray."""
    from nerfgauge.nerf.grid_field import VoxelGridField
    from nerfgauge.nerf.models import CompactNeRF

    space = _forward_space()
    box = torch.tensor(space.box, dtype=torch.float32)
    field = VoxelGridField(box, 96, 96, view_dependent=False, space=space)
    model = CompactNeRF(field)
    wall = 12.0
    nz, ny, nx = field.shape
    g = torch.stack(torch.meshgrid(*[torch.linspace(float(box[0, i]), float(box[1, i]), n)
                                     for i, n in zip((2, 1, 0), (nz, ny, nx))], indexing="ij"), -1).flip(-1)
    z = torch.exp(g[..., 2] / LOG_DEPTH_SCALE)  # camera depth of every node = world y here
    dense = field.to_dense()
    dense[0] = torch.where(z >= wall, torch.tensor(8.0), torch.tensor(-30.0))
    field.load_dense(dense)
    directions = torch.tensor([[0.0, 1.0, 0.0], [0.2, 1.0, 0.1], [-0.3, 1.0, -0.25]])
    directions = directions / directions.norm(dim=-1, keepdim=True)
    origins = torch.zeros_like(directions)
    with torch.no_grad():
        out = model.render(origins, directions)
    truth = wall / directions[:, 1]
    assert torch.allclose(out.opacity, torch.ones(3), atol=1e-3)
    # within one log-depth cell (relative size (box depth extent / cells) / k) of the truth
    cell = float(box[1, 2] - box[0, 2]) / (nz - 1) / LOG_DEPTH_SCALE
    assert torch.allclose(out.depth, truth, rtol=cell)


def test_world_density_query_is_differentiable_in_every_space():
    from nerfgauge.nerf.grid_field import VoxelGridField
    from nerfgauge.nerf.models import CompactNeRF

    aabb = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    orbit = np.stack([_camera((3 * math.cos(a), 3 * math.sin(a), 1.0), (0, 0, 0)) for a in np.linspace(0, 6, 8)])
    for space in (make_space("contracted", aabb, orbit), _forward_space()):
        field = VoxelGridField(torch.tensor(space.box, dtype=torch.float32), 16, 16, False, space=space)
        field.load_dense(field.to_dense().normal_(generator=torch.Generator().manual_seed(0)))
        points = torch.tensor([[0.3, 2.0, 0.1], [5.0, 40.0, -2.0]], requires_grad=True)
        sigma = CompactNeRF(field).density(points)
        assert sigma.shape == (2,) and torch.isfinite(sigma).all() and bool((sigma >= 0).all())
        sigma.sum().backward()
        assert points.grad is not None and torch.isfinite(points.grad).all()


def test_space_round_trips_json():
    space = _forward_space()
    assert Space.from_json(space.to_json()) == space
    with pytest.raises(ValueError):
        Space.from_json({"kind": "ndcx", "box": []})


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 200), st.integers(1, 6), st.floats(0.01, 100.0), st.integers(0, 2**31 - 1))
def test_int8_model_values_round_trip_within_half_a_step(n, channels, spread, seed):
    from nerfgauge.nerf.checkpoint import dequantise_per_channel, quantise_per_channel

    values = torch.randn((n, channels), generator=torch.Generator().manual_seed(seed)) * spread
    codes, offset, scale = quantise_per_channel(values)
    assert codes.dtype == torch.uint8 and offset.shape == scale.shape == (channels,)
    back = dequantise_per_channel(codes, offset, scale)
    # half a quantisation step, plus float32 rounding of values of this size
    assert bool(((back - values).abs() <= scale / 2 + 1e-6 * spread * 8).all())


def test_int8_saved_model_renders_like_the_fp16_one():
    """A pruned model saved with int8 values loads (weights_only) and renders within the
    colour change its quantisation error allows."""
    import io

    from nerfgauge.nerf.checkpoint import build_model, model_from_payload, model_payload

    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    config = TrainConfig(dataset="d", steps=1, view_dependent=False, final_resolution=16, start_resolution=16,
                         parametrisation="bounded")
    model = build_model(config, aabb)
    model.field.load_dense(model.field.to_dense().normal_(generator=torch.Generator().manual_seed(3)))
    loaded = {}
    for kind in ("fp16", "int8"):
        buffer = io.BytesIO()
        torch.save(model_payload(model, TrainConfig(**{**config.__dict__, "quantise": kind}), prune=True), buffer)
        buffer.seek(0)
        loaded[kind] = (model_from_payload(torch.load(buffer, weights_only=True)), buffer.getbuffer().nbytes)
    assert loaded["int8"][1] < loaded["fp16"][1]
    grids = [loaded[k][0].field.to_dense() for k in ("fp16", "int8")]
    dense = model.field.to_dense()
    channel_range = dense.flatten(1).amax(1) - dense.flatten(1).amin(1)
    error = (grids[0] - grids[1]).abs().flatten(1).amax(1)
    assert bool((error <= channel_range / 255 / 2 + 2e-3 * channel_range.abs().max()).all())


def test_contraction_frame_centres_on_the_orbit_target_and_sizes_the_inner_ball():
    """Orbit cameras inside a huge terrain AABB: the centre is their target (not the AABB's
    middle, 14 units above it) and the inner ball just holds the cameras. Cameras in a room
    whose walls are a few camera radii away: the inner ball reaches the walls."""
    from nerfgauge.nerf.parametrisation import NEAR_AABB_FACTOR, contraction_frame

    target = np.array([0.0, 0.0, 0.3])
    orbit = np.stack([_camera(target + 3.2 * np.array([math.cos(a), math.sin(a), 0.2]), target)
                      for a in np.linspace(0, 6, 12)])
    terrain = np.array([[-100.0, -100.0, -1.0], [100.0, 100.0, 30.0]])
    centre, radius = contraction_frame(terrain, orbit)
    assert np.allclose(centre, target, atol=1e-6)
    farthest = float(np.linalg.norm(orbit[:, :3, 3] - target, axis=1).max())
    assert radius == pytest.approx(1.1 * farthest)
    # outward-looking cameras near the middle of a 5 x 5 x 1.2 room: the walls are near content
    room = np.array([[-2.5, -2.5, -0.3], [2.5, 2.5, 0.9]])
    inside = np.stack([_camera((0.4 * math.cos(a), 0.4 * math.sin(a), 0.3),
                               (2 * math.cos(a), 2 * math.sin(a), 0.3)) for a in np.linspace(0, 6, 12)])
    centre, radius = contraction_frame(room, inside)
    assert np.all(centre >= room[0]) and np.all(centre <= room[1])
    reach = float(np.maximum(room[1] - centre, centre - room[0]).max())
    cams = 1.1 * float(np.linalg.norm(inside[:, :3, 3] - centre, axis=1).max())
    assert cams < reach <= NEAR_AABB_FACTOR * cams and radius == pytest.approx(reach)
    # parallel axes (forward-facing among the content): no focus, the cameras' centroid
    parallel = np.stack([_camera((x, 0.0, 0.5), (x, 1.0, 0.5)) for x in (-0.5, 0.0, 0.5)])
    centre, _ = contraction_frame(terrain, parallel)
    assert np.allclose(centre, [0.0, 0.0, 0.5])


@pytest.mark.parametrize("kind", ["contracted", "forward"])
def test_march_space_keeps_exactly_the_samples_in_occupied_cells(kind):
    """march_space's samples are exactly the intervals whose sample point lies in an
    occupied cell (the brute force below), for a sparse, surface-like occupancy and a
    dense one (a guard for any faster marching: it must keep the same samples)."""
    from nerfgauge.nerf.marching import march_space

    g = torch.Generator().manual_seed(3)
    if kind == "contracted":
        space = Space("contracted", [[-2.0] * 3, [2.0] * 3], centre=[0.0, 0.0, 0.3], radius=1.5)
        origins = torch.randn(300, 3, generator=g) * 0.4
        directions = torch.nn.functional.normalize(torch.randn(300, 3, generator=g), dim=-1)
    else:
        space = _forward_space()
        origins = (torch.rand(300, 3, generator=g) - 0.5) * 0.02
        directions = torch.nn.functional.normalize(
            torch.cat([(torch.rand(300, 1, generator=g) - 0.5) * 0.6, torch.ones(300, 1),
                       (torch.rand(300, 1, generator=g) - 0.5) * 0.6], dim=1), dim=-1)
    box = torch.tensor(space.box, dtype=torch.float32)
    res = 42  # not a multiple of the pooled blocks
    nodes = torch.stack(torch.meshgrid(*[torch.linspace(0, 1, res)] * 3, indexing="ij"), -1)
    shell = ((nodes - 0.5).norm(dim=-1) - 0.3).abs() < 0.03  # a thin spherical shell of cells
    dense = torch.rand((res,) * 3, generator=g) < 0.3
    scattered = torch.rand((res,) * 3, generator=g) < 0.003  # isolated cells: the coarse test's hardest case
    step = 0.5 * float((box[1] - box[0]).max()) / res
    jitter = torch.rand(300, generator=g)
    for occupancy in (shell, dense, scattered):
        got = march_space(origins, directions, space, box, occupancy, step, jitter=jitter)
        edges = space.ray_edges(origins, directions, step)
        lengths = edges[:, 1:] - edges[:, :-1]
        rays, cols = (lengths > 0).nonzero(as_tuple=True)
        t = edges[rays, cols] + jitter[rays] * lengths[rays, cols]
        grid = space.to_grid(origins[rays] + t[:, None] * directions[rays])
        index = ((grid - box[0]) / ((box[1] - box[0]) / res)).floor().long()
        inside = ((index >= 0) & (index < res)).all(-1)
        index = index.clamp(0, res - 1)
        keep = inside & occupancy[index[:, 2], index[:, 1], index[:, 0]]
        assert keep.any() and not keep.all()
        assert torch.equal(got.ray_index, rays[keep])
        assert torch.equal(got.t_mid, t[keep])
        assert torch.equal(got.step, lengths[rays, cols][keep])


@pytest.mark.parametrize("scene, expected", [("inside", "bounded"), ("far-reaching", "contracted"),
                                             ("depth-range", "forward"), ("primitives", "bounded")])
def test_auto_choice_on_the_planned_cameras_of_real_scenes(scene, expected):
    """Cameras among near content (a room) keep one grid; cameras among content that reaches
    far beyond them get contraction; a forward-facing capture gets log depth."""
    from nerfgauge.generate.pipeline import GenerateConfig, plan

    the_plan = plan(GenerateConfig(scene=scene, views=12, val_views=0, test_views=2, width=16, height=16, spp=1))
    kind, reason = choose_parametrisation(None, np.asarray(the_plan.scene.aabb), the_plan.poses["train"])
    assert kind == expected, reason


@pytest.mark.parametrize("kind", ["bounded", "contracted", "forward"])
def test_the_marching_step_follows_the_parametrisation_unless_set(kind):
    """Unset, the training step is the parametrisation's (a whole voxel in contracted
    space, half a voxel elsewhere) and the reason says so; set, it is kept."""
    import numpy as np

    from nerfgauge.nerf.config import STEP_RATIOS, resolve, step_ratio_of

    aabb = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    c2w = np.tile(np.eye(4), (4, 1, 1))
    c2w[:, :3, 3] = [[0, 0, 4], [4, 0, 0], [0, 4, 0], [-4, 0, 0]]
    auto, reasons = resolve(TrainConfig(dataset="d", steps=1, parametrisation=kind), None, aabb, c2w, 100.0, 64)
    assert auto.step_ratio == STEP_RATIOS[kind] == step_ratio_of(auto)
    assert (auto.step_ratio == 1.0) == (kind == "contracted") and kind in reasons["step_ratio"]
    fixed, reasons = resolve(TrainConfig(dataset="d", steps=1, parametrisation=kind, step_ratio=0.25), None, aabb,
                             c2w, 100.0, 64)
    assert fixed.step_ratio == 0.25 and reasons["step_ratio"] == "set on the command line"


@pytest.mark.parametrize("kind", ["bounded", "contracted", "forward"])
def test_the_batch_follows_the_parametrisation_unless_set(kind):
    """Unset, a step's rays are the parametrisation's (2048 in contracted space, whose rays
    keep ten times the samples, 4096 elsewhere) and the reason says so; set, it is kept."""
    import numpy as np

    from nerfgauge.nerf.config import BATCH_RAYS, resolve

    aabb = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    c2w = np.tile(np.eye(4), (4, 1, 1))
    c2w[:, :3, 3] = [[0, 0, 4], [4, 0, 0], [0, 4, 0], [-4, 0, 0]]
    auto, reasons = resolve(TrainConfig(dataset="d", steps=1, parametrisation=kind), None, aabb, c2w, 100.0, 64)
    assert auto.batch_rays == BATCH_RAYS[kind] == (2048 if kind == "contracted" else 4096)
    assert kind in reasons["batch_rays"] and str(auto.batch_rays) in reasons["batch_rays"]
    fixed, reasons = resolve(TrainConfig(dataset="d", steps=1, parametrisation=kind, batch_rays=512), None, aabb,
                             c2w, 100.0, 64)
    assert fixed.batch_rays == 512 and reasons["batch_rays"] == "set on the command line"


def test_an_orbit_around_far_content_gets_the_ball_its_views_hold():
    """Orbit cameras looking at a target among far terrain: with the view's half angle the
    inner ball is VIEW_BALL_FACTOR x the view's half-width at the target (the cameras sit in
    the shell); without it, or when a camera does not have the target in view, or when the
    cameras look outward, the ball holds the cameras as before."""
    from nerfgauge.nerf.parametrisation import VIEW_BALL_FACTOR, contraction_frame

    target = np.array([0.0, 0.0, 0.3])
    orbit = np.stack([_camera(target + 3.2 * np.array([math.cos(a), math.sin(a), 0.2]), target)
                      for a in np.linspace(0, 6, 12)])
    terrain = np.array([[-100.0, -100.0, -1.0], [100.0, 100.0, 30.0]])
    distance = 3.2 * math.sqrt(1 + 0.2 ** 2)
    tan_half = math.tan(math.radians(20))
    centre, radius = contraction_frame(terrain, orbit, tan_half)
    assert np.allclose(centre, target, atol=1e-6)
    assert radius == pytest.approx(VIEW_BALL_FACTOR * distance * tan_half) and radius < distance
    assert contraction_frame(terrain, orbit)[1] == pytest.approx(1.1 * distance)
    # one camera turned 30 degrees away: the target leaves its 20-degree half view
    turned = orbit.copy()
    turn = np.array([[math.cos(0.52), -math.sin(0.52), 0], [math.sin(0.52), math.cos(0.52), 0], [0, 0, 1]])
    turned[0, :3, :3] = turn @ turned[0, :3, :3]
    assert contraction_frame(terrain, turned, tan_half)[1] == pytest.approx(
        1.1 * float(np.linalg.norm(turned[:, :3, 3] - contraction_frame(terrain, turned)[0], axis=1).max()))
    outward = np.stack([_camera((0.4 * math.cos(a), 0.4 * math.sin(a), 0.3),
                                (2 * math.cos(a), 2 * math.sin(a), 0.3)) for a in np.linspace(0, 6, 12)])
    assert contraction_frame(terrain, outward, tan_half)[1] == pytest.approx(contraction_frame(terrain, outward)[1])


def _edges_with_the_ball_from_zero(o, d, grid_step):
    """The interval edges before cameras could sit outside the ball (the oracle for rays
    that start inside it): uniform from 0 to the exit, disparity-uniform beyond. Unit ball."""
    b = (o * d).sum(-1)
    disc = b * b - ((o * o).sum(-1) - 1)
    t_exit = torch.where(disc > 0, -b + disc.clamp_min(0).sqrt(), (-b).clamp_min(0)).clamp_min(0)
    k = torch.arange(max(1, math.ceil(float(t_exit.max()) / grid_step)) + 1, dtype=o.dtype) * grid_step
    n_outer = max(1, math.ceil((1 - grid_step) / grid_step))
    u = (1 - torch.arange(1, n_outer + 1, dtype=o.dtype) * grid_step).clamp_min(grid_step)
    return torch.cat([torch.minimum(k[None, :], t_exit[:, None]), t_exit[:, None] + (1 / u[None, :] - 1)], dim=1)


def _positive_intervals(edges):
    lengths = edges[:, 1:] - edges[:, :-1]
    rays, cols = (lengths > 0).nonzero(as_tuple=True)
    return rays, edges[rays, cols], lengths[rays, cols]


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.02, 0.05, 0.1]))
def test_contracted_edges_from_inside_the_ball_are_unchanged_and_from_outside_disparity_spaced(seed, grid_step):
    """Rays starting in the ball get exactly the intervals they always had. A camera
    outside it marches towards it in steps of one grid_step of contracted radius (exact
    on radial rays: u = 1 / r from 1 / r0 to 1), not in the ball's fine steps, and its
    edges still start at 0, never decrease and stay finite."""
    g = torch.Generator().manual_seed(seed)
    space = Space("contracted", [[-2.0] * 3, [2.0] * 3], centre=[0.0, 0.0, 0.0], radius=1.0)
    inside = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1) \
        * torch.rand(64, 1, generator=g, dtype=torch.float64) * 0.99
    directions = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    got, want = _positive_intervals(space.ray_edges(inside, directions, grid_step)), \
        _positive_intervals(_edges_with_the_ball_from_zero(inside, directions, grid_step))
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    # radial rays from 1.5 to 6 radii out, pointing at the centre
    r0 = 1.5 + 4.5 * torch.rand(32, 1, generator=g, dtype=torch.float64)
    towards = torch.nn.functional.normalize(torch.randn(32, 3, generator=g, dtype=torch.float64), dim=-1)
    edges = space.ray_edges(-towards * r0, towards, grid_step)
    assert torch.isfinite(edges).all() and (edges[:, 0] == 0).all() and (edges[:, 1:] >= edges[:, :-1]).all()
    rays, start, length = _positive_intervals(edges)
    before = start + length <= (r0[rays, 0] - 1) + 1e-9  # intervals before the ball's surface
    far_end, near_end = r0[rays, 0] - start, r0[rays, 0] - start - length  # radii; contracted: 2 - 1 / r
    step = (2 - 1 / far_end[before]) - (2 - 1 / near_end[before])
    assert (step <= grid_step * (1 + 1e-9)).all()
    per_ray = torch.bincount(rays[before], minlength=32)
    assert (per_ray <= torch.ceil((1 - 1 / r0[:, 0]) / grid_step) + 1).all()


# --- the rule on captures nobody tuned it on (issue 34) --------------------------------


def _planned_capture(scene, views=40, size=16):
    """(aabb [2, 3], train c2w [n, 4, 4], share of train pixel-centre rays that hit the
    scene's meshes): the capture `nerfgauge generate SCENE` would make, without rendering
    (rays cast with trimesh against the ground-truth meshes; alpha 1 is full coverage, the
    pixel-centre hit share is its no-render stand-in)."""
    from nerfgauge.core.camera import pixel_rays
    from nerfgauge.generate.pipeline import GenerateConfig, plan

    the_plan = plan(GenerateConfig(scene=scene, views=views, val_views=0, test_views=2, width=size, height=size,
                                   spp=1))
    parts = [shape.mesh() for shape in the_plan.scene.shapes]
    if not parts:
        return np.asarray(the_plan.scene.aabb), the_plan.poses["train"], 0.0
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    mesh = trimesh.Trimesh(np.concatenate([p.vertices for p in parts]),
                           np.concatenate([p.faces + o for p, o in zip(parts, offsets)]), process=False)
    rays = [pixel_rays(pose, the_plan.intrinsics) for pose in the_plan.poses["train"]]
    origins = np.concatenate([o.reshape(-1, 3) for o, _ in rays])
    directions = np.concatenate([d.reshape(-1, 3) for _, d in rays])
    try:  # Open3D's BVH casts these in milliseconds; trimesh's rtree fallback takes minutes
        import open3d as o3d
    except Exception:  # every 8th ray (a share of 1.0 stays 1.0; 2000+ rays still see sky)
        hit = mesh.ray.intersects_any(origins[::8], directions[::8])
    else:
        caster = o3d.t.geometry.RaycastingScene()
        caster.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                             o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
        found = caster.cast_rays(o3d.core.Tensor(np.concatenate([origins, directions], 1).astype(np.float32)))
        hit = np.isfinite(found["t_hit"].numpy())
    return np.asarray(the_plan.scene.aabb), the_plan.poses["train"], float(hit.mean())


import trimesh  # noqa: E402  (used by the helper above; trimesh is a dependency)


def test_a_closed_room_seen_from_inside_is_bounded_because_it_is_closed():
    """The room's walls reach 10x beyond the cameras' cluster, which made the old rule
    (cameras inside, AABB reaching > 8 camera radii) contract it; every ray ends on a wall
    or the furniture, and the cameras look outwards: everything seen is in the box, one
    grid. Without the evidence (opaque unknown) or with sky in view the old rule stands."""
    aabb, c2w, opaque = _planned_capture("room")
    assert opaque == 1.0  # closed: no pixel-centre ray leaves the room
    kind, reason = choose_parametrisation(None, aabb, c2w, opaque)
    assert kind == "bounded" and "closed" in reason and "100.00% of training pixels opaque" in reason, reason
    kind, reason = choose_parametrisation(None, aabb, c2w, None)
    assert kind == "contracted" and "reaches" in reason, reason
    kind, reason = choose_parametrisation(None, aabb, c2w, 0.8)
    assert kind == "contracted" and "the capture is open" in reason, reason


def test_a_closed_orbit_keeps_contraction():
    """far-reaching's orbit with no sky in view (opaque 1.0) is still an orbit inside a
    world 30x its radius: the cameras look at a common point ahead, so closure does not
    make it a room."""
    aabb, c2w, _ = _planned_capture("far-reaching", views=12)
    kind, reason = choose_parametrisation(None, aabb, c2w, 1.0)
    assert kind == "contracted" and "common point" in reason, reason


@pytest.mark.parametrize("scene, expected", [("far-object", "bounded"), ("forward-near", "forward")])
def test_the_other_check_scenes(scene, expected):
    """A small object seen from far: cameras outside a small AABB, from every side ->
    bounded. A forward capture of near content (depth ratio ~5) -> forward (measured at
    64 px, 400 steps: BENCHMARKS.md)."""
    aabb, c2w, opaque = _planned_capture(scene)
    kind, reason = choose_parametrisation(None, aabb, c2w, opaque)
    assert kind == expected, reason


@pytest.mark.parametrize("scene, expected", [
    ("thin", "bounded"), ("checker-fine", "bounded"), ("mirror", "bounded"), ("depth-range", "forward"),
    ("hdr", "bounded"), ("glass", "bounded"), ("empty", "bounded"), ("tiny", "bounded"),
    ("far-reaching", "contracted"), ("inside", "bounded")])
def test_bench_hard_picks_do_not_change(scene, expected):
    """bench hard's captures (its 40 views; 16 px rays suffice for the hit share): the
    same pick as before the closure rule, with and without the capture's opacity."""
    aabb, c2w, opaque = _planned_capture(scene)
    assert choose_parametrisation(None, aabb, c2w, opaque)[0] == expected
    assert choose_parametrisation(None, aabb, c2w, None)[0] == expected
    if scene in ("inside", "far-reaching"):
        assert opaque < 0.999  # sky in view: open captures


def test_opaque_share_counts_rays_whose_alpha_is_one_within_8_bit_rounding():
    from nerfgauge.nerf.data import RayBatch
    from nerfgauge.nerf.train import opaque_share

    rgba = torch.zeros((4, 4))
    rgba[:, 3] = torch.tensor([1.0, 254.6 / 255, 254 / 255, 0.0])  # 8-bit 255 decoded with rounding error; 254
    rays = RayBatch(torch.zeros((4, 3)), torch.zeros((4, 3)), rgba)
    assert opaque_share(rays) == 0.5
    assert opaque_share(RayBatch(torch.zeros((0, 3)), torch.zeros((0, 3)), None)) is None
