"""Thin-lens ground truth: the lens rays, Mitsuba's thinlens sensor, the generator's lens views.

Conventions (docs/conventions.md): a frame's lens is {"aperture_radius": A, "focus_distance": D}
in scene units; the plane z = -D in camera space (D along the optical axis) is in focus;
aperture 0 is the pinhole, bit for bit.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cli_errors import one_line_exit_2
from nerfgauge.core.camera import (
    Intrinsics,
    ThinLens,
    camera_directions,
    concentric_disk,
    lens_samples,
    look_at,
    pixel_rays,
    stratified_unit_square,
    thin_lens_rays,
)
from nerfgauge.core.errors import InputError

# --- the rays ---------------------------------------------------------------------------------


def test_aperture_zero_rays_are_the_pinhole_rays_bit_for_bit():
    c2w = look_at((2.0, -3.0, 1.0), (0.0, 0.1, 0.2))
    intrinsics = Intrinsics.from_fov(24, 16, 45.0)
    origins, directions = thin_lens_rays(c2w, intrinsics, ThinLens(0.0, 2.5), lens_samples(5, 0))
    pin_o, pin_d = pixel_rays(c2w, intrinsics)
    assert origins.shape == (5, 16, 24, 3)
    assert np.array_equal(origins, np.broadcast_to(pin_o, origins.shape))
    assert np.array_equal(directions, np.broadcast_to(pin_d, directions.shape))


def test_every_lens_ray_of_a_pixel_meets_its_focus_point_and_starts_on_the_lens():
    c2w = look_at((2.0, -3.0, 1.0), (0.0, 0.1, 0.2))
    intrinsics = Intrinsics.from_fov(20, 12, 50.0)
    lens = ThinLens(0.3, 2.0)
    disk = lens_samples(9, 1)
    origins, directions = thin_lens_rays(c2w, intrinsics, lens, disk)
    focus = lens.focus_distance * camera_directions(intrinsics) @ c2w[:3, :3].T + c2w[:3, 3]  # [H, W, 3]
    # the ray reaches the focus plane (camera z = -D) after t = |F - O| along d
    t = np.linalg.norm(focus[None] - origins, axis=-1, keepdims=True)
    np.testing.assert_allclose(origins + t * directions, np.broadcast_to(focus, origins.shape), atol=1e-12)
    local = (origins[:, 0, 0] - c2w[:3, 3]) @ c2w[:3, :3]  # [S, 3] camera space
    np.testing.assert_allclose(local[:, 2], 0, atol=1e-12)  # on the lens plane
    np.testing.assert_allclose(local[:, :2], lens.aperture_radius * disk, atol=1e-12)


def test_lens_samples_are_stratified_and_uniform_on_the_disc():
    square = stratified_unit_square(12, np.random.default_rng(3))  # 3 x 4 strata
    cells = {(int(x * 4), int(y * 3)) for x, y in square}
    assert len(cells) == 12  # one sample in each stratum
    disk = lens_samples(4096, 7)
    assert np.all(np.linalg.norm(disk, axis=1) <= 1 + 1e-12)
    # uniform on the unit disc: E[r^2] = 1/2, E[x] = E[y] = 0; stratified, so far tighter
    # than the 1/sqrt(n) of independent samples
    assert abs(np.mean(np.sum(disk**2, axis=1)) - 0.5) < 2e-3
    assert np.all(np.abs(disk.mean(axis=0)) < 2e-3)
    assert np.array_equal(lens_samples(16, (1, 2)), lens_samples(16, (1, 2)))  # seeded


def test_thin_lens_rays_equal_mitsuba_thinlens_rays(mi):
    """Our lens rays are the lines Mitsuba's thinlens sensor traces for the same aperture
    sample: Mitsuba maps it with the same concentric map, in its camera frame whose +X is
    our -X (camera.to_mitsuba), and starts rays at the near clip along the same line."""
    from nerfgauge.generate.render import sensor_dict

    width, height = 12, 8
    c2w = look_at((3.0, -2.0, 1.5), (0.1, 0.2, 0.3))
    intrinsics = Intrinsics.from_fov(width, height, 50.0)
    lens = ThinLens(0.2, 3.0)
    sensor = mi.load_dict(sensor_dict(mi, c2w, intrinsics, 1, lens))
    assert "ThinLens" in str(sensor)
    aperture_sample = np.array([[0.8, 0.3]])
    disk = concentric_disk(aperture_sample) * [-1.0, 1.0]  # Mitsuba's +X is our -X
    origins, directions = thin_lens_rays(c2w, intrinsics, lens, disk)
    for row, col in ((0, 0), (3, 7), (7, 11)):
        film = mi.Point2f((col + 0.5) / width, (row + 0.5) / height)
        ray, _ = sensor.sample_ray(0.0, 0.0, film, mi.Point2f(*(float(x) for x in aperture_sample[0])))
        o, d = (np.array([np.asarray(v[k]).ravel()[0] for k in range(3)], np.float64) for v in (ray.o, ray.d))
        np.testing.assert_allclose(d, directions[0, row, col], atol=1e-5)
        np.testing.assert_allclose(np.cross(o - origins[0, row, col], d), 0, atol=1e-5)


@pytest.mark.parametrize("aperture,focus,text", [(-0.1, 2.0, "aperture"), (0.1, 0.0, "focus distance"),
                                                 (0.1, -2.0, "focus distance"), (float("nan"), 2.0, "aperture"),
                                                 (0.1, float("inf"), "focus distance")])
def test_bad_lens_is_one_input_error(aperture, focus, text):
    with pytest.raises(InputError, match=text):
        ThinLens(aperture, focus)


# --- Mitsuba through the lens -------------------------------------------------------------------

FOV = 40.0
SIDE = 32


def _render(mi, scene, lens, spp, seed):
    from nerfgauge.generate.render import render_rgba

    intrinsics = Intrinsics.from_fov(SIDE, SIDE, FOV)
    return render_rgba(mi, scene, np.eye(4), intrinsics, spp, seed, lens).astype(np.float64)


def test_aperture_zero_renders_the_pinhole_image_bit_for_bit(mi):
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path"}, "sky": {"type": "constant"},
                          "ball": {"type": "sphere", "center": [0, 0, -3], "radius": 0.6}})
    assert np.array_equal(_render(mi, scene, ThinLens(0.0, 3.0), 4, 5), _render(mi, scene, None, 4, 5))


def test_plane_at_the_focus_distance_renders_sharp(mi):
    """A checkerboard plane facing the camera at z = -D under a constant sky: every lens ray
    of a film point meets the plane where the pinhole ray does, so the thin-lens image is the
    pinhole image up to Monte Carlo noise (a diffuse plane alone under a uniform sky
    reflects albedo * sky exactly; the noise is the film's pixel sampling). Out of focus the
    same plane is visibly blurred, so the comparison can fail."""
    depth = 2.0
    half = depth * math.tan(math.radians(FOV / 2)) * 1.5
    plane = {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, -depth]).scale([half, half, 1]),
             "bsdf": {"type": "diffuse", "reflectance": {
                 "type": "checkerboard", "color0": {"type": "rgb", "value": 0.1},
                 "color1": {"type": "rgb", "value": 0.9}, "to_uv": mi.ScalarTransform4f().scale([4.5, 4.5, 1])}}}
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 2},
                          "sky": {"type": "constant"}, "plane": plane})
    spp = 64
    pinhole = _render(mi, scene, None, spp, 1)
    noise = np.abs(_render(mi, scene, None, spp, 2) - pinhole).mean()  # two pinhole renders: the noise level
    in_focus = np.abs(_render(mi, scene, ThinLens(0.3, depth), spp, 3) - pinhole).mean()
    off_focus = np.abs(_render(mi, scene, ThinLens(0.3, depth / 2), spp, 3) - pinhole).mean()
    assert in_focus < 1.5 * noise + 1e-4, (in_focus, noise)
    assert off_focus > 5 * noise, (off_focus, noise)


def blur_radius_px(aperture, focus, depth, focal_px):
    """Radius in pixels of the image of an on-axis point at depth d through a thin lens.

    Camera space: lens in z = 0, radius A; in-focus plane z = -D; point P = (0, 0, -d). The
    ray from lens point L = (A u, A v, 0) through P meets the focus plane at
        F = L + (P - L) * D / d,   so   F_xy = A (u, v) (1 - D / d).
    That ray belongs to the film point whose pinhole ray passes F (every lens ray of a film
    point meets the focus plane at the same point), i.e. image offset x = f_px F_x / D.
    Over the lens disc |(u, v)| <= 1 the point spreads into a disc of radius
        r = f_px A |1 - D / d| / D = f_px A |d - D| / (d D)   pixels,
    the circle of confusion of diameter c = 2 r = 2 A f_px |d - D| / (d D).
    """
    return focal_px * aperture * abs(depth - focus) / (depth * focus)


def second_moment(image):
    """Intensity-weighted mean squared distance from the intensity centroid, px^2. image: [H, W]."""
    rows, cols = np.mgrid[0:image.shape[0], 0:image.shape[1]] + 0.5
    total = image.sum()
    cy, cx = (image * rows).sum() / total, (image * cols).sum() / total
    return (image * ((rows - cy) ** 2 + (cols - cx) ** 2)).sum() / total


@pytest.mark.parametrize("aperture,focus,depth", [(0.25, 2.0, 4.0), (0.5, 2.0, 4.0), (0.4, 3.0, 1.8)])
def test_off_focus_point_blurs_into_the_circle_of_confusion(mi, aperture, focus, depth):
    """A tiny emitting sphere on the axis spreads into a uniform disc of the radius
    blur_radius_px. A uniform disc of radius r has second moment r^2 / 2 about its centre,
    and second moments add under convolution, so with the sharp (pinhole) image's moment M0
    (the sphere's own size and the box filter of the pixels, the quantisation) removed,
        r_measured = sqrt(2 (M - M0)).
    Tolerance: 4 % plus 0.1 px, for the residual noise of 512 spp and the pixel grid
    cutting the disc (measured moments of a disc rasterised at these radii agree with
    r^2 / 2 to within about 1 %)."""
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 1},
                          "dot": {"type": "sphere", "center": [0, 0, -depth], "radius": 0.03 * depth,
                                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}})
    focal_px = Intrinsics.from_fov(SIDE, SIDE, FOV).fx
    sharp = _render(mi, scene, None, 512, 1)[..., :3].mean(-1)
    blurred = _render(mi, scene, ThinLens(aperture, focus), 512, 2)[..., :3].mean(-1)
    expected = blur_radius_px(aperture, focus, depth, focal_px)
    assert 2.0 < expected < 7.0  # inside the 32-px frame, and well above a pixel
    measured = math.sqrt(2 * (second_moment(blurred) - second_moment(sharp)))
    assert abs(measured - expected) < 0.04 * expected + 0.1, (measured, expected)
    # the light is conserved: the same power, spread out
    assert abs(blurred.sum() / sharp.sum() - 1) < 0.05


# --- the generator --------------------------------------------------------------------------


def test_generator_writes_lens_frames_with_pinhole_ground_truth(make_dataset, tiny_dataset, tmp_path):
    """--aperture/--focus-distance: test frames carry their lens and are rendered through it;
    train frames are unchanged; depth, normals and masks stay those of the pinhole rays."""
    from nerfgauge.core.dataset import Dataset

    lens_root = make_dataset(tmp_path / "lens", aperture=0.15, focus_distance=2.5)
    pinhole, lens = Dataset(tiny_dataset), Dataset(lens_root)
    test_meta = json.loads((lens_root / "transforms_test.json").read_text())
    assert all(frame["lens"] == {"model": "thinlens", "aperture_radius": 0.15, "focus_distance": 2.5}
               for frame in test_meta["frames"])
    assert not any("lens" in frame for frame in json.loads((lens_root / "transforms_train.json").read_text())["frames"])
    assert lens.cameras("test").lens(0) == ThinLens(0.15, 2.5) and lens.cameras("train").lens(0) is None
    assert np.array_equal(lens.c2w("test"), pinhole.c2w("test"))
    assert np.array_equal(lens.image_linear("train", 0), pinhole.image_linear("train", 0))
    assert not np.array_equal(lens.image_linear("test", 0), pinhole.image_linear("test", 0))
    for index in range(2):
        assert np.array_equal(lens.depth("test", index), pinhole.depth("test", index))
        assert np.array_equal(lens.mask("test", index), pinhole.mask("test", index))
        assert np.array_equal(lens.normals("test", index), pinhole.normals("test", index))
    scene = json.loads((lens_root / "scene.json").read_text())
    assert scene["camera"]["lens"]["splits"] == ["test"]


def test_pinhole_recipe_is_unchanged_by_the_lens_fields():
    """A dataset without a lens keeps the recipe it had before lenses existed (no new keys),
    so earlier datasets resume instead of being refused as another recipe."""
    from nerfgauge.generate.pipeline import GenerateConfig

    assert "aperture" not in GenerateConfig().to_json()
    assert GenerateConfig(aperture=0.1, focus_distance=2.0).to_json()["aperture"] == 0.1


@pytest.mark.parametrize("flags,expected", [
    (["--aperture", "-0.1", "--focus-distance", "2"], "aperture"),
    (["--aperture", "0.1", "--focus-distance", "0"], "argument --focus-distance: expected a number above 0"),
    (["--aperture", "0.1", "--focus-distance", "-3"], "argument --focus-distance: expected a number above 0"),
    (["--aperture", "0.1"], "--focus-distance"),
])
def test_generate_refuses_a_bad_lens_in_one_line(capsys, tmp_path, flags, expected):
    one_line_exit_2(capsys, ["generate", "primitives", "--out", tmp_path / "d", "--views", "4", *flags], expected)
    assert not (tmp_path / "d").exists()  # nothing written on bad input
