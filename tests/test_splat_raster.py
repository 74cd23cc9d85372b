"""The tiled CPU rasteriser (splat.raster, splat.tiles) against the brute-force oracle
(splat.reference): colour, depth, opacity and every gradient, on random scenes of a few
hundred overlapping Gaussians at 40 x 28 pixels (3 x 2 tiles of 16, the last row and column
partial), some behind the camera or outside the view.

Tolerances, from the arithmetic each side does:
- float32 inputs (what training feeds it): the kernels read the float32 values, compute in
  float64 and round each output once to float32, while the oracle composites the same float32
  values upcast to float64. Both take every discrete decision (1/255, 0.99, T < 1e-4) on the
  same float64 numbers, so they differ by the outputs' final rounding, half a float32 ulp
  (2^-24 relative), plus float64 rounding over at most a few hundred terms (~1e-14): the test
  allows 2^-22 of each tensor's largest magnitude (four ulps of it). A wrong sign, weight,
  order or missed pair shows at 1e-3 or more.
- float64 end to end (projection, colour, compositing): the same maths in two orders
  (cumulative products against the recursive T_i = T_{i+1} / (1 - alpha_i) and S recursion
  of the backward), each with at most ~10^3 roundings of 1.1e-16 amplified by the conic's
  condition (<= ~10^3 here): 1e-9 relative to each tensor's largest magnitude leaves two
  orders of margin. Measured: 1e-12 to 1e-15.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest
import torch
from nerfgauge.splat.projection import project
from nerfgauge.splat.raster import rasterise
from nerfgauge.splat.reference import composite_reference
from nerfgauge.splat.render import render
from nerfgauge.splat.tiles import TILE, bin_gaussians, depth_order, footprint_box, tile_grid
from splat_scenes import activated, as_numpy, camera, grads_of, scene

FLOAT32_TOLERANCE = 2.0 ** -22
FLOAT64_TOLERANCE = 1e-9


def close(a, b, tolerance: float) -> None:
    a, b = as_numpy(a), as_numpy(b)
    scale = max(np.abs(b).max(), 1e-30)
    worst = np.abs(a - b).max() / scale
    assert worst <= tolerance, f"differs by {worst:.3g} of the largest magnitude {scale:.3g} (allowed {tolerance:.3g})"


def projected_inputs(seed: int, n: int = 300):
    """The 2D Gaussians of a scene (float32, as training gives them) and their depths."""
    params = scene(n, seed, torch.float32)
    means, scales, quats, opacities, sh = activated(params)
    cam = camera(dtype=torch.float32)
    p = project(means, scales, quats, cam)
    keep = p.in_front
    features = torch.cat([torch.rand(int(keep.sum()), 3, generator=torch.Generator().manual_seed(seed)),
                          p.depths[keep, None]], dim=1)
    return (p.means2d[keep].detach(), p.conics[keep].detach(), opacities[keep].detach(), features.detach(),
            p.depths[keep].detach(), footprint_box(p.cov2d_diagonal[keep], opacities[keep].detach()), cam)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compositing_and_its_gradients_match_the_oracle_in_float32(seed):
    means2d, conics, opacities, features, depths, half, cam = projected_inputs(seed)
    binning = bin_gaussians(means2d, half, depths, cam.width, cam.height)
    assert len(binning.ids) > len(means2d), "the scene should put Gaussians in several tiles"
    fast_inputs = [t.clone().requires_grad_(True) for t in (means2d, conics, opacities, features)]
    oracle_inputs = [t.double().clone().requires_grad_(True) for t in (means2d, conics, opacities, features)]
    colour, alpha = rasterise(*fast_inputs, binning, cam.width, cam.height)
    colour_ref, alpha_ref = composite_reference(*oracle_inputs, depths.double(), cam.width, cam.height)
    assert colour.dtype == torch.float32 and 0.2 < float(alpha.detach().mean()) < 0.999
    close(colour, colour_ref, FLOAT32_TOLERANCE)
    close(alpha, alpha_ref, FLOAT32_TOLERANCE)
    g = torch.Generator().manual_seed(seed + 10)
    w_colour, w_alpha = torch.randn(colour.shape, generator=g), torch.randn(alpha.shape, generator=g)
    fast = torch.autograd.grad((colour * w_colour).sum() + (alpha * w_alpha).sum(), fast_inputs)
    ref = torch.autograd.grad((colour_ref * w_colour.double()).sum() + (alpha_ref * w_alpha.double()).sum(),
                              oracle_inputs)
    for name, a, b in zip(("means2d", "conics", "opacities", "features"), fast, ref):
        assert float(b.abs().max()) > 0, name
        close(a, b, FLOAT32_TOLERANCE)


@pytest.mark.parametrize("seed", [3, 4])
def test_rendering_and_every_parameter_gradient_match_the_oracle_in_float64(seed):
    cam = camera()
    background = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    results = {}
    for backend in ("cpu", "reference"):
        params = {k: v.clone().requires_grad_(True) for k, v in scene(300, seed).items()}
        out = render(*activated(params), cam, background, 3, backend=backend)
        outputs = {"rgb": out.rgb, "depth": out.depth, "opacity": out.opacity}
        results[backend] = ({k: v.detach() for k, v in outputs.items()}, grads_of(outputs, params))
    (fast, fast_grads), (ref, ref_grads) = results["cpu"], results["reference"]
    assert float((ref["depth"] > 0).float().mean()) > 0.3 and float(ref["opacity"].max()) > 0.99
    for name in ("rgb", "depth", "opacity"):
        close(fast[name], ref[name], FLOAT64_TOLERANCE)
    for name in ("means", "log_scales", "quats", "logits", "sh"):
        assert float(ref_grads[name].abs().max()) > 0, name
        close(fast_grads[name], ref_grads[name], FLOAT64_TOLERANCE)


def test_every_pixel_a_gaussian_reaches_is_in_a_tile_it_is_binned_into():
    """The footprint box (alpha < 1/255 outside it) and the tile lists: no pair the oracle
    composites is missing, whatever the opacity."""
    means2d, conics, opacities, features, depths, half, cam = projected_inputs(5)
    binning = bin_gaussians(means2d, half, depths, cam.width, cam.height)
    tiles_x, _ = tile_grid(cam.width, cam.height)
    ys, xs = torch.meshgrid(torch.arange(cam.height) + 0.5, torch.arange(cam.width) + 0.5, indexing="ij")
    m, c, o = means2d.double(), conics.double(), opacities.double()
    dx, dy = m[None, :, 0] - xs.reshape(-1, 1), m[None, :, 1] - ys.reshape(-1, 1)
    alpha = o * torch.exp(-0.5 * (c[:, 0] * dx * dx + c[:, 2] * dy * dy) - c[:, 1] * dx * dy)  # [P, V]
    pixel, gaussian = (alpha >= 1 / 255).nonzero(as_tuple=True)
    tile = (pixel // cam.width // TILE) * tiles_x + (pixel % cam.width) // TILE
    listed = {(t, int(i)) for t in range(len(binning.offsets) - 1)
              for i in binning.ids[binning.offsets[t]:binning.offsets[t + 1]]}
    missing = [(int(t), int(i)) for t, i in zip(tile, gaussian) if (int(t), int(i)) not in listed]
    assert len(pixel) > 1000 and not missing, missing[:5]
    for t in range(len(binning.offsets) - 1):  # each tile's list front to back
        order = depths[binning.ids[binning.offsets[t]:binning.offsets[t + 1]]]
        assert bool((order[1:] >= order[:-1]).all())


def test_depth_order_is_a_stable_sort_by_depth_with_ties_in_index_order():
    """The binning's sort key against numpy's lexsort (depth, then index), on drawn depths with
    many ties, both signs, +0.0 and -0.0 (equal: a tie), and candidates in any order."""
    rng = np.random.default_rng(7)
    for _ in range(300):
        n = int(rng.integers(1, 300))
        depths = (rng.normal(size=n) * rng.choice([1e-3, 1.0, 1e3])).astype(np.float32)
        depths[rng.random(n) < 0.3] = depths[0]
        depths[rng.random(n) < 0.1] = 0.0
        depths[rng.random(n) < 0.1] = -0.0
        candidates = rng.permutation(n)[:int(rng.integers(0, n + 1))].astype(np.int64)
        expected = candidates[np.lexsort((candidates, depths[candidates].astype(np.float64)))]
        assert np.array_equal(depth_order(depths, candidates), expected)


def test_the_result_does_not_depend_on_the_thread_count():
    means2d, conics, opacities, features, depths, half, cam = projected_inputs(6)
    binning = bin_gaussians(means2d, half, depths, cam.width, cam.height)
    runs = []
    before = numba.get_num_threads()
    try:
        for threads in (1, numba.config.NUMBA_NUM_THREADS):
            numba.set_num_threads(threads)
            inputs = [t.clone().requires_grad_(True) for t in (means2d, conics, opacities, features)]
            colour, alpha = rasterise(*inputs, binning, cam.width, cam.height)
            grads = torch.autograd.grad(colour.sum() + alpha.sum(), inputs)
            runs.append([colour.detach(), alpha.detach(), *grads])
    finally:
        numba.set_num_threads(before)
    for a, b in zip(*runs):
        assert torch.equal(a, b)


def test_an_image_without_gaussians_is_the_background():
    cam = camera(dtype=torch.float32)
    params = {k: v[:0].float() for k, v in scene(4, 0).items()}
    out = render(*activated(params), cam, torch.tensor([0.1, 0.2, 0.3]), 3)
    assert torch.equal(out.rgb, torch.tensor([0.1, 0.2, 0.3]).expand(cam.height, cam.width, 3))
    assert float(out.opacity.abs().max()) == 0 and float(out.depth.abs().max()) == 0
