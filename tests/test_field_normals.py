"""The field's normals (eval.normals): central differences in front of the surface on a
voxel model, the analytic gradient at the surface otherwise, checked on a density whose
gradient is known in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfgauge.eval.normals import FRONT_VOXELS, field_normals, surface_normals

RADIUS, WIDTH, VOXEL = 1.0, 0.2, 0.01


class Ball:
    """sigma(x) = 200 sigmoid((R - |x|) / w): radial, so its gradient is -|grad| x / |x|
    everywhere and the outward normal at any point is x / |x|."""

    def __init__(self, has_grid: bool):
        self.has_grid = has_grid

    def density(self, x):
        return 200 * torch.sigmoid((RADIUS - x.norm(dim=-1)) / WIDTH)

    def world_voxel(self, x):
        return torch.full_like(x[:, 0], VOXEL)


def _rays(count: int, seed: int = 0):
    """Rays from outside the ball towards random points of it that they hit; their exact
    distances to the sphere |x| = R and the outward normals there."""
    rng = np.random.default_rng(seed)
    origins = rng.normal(size=(count, 3))
    origins *= 3 / np.linalg.norm(origins, axis=1, keepdims=True)
    targets = rng.normal(size=(count, 3))
    targets *= rng.uniform(0, 0.8, size=(count, 1)) / np.linalg.norm(targets, axis=1, keepdims=True)  # inside
    d = targets - origins
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    b = np.einsum("ij,ij->i", origins, d)
    c = np.einsum("ij,ij->i", origins, origins) - RADIUS ** 2
    t = -b - np.sqrt(b * b - c)  # the near intersection
    hits = origins + t[:, None] * d
    as_tensor = lambda a: torch.from_numpy(a)  # noqa: E731 (float64 keeps the check about the rule, not rounding)
    return as_tensor(origins), as_tensor(d), as_tensor(t), hits / RADIUS


def _angles_degrees(a, b):
    cos = np.clip(np.einsum("ij,ij->i", a, b), -1, 1)
    return np.degrees(np.arccos(cos))


def test_central_differences_in_front_of_the_surface_give_the_radial_normal():
    origins, directions, depth, truth = _rays(500)
    normals, defined = surface_normals(Ball(has_grid=True), origins, directions, depth)
    assert bool(defined.all())
    front = (origins + (depth - FRONT_VOXELS * VOXEL)[:, None] * directions).numpy()
    radial = front / np.linalg.norm(front, axis=1, keepdims=True)
    # central differences of step h are the gradient at the front point up to the Taylor
    # term of order h^2 (third derivatives / 6): with the profile's width w = 20 h, a few
    # thousandths of a degree
    assert _angles_degrees(normals.numpy(), radial).max() < 0.05
    # ... which is the surface's normal up to the shift along the ray: at most
    # atan(FRONT_VOXELS h / R) from the normal where the ray meets the sphere, and visibly
    # off it for oblique rays (the shift is there)
    off = _angles_degrees(normals.numpy(), truth)
    assert off.max() <= math.degrees(math.atan(FRONT_VOXELS * VOXEL / RADIUS)) + 0.05 and off.max() > 0.3


def test_a_model_without_a_grid_takes_the_analytic_gradient_at_the_surface():
    origins, directions, depth, truth = _rays(200, seed=1)
    normals, defined = surface_normals(Ball(has_grid=False), origins, directions, depth)
    assert bool(defined.all())
    assert _angles_degrees(normals.numpy(), truth).max() < 1e-5  # autograd of a radial field: radial


def test_a_zero_gradient_is_undefined():
    class Empty(Ball):
        def density(self, x):
            return 0 * x.sum(dim=-1)  # depends on x, with a zero gradient

    points = torch.zeros((4, 3), dtype=torch.float64) + 0.5
    for step in (None, torch.full((4,), VOXEL, dtype=torch.float64)):
        normals, defined = field_normals(Empty(has_grid=True), points, step)
        assert not bool(defined.any()) and bool((normals == 0).all())


@pytest.mark.parametrize("seed", [0, 1])
def test_world_voxel_is_the_grid_voxel_in_world_units(seed):
    """A compact model's world voxel is its grid's voxel where space is bounded, and scales
    with the contraction's world length per unit in contracted space."""
    from nerfgauge.nerf.config import TrainConfig
    from nerfgauge.nerf.checkpoint import build_model

    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    model = build_model(TrainConfig(dataset="unused", steps=1, final_resolution=64, start_resolution=32,
                                    parametrisation="bounded", view_dependent=False), aabb)
    points = torch.from_numpy(np.random.default_rng(seed).uniform(-0.9, 0.9, size=(10, 3))).float()
    assert torch.allclose(model.world_voxel(points), torch.full((10,), 2.0 / 32))
