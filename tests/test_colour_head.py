"""The residual colour head (issue 34, item 2: capacity a longer budget buys): adding it
leaves the field's colours unchanged, it models colour that trilinear logits cannot (a
stripe inside one cell, against the bound on any monotone fit), the rule that adds it,
and a run that takes it saves, reloads and resumes it."""

from __future__ import annotations

import json

import pytest
import torch
from cli_errors import one_line_exit_2

from nerfgauge.cli import main
from nerfgauge.nerf.config import TrainConfig, colour_head_for
from nerfgauge.nerf.grid_field import VoxelGridField

UNIT_BOX = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])


def _random_field(seed: int, resolution: int = 4) -> VoxelGridField:
    generator = torch.Generator().manual_seed(seed)
    field = VoxelGridField(UNIT_BOX, resolution, resolution, view_dependent=False, allocate=False)
    nodes = torch.ones(field.shape, dtype=torch.bool)
    field.load_nodes(nodes, torch.randn((int(nodes.sum()), 4), generator=generator))
    return field


@pytest.mark.parametrize("seed", [0, 1])
def test_adding_the_head_leaves_every_colour_and_density_as_it_was(seed):
    field = _random_field(seed)
    points = torch.rand((500, 3), generator=torch.Generator().manual_seed(seed + 10))
    directions = torch.nn.functional.normalize(torch.randn(500, 3, generator=torch.Generator().manual_seed(seed)), dim=1)
    with torch.no_grad():
        sigma, rgb = field(points, directions)
        field.add_residual_head(12)
        sigma_after, rgb_after = field(points, directions)
    assert field.channels == 12 and field.features.shape[1] == 12 and field.residual_head
    # the head's output layer is zero: sigmoid(logits + 0), bit for bit
    assert torch.equal(sigma, sigma_after) and torch.equal(rgb, rgb_after)
    # the same through the gradient path (the 8-row gather training uses)
    sigma_grad, rgb_grad = field.at_stencil(field.stencil(points), points, directions)
    assert torch.allclose(rgb_grad, rgb, atol=1e-6) and torch.allclose(sigma_grad, sigma, rtol=1e-5)


def test_the_head_is_refused_where_it_does_not_apply():
    with pytest.raises(ValueError):
        _random_field(0).add_residual_head(3)  # no extra channel
    field = _random_field(0)
    field.add_residual_head(8)
    with pytest.raises(ValueError):
        field.add_residual_head(8)  # twice
    view_dependent = VoxelGridField(UNIT_BOX, 4, 4, view_dependent=True)
    with pytest.raises(ValueError):
        view_dependent.add_residual_head(12)


def _fit_stripe(field: VoxelGridField, steps: int) -> float:
    """Fit a stripe inside the field's one cell: along x at y = z = 1/2, colour 1 on the
    middle third and 0 elsewhere (every channel). Returns the mean squared error."""
    x = (torch.arange(300, dtype=torch.float32) + 0.5) / 300
    points = torch.stack([x, torch.full_like(x, 0.5), torch.full_like(x, 0.5)], dim=1)
    target = ((x > 1 / 3) & (x < 2 / 3)).float()[:, None].expand(-1, 3)
    directions = torch.tensor([[0.0, 0.0, 1.0]]).expand(300, 3)
    optimizer = torch.optim.Adam([field.features] + ([] if field.head is None else list(field.head.parameters())),
                                 lr=2e-2)
    for _ in range(steps):
        _, rgb = field.at_stencil(field.stencil(points), points, directions)
        loss = ((rgb - target) ** 2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        _, rgb = field(points, directions)
    return float(((rgb - target) ** 2).mean())


@pytest.mark.slow
def test_the_head_models_a_stripe_inside_one_cell_that_trilinear_logits_cannot():
    """Along a line inside one cell, trilinear logits are linear, so their sigmoid is
    monotone. The best monotone fit of a 0-1-0 stripe over equal thirds is isotonic
    regression's (0, 1/2, 1/2) or its mirror: mean squared error 1/6 exactly, a bound no
    number of steps can beat. The head's ReLU layer makes colour piecewise linear in the
    features, so it can rise and fall inside the cell."""
    torch.manual_seed(0)
    plain = _random_field(0, resolution=1)
    plain_error = _fit_stripe(plain, 1500)
    assert plain_error >= 1 / 6 - 1e-3  # the bound holds (up to the 300 samples' discretisation)
    with_head = _random_field(0, resolution=1)
    with torch.random.fork_rng():
        torch.manual_seed(3)
        with_head.add_residual_head(12)
    head_error = _fit_stripe(with_head, 1500)
    assert head_error < (1 / 6) / 4


def test_the_rule_follows_the_user_keeps_the_head_off_a_view_dependent_grid_and_off_by_default():
    for kind in ("bounded", "contracted", "forward"):
        head, reason = colour_head_for(TrainConfig(dataset="d", steps=10, view_dependent=False, parametrisation=kind))
        assert head is False and "--colour-head on" in reason
    head, reason = colour_head_for(TrainConfig(dataset="d", steps=10, view_dependent=True, parametrisation="bounded"))
    assert head is False and "view-dependent" in reason
    for wanted in (True, False):
        config = TrainConfig(dataset="d", steps=10, view_dependent=False, parametrisation="bounded",
                             colour_head=wanted)
        assert colour_head_for(config) == (wanted, "set on the command line")


def test_config_keeps_older_recipes_and_refuses_what_cannot_take_the_head():
    assert "colour_head" not in TrainConfig(dataset="d", steps=1).to_json()
    assert TrainConfig(dataset="d", steps=1, colour_head=False).to_json()["colour_head"] is False
    from nerfgauge.core.errors import InputError
    for bad in ({"colour_head": "yes"}, {"colour_head": True, "model": "vanilla"},
                {"colour_head": True, "view_dependent": True}):
        with pytest.raises(InputError):
            TrainConfig(dataset="d", steps=1, **bad).validate()


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory, make_dataset):
    return make_dataset(tmp_path_factory.mktemp("head") / "data", views=12, val_views=2, test_views=2,
                        width=32, height=32, spp=8)


