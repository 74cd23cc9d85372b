"""Surface opacity (issue 52, item 3): a sample's opacity is the relative rise of occupancy
o = 1 - exp(-sigma delta R) along its ray (nerf.packed.occupancy_rise_taus), so a ray that
skims a surface's faint front takes that front's occupancy once, not summed over its path.

Checked against a per-ray loop written from the definition, in every place the compact model
composites: the packed torch quadrature (training), its front-to-back windows (a GPU's
inference), the compiled CPU kernel (`nerfgauge render`), and the training loop that turns it
on at the half-budget refinement and saves it in model.pt."""

from __future__ import annotations

import json
import math

import pytest
import torch
import torch.nn.functional as F
from test_compact_nerf import blob_model
from test_render_compiled import _compiled, _rays

import nerfgauge.nerf.schedule as S
from nerfgauge.nerf.marching import sample_deltas
from nerfgauge.nerf.packed import RISE_ALPHA_MAX_GAP, packed_render, packed_transmittance, render_front_to_back


def _reference(sigmas, deltas, ray_index, rise):
    """Per ray, sample by sample, from the definition: o_i = 1 - exp(-sigma_i delta_i R),
    alpha_i = max(0, (o_i - o_{i-1}) / (1 - o_{i-1})), o_{-1} = 0; returns each ray's
    opacity 1 - prod(1 - alpha) (float64, no clamp: the cases stay below alpha = 1 - 1e-6)."""
    out = {}
    previous = {}
    for s, d, r in zip(sigmas.double().tolist(), deltas.double().tolist(), ray_index.tolist()):
        o = 1 - math.exp(-s * d * rise)
        before = previous.get(r, 0.0)
        alpha = max(0.0, (o - before) / (1 - before))
        out[r] = 1 - (1 - out.get(r, 0.0)) * (1 - alpha)
        previous[r] = o
    return out


def _opacity(sigmas, deltas, rays, n_rays, rise):
    transmittance, tau = packed_transmittance(sigmas, deltas, rays, n_rays, rise)
    last = torch.zeros(n_rays, dtype=torch.float64)
    for i, r in enumerate(rays.tolist()):  # the ray's transmittance after its last sample
        last[r] = float(transmittance[i] * torch.exp(-tau[i]))
    return 1 - last


def test_a_ray_skimming_a_front_takes_its_occupancy_once_where_density_sums_it():
    """Ray 0 runs 40 samples through a constant faint front (sigma delta = 0.02): with
    density opacity it ends at 1 - exp(-0.8) = 0.55, with surface opacity (R = 2) at that
    front's occupancy, 1 - exp(-0.04) = 0.039, however long the path. Ray 1 enters a surface
    (occupancy rising to ~1): opaque either way."""
    n = 40
    sigmas = torch.cat([torch.full((n,), 0.04, dtype=torch.float64), torch.linspace(0.01, 40.0, 10).double()])
    deltas = torch.full_like(sigmas, 0.5)
    rays = torch.cat([torch.zeros(n, dtype=torch.long), torch.ones(10, dtype=torch.long)])
    density = _opacity(sigmas, deltas, rays, 2, 0.0)
    surface = _opacity(sigmas, deltas, rays, 2, 2.0)
    assert float(density[0]) == pytest.approx(1 - math.exp(-n * 0.02), abs=1e-12)
    assert float(surface[0]) == pytest.approx(1 - math.exp(-0.04), abs=1e-12)
    assert float(surface[1]) > 1 - 1e-6 and float(density[1]) > 1 - 1e-6


