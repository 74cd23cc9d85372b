"""The rate a run ends at (nerf.schedule's `lr_scale`): a budget of up to LR_DECADE_STEPS
steps decays by LR_FINAL_FRACTION over its fraction alone, a longer grid run one more decade
every LR_DECADE_STEPS steps past that (past its half-budget refinement decision, for a run
that makes one, when that comes later), down to LR_MIN_FRACTION. The expected rates are
written as powers of ten from the rule's words (log10 of the scale is minus the decades), not
through the function's own arithmetic; then a tiny run shows the loop hands Adam that rate."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import nerfgauge.nerf.schedule as S
from nerfgauge.nerf.checkpoint import LoopState
from nerfgauge.nerf.config import refined_resolution
from nerfgauge.nerf.schedule import Schedule

DECADE = S.LR_DECADE_STEPS


def make(steps=None, budget=None, grid=True, refines=True) -> Schedule:
    return Schedule(steps=steps, budget_seconds=budget, start_resolution=27, final_resolution=109,
                    refined_resolution=refined_resolution(109), grid=grid, budget_decides=budget is not None,
                    edges=refines, refine_grid=refines, colour_head=False)


def decided_at_half(steps: int, step: int, seconds: float = 0.0) -> LoopState:
    """The loop at `step` of a run whose refinement was decided at half its `steps` (the
    first step at or past the half, as `refinement_due` decides), once it is that far."""
    half = math.ceil(steps / 2)
    return LoopState(step=step, seconds=seconds, edge_points_step=half if step >= half else 0)


def scale(schedule: Schedule, state: LoopState) -> float:
    return schedule.lr_scale(state, schedule.fraction_done(state))


def test_the_constants_say_a_decade_a_budget_and_a_floor_below_it():
    """The rule's words hold for these values: one decade (x 0.1) over a budget, so the floor
    lies below a short run's end."""
    assert S.LR_FINAL_FRACTION == pytest.approx(0.1)
    assert 0 < S.LR_MIN_FRACTION < S.LR_FINAL_FRACTION and DECADE > 0


@settings(max_examples=60, deadline=None)
@given(steps=st.integers(1, DECADE), at=st.floats(0, 1))
def test_a_run_of_up_to_the_decade_steps_decays_by_its_fraction_alone(steps, at):
    """A --steps run of at most LR_DECADE_STEPS steps: log10(scale) = -step / steps, as before
    the rule, at every step."""
    schedule = make(steps=steps)
    state = LoopState(step=min(steps, math.floor(at * steps)))
    assert math.log10(scale(schedule, state)) == pytest.approx(-state.step / steps, abs=1e-12)


@settings(max_examples=60, deadline=None)
@given(step=st.integers(0, DECADE), seconds=st.floats(0, 600.0))
def test_a_time_budget_within_the_decade_steps_decays_by_its_seconds_alone(step, seconds):
    schedule = make(budget=600.0)
    state = LoopState(step=step, seconds=seconds)
    assert math.log10(scale(schedule, state)) == pytest.approx(-seconds / 600.0, abs=1e-12)