def test_cli_refuses_the_head_on_a_view_dependent_grid(small_dataset, tmp_path, capsys):
    one_line_exit_2(capsys, ["train", small_dataset, "--out", tmp_path / "r", "--steps", "5", "--quiet",
                             "--colour-head", "on", "--view-dependent", "on"], "--colour-head on", "diffuse")
    assert not (tmp_path / "r" / "model.pt").exists()


@pytest.mark.slow
def test_a_run_adds_the_head_at_its_final_grid_saves_it_renders_it_and_resumes_it(small_dataset, tmp_path):
    """420 steps: the grid grows at steps 100, 200 and 300 (MIN_STAGE_STEPS), so the head
    is added at step 400, once the final grid trained 100 steps (20 steps train it): `on`
    adds it, `auto` does not, and config.json says which and why (auto leaves no
    `colour_head` key: the recipe of a run made before the head). What is asserted is the
    schedule and the saved state, not image quality: 1024 rays a step suffice."""
    from nerfgauge.nerf.checkpoint import load_checked, load_model, restore_model

    runs = {}
    for choice in ("on", "auto"):
        run = runs[choice] = tmp_path / choice
        assert main(["train", str(small_dataset), "--out", str(run), "--steps", "420", "--quiet",
                     "--colour-head", choice, "--threads", "1", "--batch-rays", "1024"]) == 0
    on = json.loads((runs["on"] / "config.json").read_text())
    auto = json.loads((runs["auto"] / "config.json").read_text())
    assert on["colour_head"] is True and on["auto_reasons"]["colour_head"] == "set on the command line"
    assert "colour_head" not in auto and "not by default" in auto["auto_reasons"]["colour_head"]
    model, config = load_model(runs["on"] / "model.pt")
    assert model.field.residual_head and model.field.channels == config.feature_channels
    assert load_model(runs["auto"] / "model.pt")[0].field.head is None
    # the training checkpoint restores the head and every value exactly
    saved = load_checked(runs["on"] / "checkpoint.pt", "checkpoint")
    restored = restore_model(saved, TrainConfig(**saved["config"]), saved["model"]["state"]["field.aabb"], "ckpt")
    state = restored.state_dict()
    assert set(state) == set(saved["model"]["state"])
    assert all(torch.equal(state[k], saved["model"]["state"][k]) for k in state)
    # renders, and a resumed run continues with the head
    assert main(["render", str(runs["on"]), "--out", str(tmp_path / "renders"), "--quiet"]) == 0
    assert main(["train", str(small_dataset), "--out", str(runs["on"]), "--steps", "440", "--resume", "--quiet",
                 "--colour-head", "on", "--threads", "1", "--batch-rays", "1024"]) == 0
    steps = [json.loads(line)["step"] for line in (runs["on"] / "log.jsonl").read_text().splitlines()]
    assert steps[-1] == 440
    assert load_model(runs["on"] / "model.pt")[0].field.residual_head
