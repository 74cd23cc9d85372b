"""The one camera: our pixel-centre rays are Mitsuba's sensor rays; conventions hold."""

import math

import numpy as np
import pytest

from nerfgauge.core.camera import (
    Intrinsics,
    look_at,
    pixel_rays,
    to_mitsuba,
    z_depth_from_distance,
)


def mitsuba_sensor_rays(mi, sensor, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's own rays through every pixel centre, row-major. Returns origins, directions [H * W, 3].

    The vectorised variants take all film positions in one call; scalar_rgb's Point2f holds
    one point, so there it is one call per pixel."""
    rows, cols = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    u = ((cols + 0.5) / width).ravel().astype(np.float32)  # [H * W]
    v = ((rows + 0.5) / height).ravel().astype(np.float32)
    if mi.variant().startswith("scalar"):
        rays = [sensor.sample_ray(0.0, 0.0, mi.Point2f(float(a), float(b)), mi.Point2f(0.5, 0.5))[0]
                for a, b in zip(u, v)]
        return (np.array([[ray.o[k] for k in range(3)] for ray in rays], np.float64),
                np.array([[ray.d[k] for k in range(3)] for ray in rays], np.float64))
    ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f(u, v), mi.Point2f(0.5, 0.5))
    return (np.stack([np.array(ray.o[k]) for k in range(3)], -1).astype(np.float64),
            np.stack([np.array(ray.d[k]) for k in range(3)], -1).astype(np.float64))


@pytest.mark.parametrize("width,height", [(32, 32), (40, 24), (17, 29)])
def test_pixel_rays_equal_mitsuba_sensor_rays(mi, width, height):
    from nerfgauge.generate.render import sensor_dict

    c2w = look_at((3.0, -2.0, 1.5), (0.1, 0.2, 0.3))
    intrinsics = Intrinsics.from_fov(width, height, 50.0)
    sensor = mi.load_dict(sensor_dict(mi, c2w, intrinsics, 1))
    origins, directions = pixel_rays(c2w, intrinsics)
    mitsuba_o, mitsuba_d = mitsuba_sensor_rays(mi, sensor, width, height)
    # float32 film positions and Mitsuba's float32 matrices: ~1e-7 per component.
    np.testing.assert_allclose(mitsuba_d, directions.reshape(-1, 3), atol=1e-5)
    # Mitsuba starts rays at the near clip along the same line through the camera centre.
    offset = mitsuba_o - origins.reshape(-1, 3)
    np.testing.assert_allclose(np.cross(offset, directions.reshape(-1, 3)), 0, atol=1e-5)


def test_look_at_is_opengl_camera_to_world():
    eye, target = np.array([2.0, 1.0, 3.0]), np.array([0.0, 0.0, 0.5])
    c2w = look_at(eye, target)
    rotation = c2w[:3, :3]
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    forward = -c2w[:3, 2]  # OpenGL cameras look along -Z
    np.testing.assert_allclose(forward, (target - eye) / np.linalg.norm(target - eye), atol=1e-12)
    assert c2w[2, 1] > 0  # camera +Y points up in the world (+Z up)
    np.testing.assert_array_equal(c2w[:3, 3], eye)


def test_look_at_straight_down_the_up_axis_is_defined():
    c2w = look_at((0, 0, 5), (0, 0, 0))
    assert np.isfinite(c2w).all()
    np.testing.assert_allclose(-c2w[:3, 2], [0, 0, -1], atol=1e-12)


def test_mitsuba_flip_is_its_own_inverse():
    c2w = look_at((1, 2, 3), (0, 0, 0))
    np.testing.assert_allclose(to_mitsuba(to_mitsuba(c2w)), c2w, atol=1e-15)


def test_row_zero_is_the_top_and_fov_is_horizontal():
    intrinsics = Intrinsics.from_fov(64, 32, 60.0)
    _, d = pixel_rays(np.eye(4), intrinsics)
    assert d[0, 32, 1] > 0 > d[-1, 32, 1]  # camera +Y is up; row 0 looks up
    assert d[16, 0, 0] < 0 < d[16, -1, 0]  # column 0 is on the left
    # The outer edges of the outer pixels span exactly the horizontal fov.
    edge = math.atan((intrinsics.width / 2) / intrinsics.fx)
    assert math.degrees(2 * edge) == pytest.approx(60.0)
    assert intrinsics.camera_angle_x == pytest.approx(math.radians(60.0))


def test_z_depth_is_distance_times_cosine():
    c2w = look_at((0, -4, 1), (0, 0, 0))
    _, d = pixel_rays(c2w, Intrinsics.from_fov(8, 6, 70.0))
    distance = np.full(d.shape[:2], 2.5)
    z = z_depth_from_distance(distance, d, c2w)
    cosine = d @ (-c2w[:3, 2])
    np.testing.assert_allclose(z, 2.5 * cosine, rtol=1e-12)
    assert (z < distance).all() and (z > 0).all()