def test_it_is_the_definition_on_random_rays_that_enter_leave_and_enter_again():
    """Random densities (rising, falling, rising again along a ray) against the per-ray loop:
    to float64 rounding, and packed_render's opacity is the same sum."""
    g = torch.Generator().manual_seed(5)
    counts = torch.randint(1, 30, (50,), generator=g)
    rays = torch.repeat_interleave(torch.arange(50), counts)
    sigmas = (torch.rand(len(rays), generator=g, dtype=torch.float64) * 3) ** 3
    deltas = torch.rand(len(rays), generator=g, dtype=torch.float64) * 0.2 + 0.05
    expected = _reference(sigmas, deltas, rays, 2.0)
    got = _opacity(sigmas, deltas, rays, 50, 2.0)
    assert max(abs(float(got[r]) - value) for r, value in expected.items()) < 1e-9
    near, far = torch.zeros(50, dtype=torch.float64), torch.full((50,), 10.0, dtype=torch.float64)
    t = torch.cumsum(deltas, 0)
    _, opacity, _, _ = packed_render(sigmas, torch.rand((len(rays), 3), generator=g, dtype=torch.float64), deltas, t,
                                     rays, near, far, 2.0)
    torch.testing.assert_close(opacity, got, rtol=0, atol=1e-9)


def test_its_gradient_stays_finite_through_an_opaque_wall():
    """sigma delta R up to 1e4 in float32: alpha is held RISE_ALPHA_MAX_GAP below 1, so the
    loss's gradient is finite everywhere, and the ray ends opaque to within that gap (an
    occupancy that reached 1 rises no further: the wall is one sample's alpha)."""
    sigmas = torch.tensor([0.0, 1.0, 100.0, 1e4, 1e4], requires_grad=True)
    deltas = torch.full((5,), 0.5)
    rays = torch.zeros(5, dtype=torch.long)
    near, far = torch.zeros(1), torch.full((1,), 3.0)
    rgb, opacity, _, _ = packed_render(sigmas, torch.rand((5, 3)), deltas, torch.arange(5.0) * 0.5, rays, near, far,
                                       2.0)
    (rgb.sum() + opacity.sum()).backward()
    assert torch.isfinite(sigmas.grad).all()
    transmittance, tau = packed_transmittance(sigmas.detach(), deltas, rays, 1, 2.0)
    assert float(transmittance[-1] * torch.exp(-tau[-1])) <= RISE_ALPHA_MAX_GAP


def test_front_to_back_windows_carry_the_occupancy_a_ray_reached():
    """Windows of 3 samples (no early stop) give the full pass's colour and opacity: each
    window starts from the occupancy its ray's last window ended at; started from 0 instead,
    a ray inside a surface would count it again."""
    g = torch.Generator().manual_seed(6)
    counts = torch.randint(1, 20, (40,), generator=g)
    rays = torch.repeat_interleave(torch.arange(40), counts)
    sigmas = (torch.rand(len(rays), generator=g) * 3) ** 3
    deltas = torch.full_like(sigmas, 0.1)
    t = torch.cumsum(deltas, 0)
    rgbs = torch.rand((len(rays), 3), generator=g)
    near, far = torch.zeros(40), torch.full((40,), 100.0)
    full_rgb, full_opacity, _, _ = packed_render(sigmas, rgbs, deltas, t, rays, near, far, 2.0)

    def window_samples(chosen):
        return rays[chosen], t[chosen], deltas[chosen], sigmas[chosen], rgbs[chosen]

    rgb, opacity, _, _ = render_front_to_back(window_samples, rays, near, far, window=3, min_transmittance=0.0,
                                              rise_steps=2.0)
    torch.testing.assert_close(opacity, full_opacity, rtol=0, atol=1e-5)
    torch.testing.assert_close(rgb, full_rgb, rtol=0, atol=1e-5)


