"""The training schedule (nerf.schedule) on its own: each decision at its boundary steps, for
step-counted and time-budgeted runs, with the expected steps derived from the rules'
constants; then a whole run's decisions walked through nerf.train's `_follow_schedule` with a
stand-in model, so the loop applies them where the rules say."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import nerfgauge.nerf.schedule as S
from nerfgauge.nerf.checkpoint import LoopState
from nerfgauge.nerf.config import MAX_AUTO_RESOLUTION, TrainConfig, refined_resolution
from nerfgauge.nerf.schedule import Schedule, start_resolution_for, upsample_count

START, FINAL = 27, 109  # a three-stage ladder (27 -> 43 -> 69 -> 109)


def make(steps=None, budget=None, **changes) -> Schedule:
    """A compact edges run's schedule on the 27 -> 109 ladder; a time budget decides its last growth."""
    fields = dict(steps=steps, budget_seconds=budget, start_resolution=START, final_resolution=FINAL,
                  refined_resolution=refined_resolution(FINAL), grid=True, budget_decides=budget is not None,
                  edges=True, refine_grid=False, colour_head=False)
    return Schedule(**{**fields, **changes})


def at_step(schedule: Schedule, step: int, **loop) -> tuple[LoopState, float]:
    """The loop state at `step` of a --steps run (or at step * seconds_per_step s of a time
    budget: loop["seconds"]) and the fraction of the budget done there."""
    state = LoopState(step=step, **loop)
    return state, schedule.fraction_done(state)


def test_the_fraction_done_counts_steps_or_training_seconds():
    assert make(steps=400).fraction_done(LoopState(step=100, seconds=999.0)) == 100 / 400
    assert make(budget=120.0).fraction_done(LoopState(step=100, seconds=30.0)) == 30.0 / 120.0


def test_the_ladder_has_three_stages_from_27_to_109_and_the_refined_grid_after_it():
    """upsample_count: round(log(final / start) / log(STAGE_RATIO)), at least MIN_UPSAMPLES;
    the stages are geometric, the one after the last is the refined grid."""
    schedule = make(steps=2000)
    assert schedule.stages == max(S.MIN_UPSAMPLES, round(math.log(FINAL / START) / math.log(S.STAGE_RATIO))) == 3
    ratio = (FINAL / START) ** (1 / 3)
    assert [schedule.resolution_at(k) for k in range(5)] == \
        [START, round(START * ratio), round(START * ratio ** 2), FINAL, refined_resolution(FINAL)]


@settings(max_examples=300, deadline=None)
@given(final=st.integers(4, 1024))
def test_the_coarse_to_fine_ladder_starts_near_32_voxels_and_grows_geometrically(final):
    """The default ladder: start grid near START_VOXELS (never above it by more than one
    half-stage, never under 16), stages of about STAGE_RATIO each ending exactly at the
    final grid, and growth at evenly spaced budget fractions ending at LAST_UPSAMPLE_AT.
    Final grids up to 160 voxels keep the three-stage quarter-start ladder (32 * 4^(3.5/3)
    = 161 is where a fourth stage lands nearer 32)."""
    from nerfgauge.nerf.schedule import LAST_UPSAMPLE_AT, MIN_UPSAMPLES, STAGE_RATIO, START_VOXELS

    start = start_resolution_for(final)
    schedule = make(steps=1, start_resolution=start, final_resolution=final, refined_resolution=refined_resolution(final))
    stages = upsample_count(start, final)
    ladder = [schedule.resolution_at(k) for k in range(stages + 1)]
    assert ladder[0] == start and ladder[-1] == final
    assert all(a <= b for a, b in zip(ladder, ladder[1:]))
    assert min(16, final) <= start <= max(16, START_VOXELS * STAGE_RATIO ** 0.5 + 1)
    if final >= 4 * 16:  # no clamp at 16: each stage is about STAGE_RATIO (half a stage of slack each way)
        step = (final / start) ** (1 / stages)
        assert STAGE_RATIO ** 0.5 <= step <= STAGE_RATIO ** 1.5
    if final <= 160:
        assert stages == MIN_UPSAMPLES and start == min(final, max(16, round(final / 4)))
    fractions = [schedule.upsample_at(k) for k in range(stages)]
    assert all(0 < a < b for a, b in zip(fractions, fractions[1:]))
    assert fractions[-1] == pytest.approx(LAST_UPSAMPLE_AT)


