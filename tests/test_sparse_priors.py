"""Sparse captures (issue 34, item 6): the train views' coverage of the scene, the rule
that turns the priors on, and the priors themselves, checked against independent
constructions (a per-point frustum test by angles, torch's Bernoulli entropy)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfgauge.core.camera import Intrinsics, look_at
from nerfgauge.nerf.config import TrainConfig, resolve
from nerfgauge.nerf.sparse_priors import (PRIOR_COLOUR_TV, PRIOR_ENTROPY, PRIOR_TV, SPARSE_VIEWS_PER_POINT,
                                          cameras_inside, opacity_entropy, origin_spread, prior_loss,
                                          sparse_priors_for, unseen_rays, views_per_point)


def _in_frustum_by_angles(point, c2w, intrinsics) -> bool:
    """Whether a camera's image holds `point`: the angles of the point in the camera's
    frame against the half-angles of a centred pinhole's field of view (cx = w/2, cy = h/2)."""
    local = (np.asarray(point) - c2w[:3, 3]) @ c2w[:3, :3]
    ahead = -local[2]
    if ahead <= 0:
        return False
    return (abs(math.atan2(local[0], ahead)) < math.atan(intrinsics.width / 2 / intrinsics.fx)
            and abs(math.atan2(local[1], ahead)) < math.atan(intrinsics.height / 2 / intrinsics.fy))


@pytest.mark.parametrize("seed", [0, 1])
def test_views_per_point_counts_the_cameras_whose_image_holds_each_point(seed):
    rng = np.random.default_rng(seed)
    intrinsics = Intrinsics(width=40, height=30, fx=35.0, fy=35.0, cx=20.0, cy=15.0)
    aabb = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    cameras = np.stack([look_at(rng.normal(size=3) * 3, rng.normal(size=3)) for _ in range(9)])
    got = views_per_point(aabb, cameras, intrinsics, seed=5)
    # the same points (the function's draw), counted by angles
    points = aabb[0] + np.random.default_rng(5).random((4096, 3)) * (aabb[1] - aabb[0])
    counts = np.array([sum(_in_frustum_by_angles(p, c, intrinsics) for c in cameras) for p in points])
    assert got == float(np.median(counts[counts > 0]))
    assert 0 < got <= len(cameras)


def test_cameras_around_an_object_hold_all_of_it_and_cameras_looking_out_share_little():
    intrinsics = Intrinsics(width=64, height=64, fx=80.0, fy=80.0, cx=32.0, cy=32.0)  # 43.6 deg field of view
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    ring = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=1)
    small_box = np.array([[-0.2, -0.2, -0.2], [0.2, 0.2, 0.2]])
    around = np.stack([look_at(4 * p, (0, 0, 0)) for p in ring])
    assert views_per_point(small_box, around, intrinsics) == 24.0
    # from the middle of a room, each looking outwards: a point is in about 24 x 43.6 / 360 images
    room = np.array([[-5.0, -5.0, -0.5], [5.0, 5.0, 0.5]])
    outward = np.stack([look_at(0.1 * p, 2 * p) for p in ring])
    assert 1 <= views_per_point(room, outward, intrinsics) <= 4
    assert views_per_point(room, outward[:0], intrinsics) == 0.0
    assert views_per_point(np.array([[-1e308] * 3, [1e308] * 3]), outward, intrinsics) is None  # extent overflows


def test_the_priors_turn_on_for_a_sparse_open_capture_from_inside_in_bounded_space_and_say_why():
    bar = SPARSE_VIEWS_PER_POINT
    on, reason = sparse_priors_for(None, bar - 1, "bounded", 1.0)
    assert on and f"{bar - 1:g} train images" in reason and "open scene (100% of the cameras" in reason
    off, reason = sparse_priors_for(None, bar, "bounded", 1.0)
    assert not off and ">=" in reason
    for kind in ("contracted", "forward"):
        off, reason = sparse_priors_for(None, 1.0, kind, 1.0)
        assert not off and f"{kind} space" in reason
    off, reason = sparse_priors_for(None, 1.0, "bounded", 0.4)  # around an object
    assert not off and "40% stand in the box" in reason
    assert sparse_priors_for(None, 1.0, "bounded", 0.5)[0] is True
    off, reason = sparse_priors_for(None, 1.0, "bounded", 1.0, opaque=1.0)  # a closed room
    assert not off and "closed (100.00%" in reason
    assert sparse_priors_for(None, 1.0, "bounded", 1.0, opaque=0.63)[0] is True  # open above
    assert sparse_priors_for(None, 1.0, "bounded", 1.0, opaque=None)[0] is True  # no alpha: counted open
    for unknown in ((None, "bounded", 1.0), (1.0, None, 1.0), (1.0, "bounded", None)):
        assert sparse_priors_for(None, *unknown)[0] is False
    assert sparse_priors_for(True, 100.0, "contracted", 0.0) == (True, "set on the command line")
    assert sparse_priors_for(False, 1.0, "bounded", 1.0) == (False, "set on the command line")