def test_the_compiled_render_is_the_full_torch_pass_with_surface_opacity():
    """The kernel (`nerfgauge render` on a CPU) against march + packed_render on the blob
    model, no early stop: to the float32 positions' rounding, as the density test in
    test_render_compiled; and it differs from density opacity there (the mode reaches it)."""
    g = torch.Generator().manual_seed(3)
    model, aabb = blob_model(g, 0.5)
    origins, directions = _rays(g, aabb)
    with torch.no_grad():
        samples = model._march(origins, directions)
        r, t, deltas = samples.ray_index, samples.t_mid, sample_deltas(samples)
        d = directions.index_select(0, r)
        sigma, rgb = model.field(torch.addcmul(origins.index_select(0, r), t[:, None], d), d)
        full = packed_render(sigma, rgb, deltas, t, r, samples.near, samples.far, 2.0)
        got = _compiled(model, origins, directions, min_transmittance=0.0, colour_min_weight=-1.0, rise_steps=2.0)
        density = _compiled(model, origins, directions, min_transmittance=0.0, colour_min_weight=-1.0)
    torch.testing.assert_close(got[1], full[1], rtol=0, atol=1e-4)
    torch.testing.assert_close(got[0], full[0], rtol=0, atol=1e-4)
    seen = full[1] > 0.5
    torch.testing.assert_close(got[2][seen], full[2][seen], rtol=0, atol=1e-4)
    assert float((got[1] - density[1]).abs().max()) > 1e-2


def test_the_depth_of_a_ray_entering_a_surface_is_its_distance():
    """A plane whose occupancy rises from 0 to 1 within a fifth of a marching step (raw
    density +20 on the nodes below it, -30 above). A sample's opacity is the rise of
    occupancy since the previous sample, which lies somewhere between the two, so the
    depth puts its weight half a step back (`nerf.packed.weight_positions`). Over rays that
    meet the plane at every phase of their samples, the error is uniform over a step: mean
    0, standard error step / sqrt(12 n) = 0.0065 steps here. At the sample itself the mean
    would be +0.5 steps. Allowed: 0.1 steps (the rise's own width, a fifth of a step, may sit
    off its half-occupancy point). The kernel and the torch windows alike."""
    from nerfgauge.nerf.grid_field import VoxelGridField
    from nerfgauge.nerf.models import CompactNeRF
    from nerfgauge.nerf.packed import occupancy

    g = torch.Generator().manual_seed(13)
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    field = VoxelGridField(aabb, 24, 24, False)
    grid = field.to_dense()
    plane_node = 11  # nodes 0..11 along z dense, 12.. empty
    grid[0] = -30.0
    grid[0, :plane_node + 1] = 20.0
    grid[1:] = 0.0
    field.load_dense(grid)
    model = CompactNeRF(field)
    model.rise_steps = 2.0
    model.update_occupancy()
    model.eval()
    step = field.marching_step
    lo, hi = -1.0 + plane_node * field.voxel, -1.0 + (plane_node + 1) * field.voxel  # the crossing's cell
    with torch.no_grad():
        for _ in range(60):  # bisection: where the occupancy over one step is 1/2
            middle = 0.5 * (lo + hi)
            sigma = field.density(torch.tensor([[0.1, 0.2, middle]]))
            if float(occupancy(sigma, torch.tensor([step]), 2.0)) > 0.5:
                lo = middle
            else:
                hi = middle
        plane = 0.5 * (lo + hi)
        n = 2000
        origins = torch.cat([torch.rand((n, 2), generator=g) - 0.5, torch.full((n, 1), 0.9)], dim=1)
        directions = F.normalize(torch.cat([torch.rand((n, 2), generator=g) - 0.5, -torch.ones((n, 1))], dim=1), dim=-1)
        truth = (origins[:, 2] - plane) / -directions[:, 2]
        for out in (model.render(origins, directions), model._render_windows(origins, directions)):
            assert bool((out.opacity > 0.999).all())
            error = (out.depth.double() - truth.double()) / step  # in marching steps
            assert abs(float(error.mean())) < 0.1, float(error.mean())
            assert float(error.min()) > -0.7 and float(error.max()) < 0.7