@settings(max_examples=300, deadline=None)
@given(final=st.integers(16, 1024), steps=st.integers(1, 5000))
def test_a_fixed_step_run_takes_only_the_stages_it_can_train(final, steps):
    """Each stage waits for MIN_STAGE_STEPS steps, so a --steps run's ladder has at most
    max(MIN_UPSAMPLES, steps / 2 / MIN_STAGE_STEPS) stages (its final grid gets at least
    half the run once that is over MIN_UPSAMPLES stages), never more than the budget
    ladder, and still ends at the final grid; resolve picks that start."""
    import numpy as np

    from nerfgauge.nerf.config import resolve
    from nerfgauge.nerf.schedule import MIN_STAGE_STEPS, MIN_UPSAMPLES

    start = start_resolution_for(final, steps)
    stages = upsample_count(start, final)
    assert stages <= max(MIN_UPSAMPLES, steps // (2 * MIN_STAGE_STEPS))
    assert stages <= upsample_count(start_resolution_for(final), final)
    assert start <= final
    aabb = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    c2w = np.tile(np.eye(4), (2, 1, 1))
    c2w[:, :3, 3] = [[0, 0, 4], [4, 0, 0]]
    resolved, _ = resolve(TrainConfig("d", steps=steps, final_resolution=final, parametrisation="bounded"), None,
                          aabb, c2w, 100.0, 64)
    assert resolved.start_resolution == start


@pytest.mark.parametrize("steps", [2000, 400])
def test_a_steps_run_grows_at_its_fractions_once_the_coarser_grid_had_its_steps(steps):
    """Growth k is due at the first step at or past LAST_UPSAMPLE_AT (k + 1) / stages of the
    run whose grid has trained MIN_STAGE_STEPS steps: 2000 steps grow at 200, 400, 600; 400
    steps (fractions at 40, 80, 120) wait for the stages' steps: 100, 200, 300."""
    schedule = make(steps=steps)
    previous = 0
    for k in range(schedule.stages):
        at = max(round(steps * S.LAST_UPSAMPLE_AT * (k + 1) / schedule.stages), previous + S.MIN_STAGE_STEPS)
        for step, due in ((at - 1, False), (at, True)):
            state, fraction = at_step(schedule, step, stage=k, last_stage=schedule.stages, stage_steps=step - previous)
            assert schedule.growth_due(state, fraction) is due, (k, step)
        previous = at
    assert previous == (600 if steps == 2000 else 300)
    state, fraction = at_step(schedule, steps - 1, stage=schedule.stages, last_stage=schedule.stages, stage_steps=999)
    assert not schedule.growth_due(state, fraction)  # no stage left


def test_a_time_budget_grows_at_its_fractions_of_the_seconds():
    """120 s: growth from stage 0 at 12 s (LAST_UPSAMPLE_AT / 3 of it), from stage 2 at 36 s,
    each once the grid has trained MIN_STAGE_STEPS steps."""
    schedule = make(budget=120.0)
    for k, seconds in ((0, 120.0 * S.LAST_UPSAMPLE_AT / 3), (2, 120.0 * S.LAST_UPSAMPLE_AT)):
        ready = LoopState(seconds=seconds, stage=k, last_stage=3, stage_steps=S.MIN_STAGE_STEPS)
        assert schedule.growth_due(ready, schedule.fraction_done(ready))
        early = dataclasses.replace(ready, seconds=seconds - 0.01)
        assert not schedule.growth_due(early, schedule.fraction_done(early))
        young = dataclasses.replace(ready, stage_steps=S.MIN_STAGE_STEPS - 1)
        assert not schedule.growth_due(young, schedule.fraction_done(young))


def test_only_a_time_budgets_last_growth_in_bounded_or_forward_space_is_on_trial():
    """A --steps run never trials a growth (its schedule stays reproducible); nor does a
    budget for growths before the last BUDGET_DECIDES_LAST_GROWTHS, nor in contracted space,
    nor for the vanilla model (for_run reads the rule from the config)."""
    config = TrainConfig("d", budget_seconds=120.0, final_resolution=108, start_resolution=27,
                         parametrisation="bounded", pixel_filter="edges")

    def of(**changes) -> Schedule:
        return Schedule.for_run(dataclasses.replace(config, **changes), grid=True, refined_resolution=171)

    last = LoopState(stage=3 - S.BUDGET_DECIDES_LAST_GROWTHS)
    assert of().growth_on_trial(last)
    assert not of().growth_on_trial(dataclasses.replace(last, stage=last.stage - 1))
    assert not of(budget_seconds=None, steps=500).growth_on_trial(last)
    assert not of(parametrisation="contracted").growth_on_trial(last)
    assert of(parametrisation="forward").growth_on_trial(last)
    assert not of(model="vanilla").growth_on_trial(last)


def _trial_clock(schedule, seconds_per_window, start_seconds=40.0):
    """Walk a growth's trial through steps_on_trial at window boundaries, the finer grid's
    warm-up taking 1 s and window k taking seconds_per_window[k]: the timings and the
    projection at each call."""
    timing, seen = S.TrialTiming(), []
    stage_steps, stage_seconds = S.GROWTH_TRIAL_WARMUP, 1.0
    per_window = S.GROWTH_TRIAL_STEPS // S.GROWTH_TRIAL_WINDOWS
    for k, window in enumerate([0.0] + list(seconds_per_window)):
        stage_steps += per_window if k else 0
        stage_seconds += window
        state = LoopState(stage_steps=stage_steps, stage_seconds=stage_seconds, seconds=start_seconds + stage_seconds)
        timing, projected = schedule.steps_on_trial(state, timing)
        seen.append((timing, projected, state))
    return seen


def test_a_growth_on_trial_is_timed_after_its_warm_up_and_judged_by_its_own_rate():
    """Nothing is timed during the warm-up; the first window starts at the first call with
    GROWTH_TRIAL_WARMUP steps done; nothing is projected before GROWTH_TRIAL_WINDOWS windows
    of GROWTH_TRIAL_STEPS / GROWTH_TRIAL_WINDOWS steps are timed, nor in the middle of a
    window; then the finer grid's steps in all = steps done + its rate x the budget's
    seconds left, kept at MIN_STEPS_AT_FINER or more."""
    schedule = make(budget=120.0)
    warming = LoopState(stage_steps=S.GROWTH_TRIAL_WARMUP - 1, stage_seconds=1.5, seconds=39.5)
    assert schedule.steps_on_trial(warming, S.TrialTiming()) == (S.TrialTiming(), None)
    per_window = S.GROWTH_TRIAL_STEPS // S.GROWTH_TRIAL_WINDOWS
    seen = _trial_clock(schedule, [0.5] * S.GROWTH_TRIAL_WINDOWS)
    assert seen[0][0] == S.TrialTiming(S.GROWTH_TRIAL_WARMUP, 1.0) and seen[0][1] is None
    assert all(projected is None for _, projected, _ in seen[:-1])
    middle = LoopState(stage_steps=S.GROWTH_TRIAL_WARMUP + per_window - 1, stage_seconds=1.4, seconds=41.4)
    assert schedule.steps_on_trial(middle, seen[0][0]) == (seen[0][0], None)
    timing, projected, state = seen[-1]
    assert timing.rates == (per_window / 0.5,) * S.GROWTH_TRIAL_WINDOWS
    assert state.stage_steps == S.GROWTH_TRIAL_WARMUP + S.GROWTH_TRIAL_STEPS
    assert projected == pytest.approx(state.stage_steps + per_window / 0.5 * (120.0 - state.seconds))
    assert schedule.keeps_growth(S.MIN_STEPS_AT_FINER) and not schedule.keeps_growth(S.MIN_STEPS_AT_FINER - 0.5)


@pytest.mark.parametrize("slow_windows", [0, 1, S.GROWTH_TRIAL_WINDOWS - 1, S.GROWTH_TRIAL_WINDOWS])
def test_a_load_that_passes_within_the_trial_does_not_decide_the_grid(slow_windows):
    """Windows slowed tenfold by another process (an idle window: 0.5 s for its steps, so
    about 1900 steps projected, kept; every window slowed to 5 s: 203, undone): the rate is the fastest
    window's, so the growth stands unless every window was slow. A load that lasts the
    whole trial is the machine the budget has."""
    schedule = make(budget=120.0)
    windows = [5.0] * slow_windows + [0.5] * (S.GROWTH_TRIAL_WINDOWS - slow_windows)
    timing, projected, state = _trial_clock(schedule, windows, start_seconds=20.0)[-1]
    fastest = (S.GROWTH_TRIAL_STEPS // S.GROWTH_TRIAL_WINDOWS) / min(windows)
    assert max(timing.rates) == pytest.approx(fastest)
    assert projected == pytest.approx(state.stage_steps + fastest * (120.0 - state.seconds))
    assert schedule.keeps_growth(projected) == (slow_windows < S.GROWTH_TRIAL_WINDOWS)


@pytest.mark.parametrize("steps", [1000, 2000])
def test_hidden_cells_are_measured_at_each_visibility_fraction_of_a_grid_run(steps):
    """Measurement k is due at the first step at or past VISIBILITY_AT[k] of the run, once."""
    schedule = make(steps=steps)
    for k, fraction in enumerate(S.VISIBILITY_AT):
        at = round(steps * fraction)
        assert not schedule.visibility_due(*at_step(schedule, at - 1, visibility_done=k))
        assert schedule.visibility_due(*at_step(schedule, at, visibility_done=k))
        assert not schedule.visibility_due(*at_step(schedule, at, visibility_done=k + 1))
    assert not dataclasses.replace(schedule, grid=False).visibility_due(*at_step(schedule, steps, visibility_done=0))


def test_occupancy_is_refreshed_every_few_steps_once_the_grid_has_grown():
    every = S.OCCUPANCY_EVERY
    assert Schedule.occupancy_due(LoopState(step=2 * every, stage=1, last_stage=3))
    assert not Schedule.occupancy_due(LoopState(step=2 * every + 1, stage=1, last_stage=3))
    assert not Schedule.occupancy_due(LoopState(step=2 * every, stage=0, last_stage=3))  # all cells live while coarse
    assert Schedule.occupancy_due(LoopState(step=2 * every, stage=0, last_stage=0))  # the start grid is the last


def test_the_colour_head_is_decided_once_the_final_grid_has_trained_its_stage_steps():
    schedule = make(steps=2000)
    settled = LoopState(stage=3, last_stage=3, stage_steps=S.MIN_STAGE_STEPS)
    assert schedule.colour_head_due(settled)
    assert not schedule.colour_head_due(dataclasses.replace(settled, stage_steps=S.MIN_STAGE_STEPS - 1))
    assert not schedule.colour_head_due(dataclasses.replace(settled, stage=2))
    assert not schedule.colour_head_due(dataclasses.replace(settled, colour_head=-1))  # decided already
    assert not dataclasses.replace(schedule, grid=False).colour_head_due(settled)


@pytest.mark.parametrize("steps, budget", [(4000, None), (None, 120.0)])
def test_half_the_budget_refines_a_run_whose_final_grid_has_trained_its_steps(steps, budget):
    """Decided once, at the first step at or past FINE_EDGE_POINTS_AT of the budget (step
    2000 of 4000, 60 s of 120): yes with FINE_EDGE_POINTS_MIN_STEPS steps at the last stage,
    no with one fewer or at a coarser stage; None before, while a trial runs, once decided,
    or for a run with neither the edges filter nor a grid to refine."""
    schedule = make(steps=steps, budget=budget)
    half = dict(step=round(4000 * S.FINE_EDGE_POINTS_AT)) if steps else dict(seconds=120.0 * S.FINE_EDGE_POINTS_AT)
    before = dict(step=half["step"] - 1) if steps else dict(seconds=half["seconds"] - 0.01)
    ready = LoopState(**half, stage=3, last_stage=3, stage_steps=S.FINE_EDGE_POINTS_MIN_STEPS)

    def due(state, trial_pending=False, on=schedule):
        return on.refinement_due(state, on.fraction_done(state), trial_pending)

    assert due(ready) is True
    assert due(dataclasses.replace(ready, **before)) is None
    assert due(dataclasses.replace(ready, stage_steps=S.FINE_EDGE_POINTS_MIN_STEPS - 1)) is False
    assert due(dataclasses.replace(ready, stage=2)) is False  # a coarser grid
    assert due(ready, trial_pending=True) is None  # the last growth is on trial
    assert due(dataclasses.replace(ready, edge_points_step=1)) is None  # decided
    assert due(ready, on=dataclasses.replace(schedule, edges=False)) is None
    assert due(ready, on=dataclasses.replace(schedule, edges=False, refine_grid=True)) is True


@pytest.mark.parametrize("steps, budget", [(4000, None), (None, 120.0)])
def test_the_finer_rung_is_decided_once_past_its_share_by_the_steps_through_3x3_points(steps, budget):
    """An `edges` run at 3 x 3 points takes FINER_EDGE_POINTS_PER_AXIS at the first step at
    or past FINER_EDGE_POINTS_AT of its budget when it has trained FINE_EDGE_POINTS_MIN_STEPS
    steps through them; no earlier, not twice, not from 2 x 2 points, not without edges."""
    schedule = make(steps=steps, budget=budget)
    at = dict(step=round(4000 * S.FINER_EDGE_POINTS_AT)) if steps else dict(seconds=120.0 * S.FINER_EDGE_POINTS_AT,
                                                                              step=3000)
    before = dict(step=at["step"] - 1) if steps else dict(seconds=at["seconds"] - 0.01)
    ready = LoopState(**at, edge_points=S.FINE_EDGE_POINTS_PER_AXIS,
                      edge_points_step=at["step"] - S.FINE_EDGE_POINTS_MIN_STEPS)

    def due(state, on=schedule):
        return on.finer_points_due(state, on.fraction_done(state))

    assert due(ready) is True
    assert due(dataclasses.replace(ready, **before)) is None
    assert due(dataclasses.replace(ready, edge_points_step=ready.edge_points_step + 1)) is False  # 999 steps
    assert due(dataclasses.replace(ready, finer_points_step=1)) is None  # decided
    assert due(dataclasses.replace(ready, edge_points=S.EDGE_POINTS_PER_AXIS)) is None  # never refined
    assert due(ready, on=dataclasses.replace(schedule, edges=False)) is None
    taken = dataclasses.replace(ready, edge_points=S.FINER_EDGE_POINTS_PER_AXIS, finer_points_step=ready.step)
    assert S.Schedule.edge_points_reason(taken).startswith(
        f"2 x 2 to step {ready.edge_points_step}, then 3 x 3: at 50% of the budget") and \
        f"then 4 x 4 from step {ready.step}: at 75% of the budget" in S.Schedule.edge_points_reason(taken)
    kept = dataclasses.replace(ready, finer_points_step=ready.step)
    assert f"kept at 75% of the budget (step {ready.step}): fewer than" in S.Schedule.edge_points_reason(kept)
    assert S.Schedule.edge_points_reason(ready).endswith("the run ended before 75% of the budget")


def test_a_refining_run_grows_past_its_final_grid_only_at_its_last_stage_and_below_the_cap():
    schedule = make(steps=4000, refine_grid=True)
    final = LoopState(stage=schedule.stages, last_stage=schedule.stages)
    assert schedule.grows_past_final(final)
    assert not schedule.grows_past_final(dataclasses.replace(final, stage=schedule.stages - 1, last_stage=2))  # undone
    assert not dataclasses.replace(schedule, refine_grid=False).grows_past_final(final)
    capped = make(steps=4000, refine_grid=True, final_resolution=MAX_AUTO_RESOLUTION,
                  refined_resolution=refined_resolution(MAX_AUTO_RESOLUTION))
    assert not capped.grows_past_final(LoopState(stage=capped.stages, last_stage=capped.stages))


def test_the_refine_reason_says_what_happened_to_the_grid():
    """refine_grid_reason names the outcome: grown; the run ended before half; the budget
    never reached the footprint's grid; for an `edges` run, not converged at half (2 x 2
    kept) or converged but the finer grid's growth undone (3 x 3 taken); otherwise both."""
    schedule = make(budget=600.0, refine_grid=True)
    last = schedule.stages
    decided = LoopState(step=6000, stage=last, last_stage=last, edge_points_step=5000)
    assert schedule.refine_grid_reason(dataclasses.replace(decided, stage=last + 1, last_stage=last + 1),
                                       173).startswith("109 -> 173 voxels from step 5000")
    assert "ended before 50%" in schedule.refine_grid_reason(dataclasses.replace(decided, edge_points_step=0), 109)
    assert "could not train the footprint's 109" in schedule.refine_grid_reason(
        dataclasses.replace(decided, stage=last - 1, last_stage=last - 1), 68)
    not_converged = schedule.refine_grid_reason(decided, 109)
    assert "fewer than" in not_converged and "undone" not in not_converged
    for points in (3, 4):  # 3 x 3 taken, and the rung past it
        undone = schedule.refine_grid_reason(dataclasses.replace(decided, edge_points=points), 109)
        assert "undone" in undone and "fewer than" not in undone
    either = dataclasses.replace(schedule, edges=False).refine_grid_reason(decided, 109)
    assert "fewer than" in either and "undone" in either


# --- a whole run's decisions, applied by nerf.train -------------------------------------------


def walk(schedule: Schedule, seconds_per_step: float) -> tuple[LoopState, dict]:
    """Drive nerf.train._follow_schedule step by step as the loop does (growths, trials,
    colour head, refinement), with a stand-in for the model whose grid follows the stages
    and a fixed time a step; visibility measurements as the loop counts them. Returns the
    final loop state and {event: [steps]}."""
    from nerfgauge.nerf.train import Training, _follow_schedule

    state = LoopState(last_stage=schedule.stages)
    model = SimpleNamespace(field=SimpleNamespace(resolution=schedule.start_resolution))
    training = Training(model, None, None, state)
    events = {"growth": [], "visibility": [], "colour_head": [], "refined": [], "undone": []}
    trial = None
    while True:
        fraction = schedule.fraction_done(state)
        if schedule.visibility_due(state, fraction):
            state.visibility_done += 1
            events["visibility"].append(state.step)
        if fraction >= 1:
            break
        stage, last_stage, colour_head = state.stage, state.last_stage, state.colour_head
        trial = _follow_schedule(training, schedule, trial, fraction, progress=False)
        if state.stage > stage:
            events["growth"].append(state.step)
        if state.stage < stage:
            events["undone"].append(state.step)
        if state.colour_head != colour_head:
            events["colour_head"].append(state.step)
        if state.last_stage > last_stage:
            events["refined"].append(state.step)
        training.model.field.resolution = schedule.resolution_at(state.stage)  # the step's _grow_grid
        state.step += 1
        state.stage_steps += 1
        state.stage_seconds += seconds_per_step
        state.seconds += seconds_per_step
    return state, events


def test_a_steps_run_walks_its_schedule_at_the_derived_steps():
    """4000 steps on the 27 -> 109 ladder with --refine-grid: growths at 400, 800, 1200
    (LAST_UPSAMPLE_AT / 3 apart); visibility at 1600, 2800 and 4000 (VISIBILITY_AT: the last
    before the end's checkpoint); the colour head decided MIN_STAGE_STEPS into the final grid; at 2000 (half)
    the final grid has trained 800 steps < FINE_EDGE_POINTS_MIN_STEPS: 2 x 2 points kept and
    no refined grid. With the bar at 800 it refines: 3 x 3 points and a fourth growth at 2001."""
    steps = 4000
    schedule = make(steps=steps, refine_grid=True)
    growths = [round(steps * S.LAST_UPSAMPLE_AT * (k + 1) / 3) for k in range(3)]
    state, events = walk(schedule, 0.01)
    assert events["growth"] == growths == [400, 800, 1200]
    assert events["visibility"] == [round(steps * f) for f in S.VISIBILITY_AT] == [1600, 2800, 4000]
    assert events["colour_head"] == [growths[-1] + S.MIN_STAGE_STEPS]
    half = round(steps * S.FINE_EDGE_POINTS_AT)
    assert half - growths[-1] < S.FINE_EDGE_POINTS_MIN_STEPS
    assert (state.edge_points_step, state.edge_points, events["refined"]) == (half, S.EDGE_POINTS_PER_AXIS, [])


def test_a_steps_run_whose_final_grid_converged_by_half_refines(monkeypatch):
    steps = 4000
    half, final_from = round(steps * S.FINE_EDGE_POINTS_AT), round(steps * S.LAST_UPSAMPLE_AT)
    monkeypatch.setattr(S, "FINE_EDGE_POINTS_MIN_STEPS", half - final_from)  # exactly what it has at half
    state, events = walk(make(steps=steps, refine_grid=True), 0.01)
    # then, at FINER_EDGE_POINTS_AT, the 3 x 3 points have trained 1000 >= the bar's steps: one rung up
    finer = round(steps * S.FINER_EDGE_POINTS_AT)
    assert (state.edge_points_step, state.finer_points_step, state.edge_points) == \
        (half, finer, S.FINER_EDGE_POINTS_PER_AXIS)
    assert events["refined"] == [half] and events["growth"][-1] == half + 1  # the next step grows it
    assert state.stage == state.last_stage == 4


@pytest.mark.parametrize("per_step", [1 / 16, 1 / 8])
def test_a_time_budget_walks_its_schedule_and_its_trial_keeps_or_undoes_the_last_growth(per_step):
    """120 s at a fixed time a step (exact in binary). Growth k at the first step past
    LAST_UPSAMPLE_AT (k + 1) / 3 of the seconds, once the grid had MIN_STAGE_STEPS steps:
    1/16 s a step grows at 192, 384, 576; 1/8 s a step waits for the stages' steps: 100, 200,
    300. The last growth is on trial and judged GROWTH_TRIAL_WARMUP + GROWTH_TRIAL_STEPS steps
    later by its rate (1 / per_step steps a second) times the seconds left, plus the steps
    done: 1344 >= MIN_STEPS_AT_FINER at 1/16 s (kept), 660 at 1/8 s (undone: stage 2 is the last)."""
    budget = 120.0
    state, events = walk(make(budget=budget), per_step)
    per_second = round(1 / per_step)
    growths, previous = [], 0
    for k in range(3):
        previous = max(round(budget * S.LAST_UPSAMPLE_AT * (k + 1) / 3 * per_second), previous + S.MIN_STAGE_STEPS)
        growths.append(previous)
    assert events["growth"] == growths == ([192, 384, 576] if per_step == 1 / 16 else [100, 200, 300])
    trial_steps = S.GROWTH_TRIAL_WARMUP + S.GROWTH_TRIAL_STEPS
    judged = growths[-1] + trial_steps
    projected = trial_steps + per_second * (budget - judged * per_step)
    assert projected == (1344 if per_step == 1 / 16 else 660)
    if projected >= S.MIN_STEPS_AT_FINER:
        assert events["undone"] == [] and state.stage == state.last_stage == 3
    else:
        assert events["undone"] == [judged] and state.stage == state.last_stage == 2
    assert state.step == round(budget * per_second)


def test_the_training_loop_reads_as_short_functions():
    """With the schedule's decisions in nerf.schedule, no function of nerf/train.py runs
    past 80 lines, and the loop itself (_train_in) stays under 60."""
    import ast
    from pathlib import Path

    source = (Path(__file__).resolve().parent.parent / "nerf" / "train.py").read_text()
    lengths = {node.name: node.end_lineno - node.lineno + 1 for node in ast.walk(ast.parse(source))
               if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))}
    assert max(lengths.values()) <= 80, {name: n for name, n in lengths.items() if n > 80}
    assert lengths["_train_in"] < 60