@pytest.mark.parametrize("decades", [1.5, 2.0])
def test_a_long_steps_run_ends_one_more_decade_down_per_decade_steps_past_the_first(decades):
    """A run of 1.5 and 2 x LR_DECADE_STEPS steps ends at 10^-(1 + 0.5) and 10^-(1 + 1) of its
    base rate; halfway through the extra decades it stands at 10^-(fraction + half of them)."""
    steps = round(decades * DECADE)
    schedule = make(steps=steps)
    past = steps - DECADE
    assert math.log10(scale(schedule, decided_at_half(steps, steps))) == pytest.approx(-(1 + past / DECADE), abs=1e-9)
    middle = DECADE + past // 2
    expected = -(middle / steps + (past // 2) / DECADE)
    assert math.log10(scale(schedule, decided_at_half(steps, middle))) == pytest.approx(expected, abs=1e-9)


def test_a_run_that_refines_past_the_decade_steps_starts_the_extra_decay_at_that_decision():
    """Six decade-steps: the refinement is decided at 3 x LR_DECADE_STEPS, and until then the
    rate follows the plain decay alone (the refined grid gets a rate that can still move its
    outlines); one decade-step after it, it stands one decade below the plain decay."""
    steps = 6 * DECADE
    schedule = make(steps=steps)
    before = decided_at_half(steps, 3 * DECADE - 1)
    assert before.edge_points_step == 0
    assert math.log10(scale(schedule, before)) == pytest.approx(-(3 * DECADE - 1) / steps, abs=1e-12)
    after = decided_at_half(steps, 4 * DECADE)
    assert math.log10(scale(schedule, after)) == pytest.approx(-(4 * DECADE / steps + 1), abs=1e-9)


def test_a_run_that_makes_no_refinement_decision_counts_from_the_decade_steps():
    """Neither edges nor --refine-grid: nothing is decided at half the budget, and the extra
    decay starts at LR_DECADE_STEPS as it always did."""
    steps = 4 * DECADE
    schedule = make(steps=steps, refines=False)
    state = LoopState(step=2 * DECADE)
    assert math.log10(scale(schedule, state)) == pytest.approx(-(2 * DECADE / steps + 1), abs=1e-9)


def test_the_extra_decay_stops_at_the_floor():
    """Four decade-steps: the plain decay ends at 10^-1 and three extra decades would take it
    to 10^-4; the floor LR_MIN_FRACTION holds it (and the floor never lifts a rate above the
    plain decay's)."""
    schedule = make(steps=4 * DECADE, refines=False)
    assert scale(schedule, LoopState(step=4 * DECADE)) == pytest.approx(S.LR_MIN_FRACTION)
    assert 10 ** -(1 + 3) < S.LR_MIN_FRACTION
    early = LoopState(step=DECADE + 1)
    assert scale(schedule, early) <= 10 ** -((DECADE + 1) / (4 * DECADE))


def test_a_steps_run_and_a_time_budget_of_as_many_steps_end_at_the_same_rate():
    steps = 2 * DECADE + 400
    by_steps = scale(make(steps=steps), decided_at_half(steps, steps))
    by_time = scale(make(budget=1200.0), decided_at_half(steps, steps, seconds=1200.0))
    decided = math.ceil(steps / 2)  # past LR_DECADE_STEPS: the extra decay counts from here
    assert decided > DECADE
    assert by_steps == by_time == pytest.approx(10 ** -(1 + (steps - decided) / DECADE))


def test_the_vanilla_nerf_keeps_its_recipes_decay_however_long_it_runs():
    schedule = make(steps=3 * DECADE, grid=False)
    assert math.log10(scale(schedule, LoopState(step=3 * DECADE))) == pytest.approx(-1.0)


@settings(max_examples=40, deadline=None)
@given(steps=st.integers(1, 5 * DECADE), per_step=st.floats(0.01, 1.0))
def test_the_rate_never_rises_along_a_run(steps, per_step):
    """Along a --steps run and along a time budget at a steady rate, sampled at 200 points:
    each scale at most the one before (Adam's moments assume a rate that only falls)."""
    for schedule, seconds in ((make(steps=steps), None), (make(budget=steps * per_step), per_step)):
        points = sorted({round(steps * k / 200) for k in range(201)})
        scales = [scale(schedule, decided_at_half(steps, p, p * seconds if seconds else 0.0)) for p in points]
        assert all(b <= a * (1 + 1e-12) for a, b in zip(scales, scales[1:]))


@pytest.mark.parametrize("switch", [0.5, 0.62])
def test_after_surface_opacity_turns_on_the_colour_anneals_to_the_floor_and_the_density_does_not(switch):
    """Surface opacity turned on at `switch` of a long run (LoopState.anneal_from): from there
    the colour tables' log10(scale) falls along a straight line in the budget's fraction,
    from the plain decay's -switch to log10(LR_MIN_FRACTION) at the end, or with the density
    where the density's is lower; the density keeps the decade rule (`lr_scale`), and before
    the switch both follow the plain decay."""
    steps = 4 * DECADE
    schedule = make(steps=steps)
    floor = math.log10(S.LR_MIN_FRACTION)
    decided = round(switch * steps)
    for fraction in (switch, (switch + 1) / 2, 1.0):
        state = LoopState(step=round(fraction * steps), edge_points_step=decided, surface_step=decided,
                          anneal_from=switch)
        scales = schedule.lr_scales(state, fraction)
        line = -switch + (floor + switch) * (fraction - switch) / (1 - switch)
        decades = max(0.0, (state.step - max(DECADE, decided)) / DECADE)
        density = max(-fraction - decades, floor)
        assert math.log10(scales["density"]) == pytest.approx(density, abs=1e-9)
        assert math.log10(scales["colour"]) == pytest.approx(min(line, density), abs=1e-9)  # never above the density's
    late = LoopState(step=steps + 500, edge_points_step=decided, surface_step=decided, anneal_from=switch)
    assert schedule.lr_scales(late, 1.02)["colour"] == pytest.approx(S.LR_MIN_FRACTION)  # a budget's last step may overrun
    off = LoopState(step=steps, edge_points_step=decided)
    assert schedule.lr_scales(off, 1.0)["colour"] == schedule.lr_scales(off, 1.0)["density"] == scale(schedule, off)


@pytest.mark.slow
def test_the_loop_hands_adam_the_schedules_rate(tiny_dataset, tmp_path, monkeypatch):
    """A 50-step `edges` run with the decade at 20 steps decides its refinement at step 25,
    past the decade, so the extra decay counts from there: Adam's grid group (in
    checkpoint.pt) holds the rate of the last step, 49: base x 10^-(49/50 + 24/20)."""
    from nerfgauge.cli import main
    from nerfgauge.nerf.checkpoint import load_checked

    monkeypatch.setattr(S, "LR_DECADE_STEPS", 20)
    run = tmp_path / "run"
    assert main(["train", str(tiny_dataset), "--out", str(run), "--steps", "50", "--quiet", "--threads", "1",
                 "--batch-rays", "256", "--pixel-filter", "edges"]) == 0
    saved = load_checked(run / "checkpoint.pt", "checkpoint")
    assert saved["loop"]["edge_points_step"] == 25
    group = saved["optimizer"]["param_groups"][0]
    assert group["lr"] == pytest.approx(group["base_lr"] * 10 ** -(49 / 50 + 24 / 20), rel=1e-9)
    assert torch.is_tensor(saved["generator"])


def test_a_checkpoint_from_before_the_density_and_colour_groups_resumes_with_the_same_moments():
    """Adam's state saved when the grid's density and colour features were one group (a run
    killed before the change) loads into today's two groups: each parameter keeps its
    moments and step, each group the saved settings and its name, and the next step moves
    every parameter as the same step on the unsplit optimiser does (Adam is elementwise: to
    float32 rounding, a few ulps of values about 30)."""
    import copy

    from test_compact_nerf import blob_model

    from nerfgauge.core.errors import InputError
    from nerfgauge.nerf.checkpoint import restore_optimizer
    from nerfgauge.nerf.config import TrainConfig
    from nerfgauge.nerf.train import make_optimizer

    config = TrainConfig(dataset="unused")

    def step(model, optimizer):
        optimizer.zero_grad()
        field = model.field
        ((field.density_table ** 2).sum() + (field.features * torch.arange(field.features.numel()).view_as(
            field.features)).sin().sum()).backward()
        optimizer.step()

    model, _ = blob_model(torch.Generator().manual_seed(3))
    old = torch.optim.Adam([{"params": [model.field.density_table, model.field.features], "lr": 0.01,
                             "base_lr": 0.01}], **model.adam_options)
    for _ in range(3):
        step(model, old)
    saved = copy.deepcopy(old.state_dict())
    resumed = copy.deepcopy(model)
    optimizer = make_optimizer(resumed, config)
    restore_optimizer(optimizer, saved, "checkpoint.pt")
    assert [group.get("name") for group in optimizer.param_groups] == ["density", "colour"]
    assert [group["lr"] for group in optimizer.param_groups] == [0.01, 0.01]
    for mine, theirs in ((resumed.field.density_table, model.field.density_table),
                         (resumed.field.features, model.field.features)):
        assert torch.equal(optimizer.state[mine]["exp_avg_sq"], old.state[theirs]["exp_avg_sq"])
    step(model, old)
    step(resumed, optimizer)
    torch.testing.assert_close(resumed.field.density_table, model.field.density_table, rtol=0, atol=1e-5)
    torch.testing.assert_close(resumed.field.features, model.field.features, rtol=0, atol=1e-6)
    # a file whose groups have no names (the vanilla NeRF's one group, say) gets today's
    vanilla = [group | {"params": [0, 1]} for group in saved["param_groups"]]
    plain = torch.optim.Adam([{"params": [resumed.field.density_table, resumed.field.features], "lr": 0.01,
                               "base_lr": 0.01, "name": "all"}])
    restore_optimizer(plain, saved | {"param_groups": vanilla}, "checkpoint.pt")
    assert plain.param_groups[0]["name"] == "all"
    # a group that matches nothing is still a damaged checkpoint
    wrong = saved | {"param_groups": [saved["param_groups"][0] | {"params": [0]}]}
    with pytest.raises(InputError, match="damaged"):
        restore_optimizer(make_optimizer(copy.deepcopy(model), config), wrong, "checkpoint.pt")
