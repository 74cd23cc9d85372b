"""Issue 52, item 2: an edges render gives rays of their own only to the points of a pixel
where the centre render changes (nerf.frames.changing_points_frame), checked against a
per-pixel loop built independently: which points change (a loop over every pixel's
neighbouring centres), their rays (the pinhole's rays with the principal point moved), the
rest interpolated between centres; a straight edge's render is the whole box render."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nerfgauge.core.camera import Intrinsics, SplitCameras, look_at, pixel_rays
from nerfgauge.core.pixel_edges import changes_towards
from nerfgauge.nerf.config import CHANGE_STEP
from nerfgauge.nerf import frames
from nerfgauge.nerf.data import jittered_direction, pixel_footprints
from nerfgauge.nerf.frame_assembly import changing_points, sub_directions, touched_box_means
from nerfgauge.nerf.frames import box_frame, interpolate_centres, pixel_offsets, rgba_png
from nerfgauge.nerf.rendering import pixel_mean

CPU = torch.device("cpu")


@pytest.fixture(params=["compiled", "torch"])
def assembly(request, monkeypatch):
    """An edges frame's host work as nerf.frame_assembly's compiled loops (the CPU's) or as
    the torch ops a GPU runs: every frame test below holds for both."""
    if request.param == "torch":
        monkeypatch.setattr(frames, "assembles_compiled", lambda device: False)
    return request.param


def _cameras(seed: int = 5, width: int = 24, height: int = 20):
    rng = np.random.default_rng(seed)
    c2w = look_at(rng.normal(size=3) * 3, rng.normal(size=3) * 0.3)
    intrinsics = Intrinsics(width=width, height=height, fx=20.0, fy=21.0, cx=width / 2 + 0.1, cy=height / 2 - 0.2)
    return SplitCameras("test", ("a",), np.stack([c2w]), intrinsics), c2w, intrinsics


def _shifted_rays(c2w, intrinsics, offset):
    """Rays through (column + 0.5 + x, row + 0.5 + y): the pinhole's with the principal point moved."""
    moved = replace(intrinsics, cx=intrinsics.cx - offset[0], cy=intrinsics.cy - offset[1])
    origins, directions = pixel_rays(c2w, moved)
    return torch.from_numpy(origins.reshape(-1, 3)).float(), torch.from_numpy(directions.reshape(-1, 3)).float()


class Counting:
    """A stand-in model's render, counting the rays it is asked for."""

    def __init__(self, render):
        self.rays, self._render = 0, render

    def render(self, origins, directions):
        self.rays += len(directions)
        return self._render(origins, directions)


def plane_edge(origins, directions):
    """A sharp straight edge across the image: colour by the side of a plane, opacity 1."""
    side = (directions @ torch.tensor([0.6, 0.0, 0.8]) > 0).float()
    rgb = torch.stack([side, 1 - side, 0.5 * torch.ones_like(side)], dim=-1)
    return SimpleNamespace(rgb=rgb, opacity=torch.ones_like(side), depth=directions[:, 0])


def disc(axis, cos_radius):
    """A sharp disc in direction space over nothing: premultiplied colour, opacity 0 or 1."""
    def render(origins, directions):
        inside = (directions @ axis > cos_radius).float()
        rgb = inside[:, None] * torch.tensor([0.9, 0.2, 0.1])
        return SimpleNamespace(rgb=rgb, opacity=inside, depth=directions[:, 0])
    return render


def _disc_model(c2w, intrinsics, radius_px: float = 5.5):
    _, directions = pixel_rays(c2w, intrinsics)
    axis = torch.from_numpy(directions[intrinsics.height // 2 - 1, intrinsics.width // 2 + 2]).float()
    return Counting(disc(axis, float(np.cos(radius_px / intrinsics.fx))))


# --------------------------------------------------------------------------------------
# which points change


def _changes_loop(rgba, offsets, step):
    """changes_towards by a loop over every pixel and point: the centres of the pixel and of
    its neighbours toward the point (clamped into the image) differ by more than `step` in
    premultiplied colour or in alpha; the centre itself has its ray already."""
    height, width = rgba.shape[:2]
    out = np.zeros((len(offsets), height, width), dtype=bool)
    for s, (x, y) in enumerate(offsets):
        if x == 0 and y == 0:
            continue
        for i in range(height):
            for j in range(width):
                rows = {i, min(max(i + int(np.sign(y)), 0), height - 1)}
                columns = {j, min(max(j + int(np.sign(x)), 0), width - 1)}
                corners = np.array([np.append(rgba[r, c, :3] * rgba[r, c, 3], rgba[r, c, 3])
                                    for r in rows for c in columns])
                out[s, i, j] = bool((corners.max(axis=0) - corners.min(axis=0)).max() > step)
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_points_that_change_are_those_whose_neighbouring_centres_differ(seed):
    rng = np.random.default_rng(seed)
    # blocks of colour (steps between some neighbours, none inside a block), some partial alpha
    blocks = rng.uniform(size=(4, 5, 4))
    rgba = np.repeat(np.repeat(blocks, 3, axis=0), 3, axis=1)[:11, :13].copy()
    rgba[..., 3] = np.where(rng.uniform(size=rgba.shape[:2]) < 0.8, 1.0, rgba[..., 3])
    rgba[..., 3] = np.where(rng.uniform(size=rgba.shape[:2]) < 0.1, 0.0, rgba[..., 3])
    rgba[..., :3] += rng.uniform(-0.03, 0.03, size=rgba[..., :3].shape)  # below any step
    for per_axis in (2, 3):
        offsets = pixel_offsets(per_axis)
        for step in (0.1, 0.02):
            assert np.array_equal(changes_towards(rgba, offsets, step), _changes_loop(rgba, offsets, step))
    assert not changes_towards(rgba, pixel_offsets(1), 0.0).any()  # the centre itself never needs another ray


def test_a_lone_different_pixel_changes_its_own_points_and_its_neighbours_points_toward_it():
    rgba = np.ones((7, 8, 4)) * [0.2, 0.4, 0.6, 1.0]
    rgba[3, 4, :3] = [0.9, 0.4, 0.6]
    changes = changes_towards(rgba, pixel_offsets(3), 0.1)  # [9, H, W]; point 4 is the centre
    assert changes[:, 3, 4].sum() == 8  # every point of its own but the centre
    assert changes[:, 3, 5].sum() == 3 and changes[:, 2, 4].sum() == 3  # the 3 points toward it
    assert changes[:, 2, 5].sum() == 1 and changes[:, 4, 3].sum() == 1  # the diagonal's corner point
    assert changes.sum() == 8 + 4 * 3 + 4 * 1
    assert not changes_towards(rgba * 0 + [0.2, 0.4, 0.6, 1.0], pixel_offsets(3), 0.0).any()
    # a step in alpha alone (a colour hidden behind alpha 0 is no step)
    faint = np.ones((7, 8, 4)) * [0.2, 0.4, 0.6, 1.0]
    faint[3, 4, 3] = 0.9
    assert changes_towards(faint, pixel_offsets(3), 0.05).sum() == 24
    hidden = np.zeros((7, 8, 4))
    hidden[3, 4, :3] = 1.0
    assert not changes_towards(hidden, pixel_offsets(3), 0.05).any()


# --------------------------------------------------------------------------------------
# the compiled assembly against the torch and numpy ops


@pytest.mark.parametrize("seed, height, width", [(0, 13, 17), (1, 13, 17), (2, 1, 17), (3, 13, 1)])
def test_the_compiled_changing_points_are_changes_towards_of_the_8_bit_render(seed, height, width):
    """Blocks of colour with partial and zero alpha, 8-bit as the PNG; frames one pixel high
    or wide included (the border repeated on both sides)."""
    rng = np.random.default_rng(seed)
    blocks = rng.uniform(size=(5, 6, 3)).astype(np.float32)
    rgb = np.repeat(np.repeat(blocks, 3, axis=0), 3, axis=1)[:height, :width].reshape(-1, 3)
    opacity = np.where(rng.uniform(size=height * width) < 0.7, 1.0, rng.uniform(size=height * width))
    opacity = np.where(rng.uniform(size=height * width) < 0.1, 0.0, opacity).astype(np.float32)
    rgb = (rgb + rng.uniform(-0.01, 0.01, size=rgb.shape)).astype(np.float32) * opacity[:, None]
    rgba8 = rgba_png(rgb, opacity, height, width)
    for per_axis in (2, 3, 4):
        offsets = pixel_offsets(per_axis)
        offsets = offsets[np.any(offsets != 0, axis=1)]
        for step in (0.3, 0.02, 0.004):  # 0.004: one 8-bit level (1 / 255) exceeds it
            expected = np.nonzero(changes_towards(rgba8 / 255.0, offsets, step).reshape(len(offsets), -1))
            point, pixel = changing_points(rgba8, offsets, step)
            assert np.array_equal(point, expected[0]) and np.array_equal(pixel, expected[1])
            assert len(point) > 0  # the comparison is not of two empty lists
            if step == 0.3:  # not of two full ones either: the blocks' insides agree at the largest step
                assert len(point) < len(offsets) * height * width


@pytest.mark.parametrize("width, height", [(24, 20), (1, 9), (7, 1)])
def test_the_compiled_sub_directions_are_the_footprints_jittered_directions(width, height):
    """Every pixel and point of a frame, the border and axes one pixel long included (a
    footprint with no step along it): the compiled direction equals jittered_direction of
    pixel_footprints to float32 rounding."""
    rng = np.random.default_rng(3)
    c2w = look_at(rng.normal(size=3) * 3, rng.normal(size=3) * 0.3)
    intrinsics = Intrinsics(width=width, height=height, fx=20.0, fy=21.0, cx=width / 2 + 0.1, cy=height / 2 - 0.2)
    _, directions = pixel_rays(c2w, intrinsics)
    offsets = pixel_offsets(4)
    point, pixel = (part.ravel() for part in np.meshgrid(np.arange(len(offsets)), np.arange(width * height),
                                                         indexing="ij"))
    expected = jittered_direction(torch.from_numpy(directions.reshape(-1, 3).astype(np.float32))[pixel],
                                  torch.from_numpy(pixel_footprints(directions, c2w))[pixel],
                                  torch.from_numpy(offsets.astype(np.float32))[point])
    got = sub_directions(directions, -c2w[:3, 2].copy(), offsets, point, pixel)
    assert np.abs(got - expected.numpy()).max() < 1e-6  # unit vectors in float32: a few ulps
    # the points do move: off-centre points differ from the centre's direction along a long axis
    assert np.abs(got - directions.reshape(-1, 3)[pixel]).max() > 0.2 / max(intrinsics.fx, intrinsics.fy)


@pytest.mark.parametrize("per_axis", [2, 3, 4])
def test_the_compiled_box_means_are_the_interpolated_and_rendered_points_mean_in_linear_light(per_axis):
    rng = np.random.default_rng(per_axis)
    height, width = 9, 11
    opacity = np.where(rng.uniform(size=height * width) < 0.3, rng.uniform(size=height * width), 1.0)
    opacity = opacity.astype(np.float32)
    rgb = (rng.uniform(size=(height * width, 3)) * opacity[:, None]).astype(np.float32)
    offsets = pixel_offsets(per_axis)
    offsets = offsets[np.any(offsets != 0, axis=1)]
    changes = rng.uniform(size=(len(offsets), height * width)) < 0.15
    changes[:, :2 * width] = False  # two untouched rows
    point, pixel = np.nonzero(changes)
    sub_opacity = rng.uniform(size=len(point)).astype(np.float32)
    sub_rgb = (rng.uniform(size=(len(point), 3)) * sub_opacity[:, None]).astype(np.float32)
    got_rgb, got_opacity = touched_box_means(rgb, opacity, height, width, offsets, per_axis % 2 == 1, point, pixel,
                                             sub_rgb, sub_opacity)
    # the oracle: every point interpolated, the rendered ones put in place, pixel_mean
    centre = torch.from_numpy(np.concatenate([rgb, opacity[:, None]], axis=1))
    every = torch.arange(height * width)
    values = interpolate_centres(centre, height, width, every, offsets)  # [S, P, 4]
    values[point, pixel] = torch.from_numpy(np.concatenate([sub_rgb, sub_opacity[:, None]], axis=1))
    if per_axis % 2 == 1:
        values = torch.cat([values, centre[None]])
    mean_rgb, mean_opacity = pixel_mean(values[..., :3], values[..., 3])
    touched = changes.any(axis=0)
    assert 0 < touched.sum() < touched.size
    assert np.abs(got_rgb[touched] - mean_rgb.numpy()[touched]).max() < 1e-5
    assert np.abs(got_opacity[touched] - mean_opacity.numpy()[touched]).max() < 1e-6
    assert np.array_equal(got_rgb[~touched], rgb[~touched]) and np.array_equal(got_opacity[~touched], opacity[~touched])


# --------------------------------------------------------------------------------------
# the frame


def _frame_oracle(model, cameras, c2w, intrinsics, per_axis, step=CHANGE_STEP):
    """The changes render by a per-pixel loop: each point's ray where the centres around it
    differ, else the bilinear interpolation of those centres; a pixel none of whose points
    changes keeps its centre value."""
    height, width = intrinsics.height, intrinsics.width
    centre = model.render(*_shifted_rays(c2w, intrinsics, (0.0, 0.0)))
    centre_rgba = torch.cat([centre.rgb, centre.opacity[:, None]], 1).numpy().reshape(height, width, 4)
    straight = rgba_png(centre.rgb.numpy(), centre.opacity.numpy(), height, width) / 255.0
    offsets = pixel_offsets(per_axis)
    changes = _changes_loop(straight, offsets, step)
    out = centre_rgba.copy()
    for i in range(height):
        for j in range(width):
            if not changes[:, i, j].any():
                continue
            values = []
            for s, (x, y) in enumerate(offsets):
                if changes[s, i, j]:
                    ray = model.render(*(part.view(height, width, 3)[i, j][None] for part in
                                         _shifted_rays(c2w, intrinsics, (x, y))))
                    values.append(np.concatenate([ray.rgb[0].numpy(), ray.opacity.numpy()]))
                else:
                    i2, j2 = min(max(i + int(np.sign(y)), 0), height - 1), min(max(j + int(np.sign(x)), 0), width - 1)
                    ax, ay = abs(x), abs(y)
                    values.append((1 - ax) * (1 - ay) * centre_rgba[i, j] + ax * (1 - ay) * centre_rgba[i, j2]
                                  + (1 - ax) * ay * centre_rgba[i2, j] + ax * ay * centre_rgba[i2, j2])
            # the box mean in linear light, as the ground truth's (nerf.rendering.pixel_mean,
            # checked against its own oracle in tests/test_rendering.py)
            stacked = torch.from_numpy(np.array(values, dtype=np.float32))  # [S, 4]
            mean_rgb, mean_opacity = pixel_mean(stacked[:, None, :3], stacked[:, None, 3])
            out[i, j] = np.append(mean_rgb[0].numpy(), mean_opacity.numpy())
    return out.reshape(-1, 4), changes


@pytest.mark.parametrize("per_axis", [2, 3, 4])  # 4: the rung nerf.schedule.FINER_EDGE_POINTS_PER_AXIS
def test_a_changes_frame_is_its_points_rays_where_the_centres_differ_and_interpolated_elsewhere(per_axis, assembly):
    cameras, c2w, intrinsics = _cameras()
    model = _disc_model(c2w, intrinsics)
    rgb, opacity, depth = box_frame(model, cameras, 0, per_axis, None, 1, CPU, edges_only=True)
    expected, changes = _frame_oracle(_disc_model(c2w, intrinsics), cameras, c2w, intrinsics, per_axis)
    assert 0 < changes.any(axis=0).sum() < changes[0].size  # the disc's rim, not the whole image
    # float32 rays and sums of 9 values: a few ulps
    assert np.abs(torch.cat([rgb, opacity[:, None]], 1).numpy() - expected).max() < 1e-5
    untouched = torch.from_numpy(~changes.any(axis=0).reshape(-1))
    centre = box_frame(_disc_model(c2w, intrinsics), cameras, 0, 1, None, 1, CPU)
    assert torch.equal(rgb[untouched], centre[0][untouched]) and torch.equal(opacity[untouched], centre[1][untouched])
    assert torch.equal(depth, centre[2])  # the centre rays' depth, as the ground truth's
    # one ray per point that changes, beyond the centre render
    assert model.rays == intrinsics.width * intrinsics.height + int(changes.sum())


@pytest.mark.parametrize("per_axis", [2, 3])
def test_a_straight_edge_renders_as_the_whole_box_with_fewer_rays_than_its_edge_pixels(per_axis, assembly):
    """A straight line that crosses the square (or segment) between centres separates some
    of them, so every point it passes gets its ray and every other point lies between equal
    centres: the changes render is the box render of every pixel."""
    cameras, _, intrinsics = _cameras()
    model, edge_pixels = Counting(plane_edge), Counting(plane_edge)
    rgb, opacity, _ = box_frame(model, cameras, 0, per_axis, None, 1, CPU, edges_only=True)
    box = box_frame(Counting(plane_edge), cameras, 0, per_axis, None, 1, CPU)
    assert torch.allclose(rgb, box[0], rtol=0, atol=1e-6) and torch.allclose(opacity, box[1], rtol=0, atol=1e-6)
    assert bool(((box[0][:, 0] > 0) & (box[0][:, 0] < 1)).any())  # mixed pixels: the edge crosses the image
    old = box_frame(edge_pixels, cameras, 0, per_axis, None, 1, CPU, edges_only=True, sub_rays="edge-pixels")
    assert torch.allclose(old[0], box[0], rtol=0, atol=1e-6)
    assert model.rays < edge_pixels.rays


def test_a_frame_where_nothing_changes_is_its_centre_render_from_one_pass(assembly):
    cameras, _, intrinsics = _cameras()

    def smooth(origins, directions):  # a ramp far below the colour step between neighbours
        value = 0.5 + 0.01 * directions[:, :1].expand(-1, 3)
        return SimpleNamespace(rgb=value, opacity=torch.ones(len(directions)), depth=directions[:, 0])

    model = Counting(smooth)
    frame = box_frame(model, cameras, 0, 3, None, 1, CPU, edges_only=True)
    assert model.rays == intrinsics.width * intrinsics.height
    assert all(torch.equal(a, b) for a, b in zip(frame, box_frame(Counting(smooth), cameras, 0, 1, None, 1, CPU)))


def gentle_ramp(c2w):
    """Colour rising across the image by about 0.02 a pixel in red (0.4 per unit of the
    direction along the camera's x axis, pixels 1/20 apart), half and a quarter of that in
    green and blue: neighbouring centres differ by less than the default step."""
    right = torch.from_numpy(np.asarray(c2w, dtype=np.float32)[:3, 0])

    def render(origins, directions):
        value = 0.5 + 0.4 * (directions @ right)[:, None] * torch.tensor([1.0, 0.5, 0.25])
        return SimpleNamespace(rgb=value, opacity=torch.ones(len(directions)), depth=directions[:, 0])
    return render


def test_a_smaller_change_step_gives_rays_to_centres_the_default_interpolates(assembly):
    """The ramp's neighbouring centres differ by 0.01-0.03 in the 8-bit render: below the
    default step nothing changes (the centre render); at 0.005 every point between them has
    its ray, and the frame is the per-pixel oracle's at that step."""
    cameras, c2w, intrinsics = _cameras()
    ramp = gentle_ramp(c2w)
    default = Counting(ramp)
    box_frame(default, cameras, 0, 3, None, 1, CPU, edges_only=True)
    assert default.rays == intrinsics.width * intrinsics.height
    model = Counting(ramp)
    rgb, opacity, _ = box_frame(model, cameras, 0, 3, None, 1, CPU, edges_only=True, change_step=0.005)
    expected, changes = _frame_oracle(Counting(ramp), cameras, c2w, intrinsics, 3, step=0.005)
    assert changes.any(axis=0).mean() > 0.5  # most pixels: the ramp steps between every column
    assert model.rays == intrinsics.width * intrinsics.height + int(changes.sum())
    assert np.abs(torch.cat([rgb, opacity[:, None]], 1).numpy() - expected).max() < 1e-5
    # a step of 1 (no channel differs by more) is the centre render
    centre = box_frame(Counting(ramp), cameras, 0, 1, None, 1, CPU)
    assert all(torch.equal(a, b) for a, b in zip(box_frame(Counting(ramp), cameras, 0, 3, None, 1, CPU,
                                                           edges_only=True, change_step=1.0), centre))


def test_an_unknown_sub_rays_choice_is_refused():
    cameras, _, _ = _cameras()
    with pytest.raises(ValueError, match="sub_rays"):
        box_frame(Counting(plane_edge), cameras, 0, 3, None, 1, CPU, edges_only=True, sub_rays="all")


# --------------------------------------------------------------------------------------
# `nerfgauge render` and `bench render`


@pytest.fixture(scope="module")
def edges_run(tiny_dataset, tmp_path_factory):
    """A 4-step edges run whose model.pt says it renders 3 x 3 points on its edges."""
    from nerfgauge.nerf.checkpoint import load_checked, save_atomic
    from nerfgauge.nerf.config import TrainConfig
    from nerfgauge.nerf.train import train

    run = tmp_path_factory.mktemp("runs") / "edges"
    train(TrainConfig(dataset=str(tiny_dataset), steps=4, pixel_filter="edges", threads=1), run, progress=False)
    payload = load_checked(run / "model.pt")
    payload["config"]["render_filter"] = "edges-3x3"
    save_atomic(payload, run / "model.pt")
    return run


@pytest.mark.slow  # trains a model (4 steps, its dataset)
def test_a_render_is_deterministic_and_its_timing_says_which_points_got_rays(edges_run, tmp_path):
    from nerfgauge.nerf.render_views import render_split

    first = render_split(edges_run, "test", tmp_path / "a", threads=2, progress=False)
    second = render_split(edges_run, "test", tmp_path / "b", threads=2, progress=False)
    assert first["sub_rays"] == "changes" and first["pixel_samples"] == 3 and first["edges_only"]
    assert first["ms_per_frame"] > 0 and first["cpu_ms_per_frame"] > 0 and first["frames"] == second["frames"] > 0
    for png in sorted((tmp_path / "a").rglob("*.png")):
        assert png.read_bytes() == (tmp_path / "b" / png.relative_to(tmp_path / "a")).read_bytes()
    assert first["change_step"] == CHANGE_STEP
    old = render_split(edges_run, "test", tmp_path / "old", threads=2, progress=False, sub_rays="edge-pixels")
    assert old["sub_rays"] == "edge-pixels" and "change_step" not in old
    finer = render_split(edges_run, "test", tmp_path / "finer", threads=2, progress=False, change_step=0.0)
    assert finer["change_step"] == 0.0


@pytest.mark.slow  # trains a model (4 steps, its dataset)
def test_a_run_renders_by_the_change_step_it_chose_unless_told_another(edges_run, tmp_path):
    import shutil
    from nerfgauge.core.errors import InputError
    from nerfgauge.nerf.checkpoint import load_checked, save_atomic
    from nerfgauge.nerf.render_views import render_split

    run = tmp_path / "run"
    shutil.copytree(edges_run, run)
    payload = load_checked(run / "model.pt")
    payload["config"]["render_change_step"] = 0.01
    save_atomic(payload, run / "model.pt")
    assert render_split(run, "test", tmp_path / "chosen", threads=1, progress=False)["change_step"] == 0.01
    told = render_split(run, "test", tmp_path / "told", threads=1, progress=False, change_step=CHANGE_STEP)
    assert told["change_step"] == CHANGE_STEP
    payload["config"]["render_change_step"] = 0.03  # not a step the choice takes: the model file is refused
    save_atomic(payload, run / "model.pt")
    with pytest.raises(InputError, match="change step"):
        render_split(run, "test", tmp_path / "bad", threads=1, progress=False)
    assert not (tmp_path / "bad").exists()


def test_an_unknown_sub_rays_choice_is_one_line_and_exit_2(tmp_path, capsys):
    from nerfgauge.cli import main
    from nerfgauge.core.errors import InputError
    from nerfgauge.nerf.render_views import render_split

    run = tmp_path / "run"  # refused before the model is read
    run.mkdir()
    with pytest.raises(InputError, match="--sub-rays"):
        render_split(run, "test", tmp_path / "r", progress=False, sub_rays="everywhere")
    assert not (tmp_path / "r").exists()
    assert main(["render", str(run), "--sub-rays", "everywhere", "--out", str(tmp_path / "r")]) == 2
    error = capsys.readouterr().err
    assert not (tmp_path / "r").exists() and "--sub-rays" in error and len(error.strip().splitlines()) == 1


@pytest.mark.parametrize("step", ["-0.01", "1.5", "nan", "inf", "fine"])
def test_a_change_step_outside_0_to_1_is_one_line_and_exit_2(tmp_path, capsys, step):
    from nerfgauge.cli import main
    from nerfgauge.core.errors import InputError
    from nerfgauge.nerf.render_views import render_split

    run = tmp_path / "run"
    run.mkdir()
    if step != "fine":
        with pytest.raises(InputError, match="--change-step"):
            render_split(run, "test", tmp_path / "r", progress=False, change_step=float(step))
    assert main(["render", str(run), "--change-step", step, "--out", str(tmp_path / "r")]) == 2
    error = capsys.readouterr().err
    assert not (tmp_path / "r").exists() and "--change-step" in error and len(error.strip().splitlines()) == 1


@pytest.mark.slow
def test_bench_render_times_and_scores_both_renders_and_refuses_other_runs(edges_run, tmp_path):
    import json

    from nerfgauge.core.errors import InputError
    from nerfgauge.orchestrate.bench.render import BEFORE, RENDERS, bench_render

    document = bench_render([edges_run], tmp_path / "bench", repeats=2, threads=1)
    row, = document["rows"]
    assert set(row["renders"]) == set(RENDERS)
    for render in row["renders"].values():
        assert len(render["ms_per_frame"]) == 2 and render["ms"] > 0 and np.isfinite(render["psnr"])
    assert row["renders"]["default"]["sub_rays"] == "changes" and row["renders"][BEFORE]["sub_rays"] == "edge-pixels"
    # the step the default render took (the run chose none: the default), none for the others
    assert row["renders"]["default"]["change_step"] == CHANGE_STEP and row["renders"][BEFORE]["change_step"] is None
    assert row["ms_ratio"] == pytest.approx(row["renders"]["default"]["ms"] / row["renders"][BEFORE]["ms"])
    assert row["cpu_ratio"] == pytest.approx(row["renders"]["default"]["cpu_ms"] / row["renders"][BEFORE]["cpu_ms"])
    assert row["psnr_change"] == pytest.approx(row["renders"]["default"]["psnr"] - row["renders"][BEFORE]["psnr"])
    assert json.loads((tmp_path / "bench" / "render.json").read_text())["command"].startswith("nerfgauge bench render")
    assert "edge-pixels-3x3" in (tmp_path / "bench" / "render.md").read_text()
    assert f"default (change step {CHANGE_STEP:g})" in (tmp_path / "bench" / "render.md").read_text()
    with pytest.raises(InputError, match="no model.pt"):
        bench_render([tmp_path / "bench"], tmp_path / "bench2")
    assert not (tmp_path / "bench2").exists()