def test_cameras_inside_is_the_share_of_centres_in_the_box():
    aabb = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    c2w = np.stack([look_at(eye, (0, 0, 5)) for eye in ((0.0, 0.0, 0.0), (0.9, -0.9, 0.5), (1.5, 0.0, 0.0),
                                                       (0.0, 0.0, -3.0))])
    assert cameras_inside(aabb, c2w) == 0.5
    assert cameras_inside(aabb, c2w[:0]) == 0.0


def test_resolve_states_the_choice_and_config_json_keeps_older_recipes():
    aabb = np.array([[-2.0, -2.0, -1.0], [2.0, 2.0, 1.0]])
    # a ring of cameras in the middle of a room, looking outwards
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ring = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=1)
    c2w = np.stack([look_at(0.3 * p, 2 * p) for p in ring])
    config = TrainConfig(dataset="d", steps=10)
    sparse, reasons = resolve(config, None, aabb, c2w, 50.0, 64, views_per_point=3.0)
    assert sparse.parametrisation == "bounded"
    assert sparse.sparse_priors is True and "3 train images" in reasons["sparse_priors"]
    closed, reasons = resolve(config, None, aabb, c2w, 50.0, 64, opaque=1.0, views_per_point=3.0)
    assert closed.sparse_priors is False and "closed" in reasons["sparse_priors"]
    dense, _ = resolve(config, None, aabb, c2w, 50.0, 64, views_per_point=40.0)
    assert dense.sparse_priors is False
    assert dense.to_json().get("sparse_priors", "absent") == "absent"  # a run made before the mode has no key
    assert sparse.to_json()["sparse_priors"] is True
    around = np.stack([look_at(4 * p + (0, 0, 1), (0, 0, 0)) for p in ring])
    outside, reasons = resolve(config, None, aabb, around, 50.0, 64, views_per_point=3.0)
    assert outside.sparse_priors is False and "from outside" in reasons["sparse_priors"]
    vanilla, reasons = resolve(TrainConfig(dataset="d", steps=10, model="vanilla"), None, aabb, c2w, 50.0, 64,
                               views_per_point=3.0)
    assert vanilla.sparse_priors is None and "sparse_priors" not in reasons  # the compact model's mode


def test_a_run_with_the_priors_takes_their_learning_rate_unless_the_api_set_one():
    """resolve: the priors' runs take PRIOR_LEARNING_RATE (and say so), others keep the
    default; a learning rate set through the API is kept either way."""
    from nerfgauge.nerf.config import DEFAULT_LEARNING_RATE
    from nerfgauge.nerf.sparse_priors import PRIOR_LEARNING_RATE

    aabb = np.array([[-2.0, -2.0, -1.0], [2.0, 2.0, 1.0]])
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ring = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=1)
    c2w = np.stack([look_at(0.3 * p, 2 * p) for p in ring])
    assert PRIOR_LEARNING_RATE != DEFAULT_LEARNING_RATE == TrainConfig(dataset="d").lr
    sparse, reasons = resolve(TrainConfig(dataset="d", steps=10), None, aabb, c2w, 50.0, 64, views_per_point=3.0)
    assert sparse.sparse_priors is True and sparse.lr == PRIOR_LEARNING_RATE and "priors" in reasons["lr"]
    dense, reasons = resolve(TrainConfig(dataset="d", steps=10), None, aabb, c2w, 50.0, 64, views_per_point=40.0)
    assert dense.lr == DEFAULT_LEARNING_RATE and "lr" not in reasons
    chosen, _ = resolve(TrainConfig(dataset="d", steps=10, lr=0.05), None, aabb, c2w, 50.0, 64, views_per_point=3.0)
    assert chosen.sparse_priors is True and chosen.lr == 0.05


def test_the_priors_are_refused_for_the_vanilla_model():
    from nerfgauge.core.errors import InputError

    with pytest.raises(InputError, match="compact model"):
        TrainConfig(dataset="d", steps=1, model="vanilla", sparse_priors=True).validate()
    TrainConfig(dataset="d", steps=1, model="vanilla", sparse_priors=False).validate()