@pytest.mark.slow
def test_a_run_turns_it_on_at_its_half_budget_refinement_and_model_pt_keeps_it(tiny_dataset, tmp_path, monkeypatch):
    """A 40-step `edges` run with --surface-opacity on whose final grid counts as converged
    (the ladder's stages 1 step, FINE_EDGE_POINTS_MIN_STEPS 0) turns it on at step 20: in checkpoint.pt's loop, in
    model.pt (the model `nerfgauge render` loads renders with it), in config.json's reasons,
    and after a resume; without the flag model.pt has none; a bad word is refused with exit 2."""
    from nerfgauge.cli import main
    from nerfgauge.nerf.checkpoint import load_checked, load_model

    monkeypatch.setattr(S, "FINE_EDGE_POINTS_MIN_STEPS", 0)
    monkeypatch.setattr(S, "MIN_STAGE_STEPS", 1)  # the ladder done by 30% of 40 steps
    common = ["--steps", "40", "--quiet", "--threads", "1", "--batch-rays", "256", "--pixel-filter", "edges"]
    on, off = tmp_path / "on", tmp_path / "off"
    assert main(["train", str(tiny_dataset), "--out", str(on), "--surface-opacity", "on", *common]) == 0
    saved = load_checked(on / "checkpoint.pt", "checkpoint")
    assert saved["loop"]["surface_step"] == 20 and saved["loop"]["anneal_from"] == 0.5
    # from there the colour's rate anneals to the floor: the last step's (39) is
    # 10^(-0.5 + (log10 floor + 0.5) * 19/20); the density's follows the plain decay, 10^(-39/40)
    density, colour = saved["optimizer"]["param_groups"][:2]
    expected = -0.5 + (math.log10(S.LR_MIN_FRACTION) + 0.5) * 19 / 20
    assert math.log10(colour["lr"] / colour["base_lr"]) == pytest.approx(expected, abs=1e-9)
    assert math.log10(density["lr"] / density["base_lr"]) == pytest.approx(-39 / 40, abs=1e-9)
    assert load_checked(on / "model.pt")["rise_steps"] == S.SURFACE_RISE_STEPS
    model, config = load_model(on / "model.pt")
    assert model.rise_steps == S.SURFACE_RISE_STEPS and config.surface_opacity is True
    assert json.loads((on / "config.json").read_text())["auto_reasons"]["surface_opacity"].startswith("on from step 20")
    assert main(["render", str(on), "--out", str(tmp_path / "renders"), "--quiet"]) == 0
    # checkpoint.pt holds tensors and the loop: a resumed run takes surface opacity from the loop
    resumed = [arg if arg != "40" else "50" for arg in common]
    assert main(["train", str(tiny_dataset), "--out", str(on), "--surface-opacity", "on", "--resume", *resumed]) == 0
    assert load_checked(on / "model.pt")["rise_steps"] == S.SURFACE_RISE_STEPS
    assert main(["train", str(tiny_dataset), "--out", str(off), *common]) == 0
    assert "rise_steps" not in load_checked(off / "model.pt") and load_model(off / "model.pt")[0].rise_steps == 0.0
    assert main(["train", str(tiny_dataset), "--out", str(tmp_path / "bad"), "--surface-opacity", "maybe", *common]) == 2
    assert not (tmp_path / "bad").exists()


@pytest.mark.parametrize("bad", [-1.0, 1e9, "2", float("nan")])
def test_a_model_with_a_damaged_surface_length_is_refused(tiny_dataset, tmp_path, bad):
    """model.pt's rise_steps drives every render: a value that is not a length in [0, 64]
    steps is a damaged model (InputError, exit 2 at the command line)."""
    from nerfgauge.core.errors import InputError
    from nerfgauge.nerf.checkpoint import load_checked, load_model, save_atomic
    from nerfgauge.nerf.config import TrainConfig
    from nerfgauge.nerf.train import train

    run = tmp_path / "run"
    train(TrainConfig(dataset=str(tiny_dataset), steps=2, threads=1, batch_rays=128), run, progress=False)
    payload = load_checked(run / "model.pt")
    payload["rise_steps"] = bad
    save_atomic(payload, run / "model.pt")
    with pytest.raises(InputError, match="surface opacity"):
        load_model(run / "model.pt")