def test_opacity_entropy_is_the_bernoulli_entropy():
    opacity = torch.tensor([0.0, 1e-3, 0.25, 0.5, 0.9, 1.0])
    expected = torch.distributions.Bernoulli(probs=opacity.clamp(1e-4, 1 - 1e-4)).entropy()
    assert torch.allclose(opacity_entropy(opacity), expected, atol=1e-6)
    assert abs(float(opacity_entropy(torch.tensor([0.5]))) - math.log(2)) < 1e-6
    # clamped at eps = 1e-4: H(eps) = eps (1 - ln eps) + O(eps^2) = 1.02e-3
    assert float(opacity_entropy(torch.tensor([0.0, 1.0])).max()) < 1.1e-3


def test_unseen_rays_move_the_train_cameras_by_their_spread():
    generator = torch.Generator().manual_seed(0)
    centres = torch.tensor([[2.0, 0.0, 0.0], [-2.0, 0.0, 0.0], [0.0, 2.0, 0.5], [0.0, -2.0, -0.5]])
    origins = centres.repeat_interleave(50, dim=0)
    directions = torch.nn.functional.normalize(torch.randn((200, 3), generator=generator), dim=1)
    spread = origin_spread(origins)
    # independent: the RMS distance of the four centres from their mean, per axis
    assert abs(spread - float(np.sqrt((centres.numpy() ** 2).sum(axis=1).mean() / 3))) < 1e-6
    n = 20000
    moved, moved_directions = unseen_rays(origins, directions, spread, n, torch.Generator().manual_seed(1))
    assert moved.shape == (n, 3) and moved_directions.shape == (n, 3)
    # each direction is a train ray's, from that ray's camera moved by the offset
    match = (moved_directions[:, None, :] == directions[None, :, :]).all(dim=2)
    assert bool(match.any(dim=1).all())
    source = origins[match.float().argmax(dim=1)]
    offsets = (moved - source).double()
    # the offsets' per-axis standard deviation: a chi estimate from 3n normal draws has a
    # relative standard error of 1/sqrt(6n) (0.3%); 5 of them
    assert abs(float(offsets.pow(2).mean().sqrt()) / spread - 1) < 5 / math.sqrt(6 * n)
    assert float(offsets.mean(dim=0).abs().max()) < 5 * spread / math.sqrt(n)


class _SlabModel(torch.nn.Module):
    """A stand-in with the compact model's render interface: every ray's opacity is the
    sigmoid of one parameter (a half-transparent haze when it is 0), and a field whose
    total variation is 1 for density and 2 for colour."""

    def __init__(self):
        super().__init__()
        self.logit = torch.nn.Parameter(torch.tensor(0.3))
        self.field = type("Field", (), {"total_variation": staticmethod(
            lambda of: torch.tensor({"density": 1.0, "features": 2.0}[of]))})()

    def render(self, origins, directions, generator=None, training=False):
        n = origins.shape[0]
        opacity = torch.sigmoid(self.logit).expand(n)
        return type("Out", (), {"opacity": opacity, "distortion": torch.zeros(n)})()


def test_the_priors_push_a_haze_towards_empty_or_opaque():
    model = _SlabModel()
    rays = torch.zeros((8, 3)), torch.tensor([[0.0, 0.0, 1.0]]).expand(8, 3)
    loss = prior_loss(model, *rays, torch.Generator().manual_seed(0))
    loss.backward()
    # d/dl of H(sigmoid(l)) = -l sigmoid'(l): pushes a positive logit up (towards opaque)
    assert float(model.logit.grad) < 0
    expected = PRIOR_ENTROPY * float(opacity_entropy(torch.sigmoid(torch.tensor([0.3])))) + PRIOR_TV + 2 * PRIOR_COLOUR_TV
    assert abs(float(loss) - expected) < 1e-7


def test_a_sparse_run_trains_with_the_priors_and_states_why(tiny_dataset, tmp_path):
    from nerfgauge.core.files import read_json
    from nerfgauge.nerf.train import train

    for setting, name in ((True, "on"), (False, "off")):
        train(TrainConfig(dataset=str(tiny_dataset), steps=3, sparse_priors=setting, threads=1), tmp_path / name,
              progress=False)
    on, off = read_json(tmp_path / "on" / "config.json"), read_json(tmp_path / "off" / "config.json")
    assert on["sparse_priors"] is True and "sparse_priors" not in off
    assert on["auto_reasons"]["sparse_priors"] == "set on the command line"
    assert on["recipe"] != off["recipe"]
    assert (tmp_path / "on" / "model.pt").read_bytes() != (tmp_path / "off" / "model.pt").read_bytes()
