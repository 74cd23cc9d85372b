"""The training schedule: when the grid grows, when the last growth is on trial, and what a
converged run refines at half its budget, as one object whose methods are the decisions.

A run's budget is a number of steps (`--steps N`: its schedule is fixed by the step count,
so the run is reproducible) or of training seconds (`--budget-seconds T`); the fraction of
it done drives every phase:

    0 ............ LAST_UPSAMPLE_AT ............ FINE_EDGE_POINTS_AT ............ 1
    coarse to fine: the grid grows      the final grid trains; at half the budget a run
    at evenly spaced fractions, each    whose final grid has trained FINE_EDGE_POINTS_MIN_STEPS
    once the coarser grid had           steps refines: an `edges` run's edge pixels through
    MIN_STAGE_STEPS steps; a time       3 x 3 points, a --refine-grid run's grid one stage
    budget's last growth is on trial    past the final one (on trial too, for a time budget)
    (kept when its measured rate
    gives it MIN_STEPS_AT_FINER steps)
    hidden cells are measured and skipped at VISIBILITY_AT; the residual colour head is
    decided once the final grid has trained MIN_STAGE_STEPS steps

The loop's counters (nerf.checkpoint.LoopState, saved in checkpoint.pt) are the schedule's
whole state: `Schedule` is frozen, reads them and answers; nerf.train applies the answers
(grows the grid, starts or undoes a trial, switches the edge points). The coarse-to-fine
ladder itself (`start_resolution_for`, `upsample_count`) is here too: nerf.config resolves a
run's start grid with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

# Coarse to fine: each stage grows the grid by this factor, from a start grid of about
# START_VOXELS, in at least MIN_UPSAMPLES stages. A start of a quarter of the final grid
# (three stages) was the rule until a 218-voxel final grid started at 54: at 256 px its
# 120 s run took 1546 steps to 38.0 dB, where a ladder from 34 took 2182 to 38.75
# (BENCHMARKS.md). The start grid only has to find where matter is, not resolve it.
STAGE_RATIO = 4 ** (1 / 3)
START_VOXELS = 32
MIN_UPSAMPLES = 3
LAST_UPSAMPLE_AT = 0.3  # the grid grows at evenly spaced fractions of the budget up to this ...
MIN_STAGE_STEPS = 100  # ... once the coarser grid had this many steps (short budgets need them)
# A time budget keeps a finer grid only if it can still give it this many steps: the finer
# grid trains GROWTH_TRIAL_STEPS steps first, timed, and the growth is undone when its
# measured rate times the seconds left falls short. Measured on primitives, 120 s, 2 CPU
# cores (BENCHMARKS.md): at 256 px the 218 grid got ~640 steps and scored 37.5 dB, the 137
# grid it skipped to ~1300-1500 steps and 38.7, so the bar sits between. (A projection from
# the coarser grid's rate times the resolution ratio, used before, was 35% pessimistic from
# the 68 grid at 128 px: the 109 grid ran at 0.84x its rate, not 0.62x, and two idle 120-s
# runs split 41.32 / 39.33 dB on which side of the bar it fell.)
MIN_STEPS_AT_FINER = 800
# ... and only for the last growth: earlier stages are cheap (a 76-voxel grid costs a
# fraction of a 218 one), and a bar set on primitives' rates kept far-reaching's
# contracted grid at its 30-voxel start (20.8 dB, against 22.8 at 48 voxels).
BUDGET_DECIDES_LAST_GROWTHS = 1
# ... and only in these spaces. In contracted space the final grid (at most 192) is what
# the inner ball needs to be sharp, and it wins with few steps: far-reaching 128 px, 120 s
# scored 27.35 dB with the 192 grid's ~170 steps (the projection said ~173) against 26.83
# with the 121 grid the bar kept (BENCHMARKS.md).
BUDGET_DECIDES_IN = ("bounded", "forward")
GROWTH_TRIAL_WARMUP = 5  # steps of a new grid not timed: the first allocate its rows and moments
GROWTH_TRIAL_STEPS = 40  # steps timed after them; ~3 s of a 120-s budget at 128 px ...
# ... in this many windows of equal steps, and the rate is the fastest window's: another
# process can only slow a window down, so the fastest is the nearest to the machine's own
# rate, and a load that passes within the trial no longer decides the grid for the whole
# run. (What prompted it: a test suite started beside a 300-s run on thin kept a 35-voxel
# grid, 40.05 dB against 44.52 idle; that suite outlasted the trial, so there the windows
# would not have helped.) A load that lasts the whole trial still counts: a budget follows
# the machine it has.
GROWTH_TRIAL_WINDOWS = 4
VISIBILITY_AT = (0.4, 0.7, 1.0)  # fractions where hidden cells are measured and skipped
OCCUPANCY_EVERY = 16  # steps between occupancy-grid updates
# The `edges` filter's edge pixels (nerfgauge.core.pixel_edges) train through the centres
# of a k x k grid of cells, k = EDGE_POINTS_PER_AXIS (2 x 2, as the box render) at first.
# When FINE_EDGE_POINTS_AT of the budget (steps or seconds) is gone, a run whose final grid
# has trained FINE_EDGE_POINTS_MIN_STEPS steps by then takes k = FINE_EDGE_POINTS_PER_AXIS
# for the rest (`Schedule.refinement_due`). A sharp field's box mean wants more than 2 x 2
# points (the k x k midpoint rule puts a straight step edge's coverage up to 1/(2k) off: a
# quarter of the step for 2 x 2, a sixth for 3 x 3), and the model fits the points it is
# trained through. Its steps cost 1.5-1.9x, which only a model converged at its final grid,
# with budget left, repays. Primitives 128 px at 1 thread, 600 s, switched at half the
# budget 1189 steps into the final grid: 44.17 dB against 43.89 with 2 x 2 throughout and
# 44.01 with 3 x 3 throughout; 120 s, switched at half the budget 268 steps into it: 38.38
# against 39.55; far-object 64 px (in no bench), 600 s: 45.24 against 44.68 (BENCHMARKS.md,
# "Finer points in the second half").
# The same decision grows the grid of an `edges` run whose final resolution the pixel
# footprint set one coarse-to-fine stage past it (x STAGE_RATIO, at most
# nerf.config.MAX_AUTO_RESOLUTION; TrainConfig.refine_grid, nerf.config.refine_grid_for):
# the footprint's grid is what the pixels resolve through one ray, and a model trained
# through several points a pixel can use a finer one once it has converged. Primitives
# 128 px at 1 thread, 600 s: 44.54 dB against 44.19 with 3 x 3 points on the 109 grid (173
# voxels from step 3541 of 5239); far-object 64 px (in no bench; its texture sets a grid
# finer than its pixels, so the rule leaves it alone): 44.33 refined against 44.97; thin
# 128 px (in no train bench; its grid is the footprint's, 104 -> 165): 47.48 against 45.64
# (BENCHMARKS.md, "A finer grid in the second half").
EDGE_POINTS_PER_AXIS = 2
FINE_EDGE_POINTS_PER_AXIS = 3
FINE_EDGE_POINTS_AT = 0.5
FINE_EDGE_POINTS_MIN_STEPS = 1000
# One rung more: at FINER_EDGE_POINTS_AT of the budget, a run whose edge pixels have trained
# FINE_EDGE_POINTS_MIN_STEPS steps through 3 x 3 points takes FINER_EDGE_POINTS_PER_AXIS per
# axis for the rest (`Schedule.finer_points_due`; the render filter edges-4x4 renders them).
# The midpoint rule through 3 x 3 points still puts a step's coverage up to a sixth off, and a
# field fitted through them draws every outline for those points. Primitives 128 px, a fresh
# 600-s model (46.81 dB) trained 1500 more steps (rate 0.01 -> 3e-4, 1 thread): through 4 x 4
# points 47.41 dB, through 3 x 3 46.95; every outline gains (checker sphere 0.0302 -> 0.0280
# RMS, blue box 0.0174 -> 0.0161, green cylinder 0.0163 -> 0.0144) (docs/results.md, "Four
# by four points"). Its steps cost about 1.6 times a 3 x 3 step's at 1 thread. Checked on two
# scenes in no bench (64 px, 6000 steps, with against without, each through the render its
# filter rule chose): far-object 49.67 against 49.36 dB, thin 44.15 against 44.01 ("The rung on
# captures it was not tuned on").
FINER_EDGE_POINTS_PER_AXIS = 4
FINER_EDGE_POINTS_AT = 0.75
# The learning rate decays exponentially, by LR_FINAL_FRACTION over the budget's fraction
# (steps or seconds), and past LR_DECADE_STEPS steps by one more such factor every
# LR_DECADE_STEPS steps, down to LR_MIN_FRACTION of its base (`Schedule.lr_scale`). Adam
# moves a voxel by about the learning rate each step it is hit, whatever its gradient's
# size, so the rate a run ends at sets how far its grid jitters about its fit; a run that
# ends at the same rate however long it trains stops growing at the same figure. Primitives
# 128 px at 600 s ended at 0.1 x 0.1 and scored 44.68 dB, at 1200 s 44.58 (the interior 2 dB
# under the 109 grid's), and the 600-s model trained on from 0.01 down to 3e-4 for 1500 steps
# scored 45.08 (interior +2.1 dB, edges +0.3). With this rule, step-budgeted: 12400 steps
# 45.13 dB against 44.76 at 6200 (interior 44.56 against 42.52; docs/results.md, "Quality
# past 600 s"). Runs of up to LR_DECADE_STEPS steps (a 600-s run at 128 px, idle, takes
# ~6200) decay as before, by construction.
# A run that refines at half its budget (an `edges` or --refine-grid run: finer edge points,
# a finer grid) starts the extra decay no earlier than that decision (`Schedule.decay_start`):
# the refined model has to move its outlines, which takes the rate. Counted from step 6000,
# a 2400-s run refined at step ~21000 at the floor rate and its edges fell 4 dB below the
# 1200-s run's (32.52 against 36.54; docs/results.md, "The 2400-s point"). Runs that decide
# before step LR_DECADE_STEPS (600 s and less) are unchanged; a 1200-s run decides at step
# 7800-9100 (idle, 2026-11-29) and so starts its extra decay that much later: 45.05 and 45.01
# dB against 44.92 before (docs/results.md, "Idle, time budgets").
# Surface opacity (TrainConfig.surface_opacity; nerf.packed.occupancy_rise_taus) turns on at
# the same decision as the finer points, with occupancy o = 1 - exp(-sigma * SURFACE_RISE_STEPS
# marching steps): a converged density model's faint fronts become occupancies of that
# length, its interiors stay opaque. The silhouettes' skin was the density's learned
# prefilter for the edge points, and a ray grazing a face took it over the face's width
# (too-wide outlines that follow the camera's elevation, docs/results.md, "Where the outline
# error comes from"); an occupancy is taken once. q7's 600-s checkpoint (primitives 128 px)
# trained 3000 more steps at rate 0.03 -> 3e-4: 46.38 dB through 3 x 3 points, outline alpha
# bias +0.0002 / RMS 0.0362, against 45.98, +0.0093 / 0.0410 with density opacity; 2 steps
# (1500 steps at 0.01 -> 3e-4: bias -0.021) against 8 (+0.024) (docs/results.md, "Surface opacity").
SURFACE_RISE_STEPS = 2.0
LR_FINAL_FRACTION = 0.1
LR_DECADE_STEPS = 6000
LR_MIN_FRACTION = 0.003


def start_resolution_for(final: int, steps: Optional[int] = None) -> int:
    """The start grid of a coarse-to-fine ladder to `final` voxels: final / STAGE_RATIO^n
    for the n that lands nearest START_VOXELS (n >= MIN_UPSAMPLES), at least 16 and at most
    the final grid (a final grid under 16 trains at one size; it used to start at 16 and shrink).
    A run of a fixed number of `steps` takes at most max(MIN_UPSAMPLES, steps / 2 /
    MIN_STAGE_STEPS) stages: each waits for MIN_STAGE_STEPS steps, so more would leave the
    final grid less than half the run (bench hard's 400 steps: three stages, as before the
    longer ladder, not five that never reached a 256 grid)."""
    stages = max(MIN_UPSAMPLES, round(math.log(final / START_VOXELS) / math.log(STAGE_RATIO)))
    if steps is not None:
        stages = min(stages, max(MIN_UPSAMPLES, steps // (2 * MIN_STAGE_STEPS)))
    return min(final, max(16, round(final / 4 ** (stages / 3))))  # = STAGE_RATIO ** stages, exact at 3


def upsample_count(start: int, final: int) -> int:
    """Coarse-to-fine stages after the start grid: geometric steps of about STAGE_RATIO,
    at least MIN_UPSAMPLES (a start equal to the final grid takes them too, at one size)."""
    return max(MIN_UPSAMPLES, round(math.log(max(final / start, 1.0)) / math.log(STAGE_RATIO)))


# The parameter group (nerf.models: CompactNeRF.parameter_groups) whose rate may anneal
# apart from the rest (`Schedule.lr_scales`); every other group takes the plain rate.
COLOUR_GROUP = "colour"


@dataclass(frozen=True)
class RateScales:
    """Learning rates as fractions of each group's base: `plain` for every group, `colour`
    for the COLOUR_GROUP. scales[name] is a group's."""

    plain: float
    colour: float

    def __getitem__(self, group: str) -> float:
        return self.colour if group == COLOUR_GROUP else self.plain


@dataclass(frozen=True)
class TrialTiming:
    """A growth on trial's clock (`Schedule.steps_on_trial`): the stage's steps and seconds
    when the current window began (None during the warm-up) and the rates (steps a second)
    of the windows timed so far."""

    window_steps: Optional[int] = None
    window_seconds: float = 0.0
    rates: tuple[float, ...] = ()


@dataclass(frozen=True)
class Schedule:
    """One run's schedule, from its resolved TrainConfig (`for_run`). Every method reads the
    loop's counters (`state`: nerf.checkpoint.LoopState) and changes nothing.

    steps, budget_seconds: the run's budget (exactly one is set); start_resolution,
    final_resolution: the coarse-to-fine ladder's ends, refined_resolution the grid one
    stage past it (nerf.config.refined_resolution); grid: the model is a voxel grid
    (visibility and the colour head are its); budget_decides: a time budget's compact run
    in BUDGET_DECIDES_IN, whose last growth is on trial; edges: the `edges` pixel filter
    (its edge points refine at half the budget); refine_grid: TrainConfig.refine_grid;
    colour_head: TrainConfig.colour_head; surface_opacity: TrainConfig.surface_opacity (on
    from the half-budget refinement)."""

    steps: Optional[int]
    budget_seconds: Optional[float]
    start_resolution: int
    final_resolution: int
    refined_resolution: int
    grid: bool
    budget_decides: bool
    edges: bool
    refine_grid: bool
    colour_head: bool
    surface_opacity: bool = False

    @classmethod
    def for_run(cls, config, *, grid: bool, refined_resolution: int) -> "Schedule":
        """The schedule of a resolved TrainConfig `config` (its start and final resolution,
        pixel filter and parametrisation set); grid: whether its model has a voxel grid."""
        return cls(steps=config.steps, budget_seconds=config.budget_seconds,
                   start_resolution=config.start_resolution, final_resolution=config.final_resolution,
                   refined_resolution=refined_resolution, grid=grid,
                   budget_decides=(config.budget_seconds is not None and config.model == "compact"
                                   and config.parametrisation in BUDGET_DECIDES_IN),
                   edges=config.pixel_filter == "edges", refine_grid=bool(config.refine_grid),
                   colour_head=bool(config.colour_head), surface_opacity=bool(config.surface_opacity))

    @property
    def refines_at_half(self) -> bool:
        """Whether the run makes the half-budget refinement decision (`refinement_due`): an
        `edges` run (its edge points) or a --refine-grid run (its grid)."""
        return self.edges or self.refine_grid

    @property
    def stages(self) -> int:
        """Coarse-to-fine growths from the start grid to the final one (`upsample_count`)."""
        return upsample_count(self.start_resolution, self.final_resolution)

    def fraction_done(self, state) -> float:
        """The share of the budget gone: steps for a --steps run, training seconds otherwise."""
        return state.step / self.steps if self.steps else state.seconds / self.budget_seconds

    # --- coarse to fine ---------------------------------------------------------------

    def resolution_at(self, stage: int) -> int:
        """Coarse to fine: geometric steps from start (stage 0) to final resolution; the stage
        after it is the refined grid."""
        ratio = self.final_resolution / self.start_resolution
        stages = self.stages
        if stage > stages:
            return self.refined_resolution
        return int(round(self.start_resolution * ratio ** (stage / stages)))

    def upsample_at(self, stage: int) -> float:
        """Fraction of the budget where the grid grows from `stage` to the next: evenly spaced
        up to LAST_UPSAMPLE_AT (0.1, 0.2, 0.3 for three stages), so the final grid always
        trains for the last 70%."""
        return LAST_UPSAMPLE_AT * (stage + 1) / self.stages

    def growth_due(self, state, fraction: float) -> bool:
        """Whether the grid grows to the next stage before this step: a stage is left, its
        fraction of the budget is gone and the current grid has trained MIN_STAGE_STEPS steps."""
        return state.stage < state.last_stage and fraction >= self.upsample_at(state.stage) \
            and state.stage_steps >= MIN_STAGE_STEPS

    def growth_on_trial(self, state) -> bool:
        """Whether the growth from `state.stage` is the budget's to decide (a trial, then keep
        or undo): only for a time budget's compact model, in BUDGET_DECIDES_IN, for the last
        BUDGET_DECIDES_LAST_GROWTHS growths. A --steps run's schedule is fixed by its step
        count, so it stays reproducible."""
        return self.budget_decides and state.stage >= self.stages - BUDGET_DECIDES_LAST_GROWTHS

    def steps_on_trial(self, state, timing: "TrialTiming") -> tuple["TrialTiming", Optional[float]]:
        """(timing, projected) for the finer grid on trial, from the timing so far (a fresh
        `TrialTiming()` at the growth). The first window starts once GROWTH_TRIAL_WARMUP
        steps are done; each window is GROWTH_TRIAL_STEPS / GROWTH_TRIAL_WINDOWS steps.
        projected: the steps the finer grid would get in all, those done plus the fastest
        window's rate times the budget's seconds left; None until every window is timed."""
        if timing.window_steps is None:
            if state.stage_steps < GROWTH_TRIAL_WARMUP:
                return timing, None
            return TrialTiming(state.stage_steps, state.stage_seconds), None
        steps = state.stage_steps - timing.window_steps
        if steps < max(1, GROWTH_TRIAL_STEPS // GROWTH_TRIAL_WINDOWS):
            return timing, None
        seconds = state.stage_seconds - timing.window_seconds
        rate = steps / seconds if seconds > 0 else math.inf
        timing = TrialTiming(state.stage_steps, state.stage_seconds, timing.rates + (rate,))
        if len(timing.rates) < GROWTH_TRIAL_WINDOWS:
            return timing, None
        return timing, state.stage_steps + max(timing.rates) * max(self.budget_seconds - state.seconds, 0.0)

    @staticmethod
    def keeps_growth(projected: float) -> bool:
        """Whether a growth on trial stands: its grid would get MIN_STEPS_AT_FINER steps."""
        return projected >= MIN_STEPS_AT_FINER

    # --- the learning rate ------------------------------------------------------------

    def lr_scale(self, state, fraction: float) -> float:
        """The learning rate before this step, as a fraction of its base: LR_FINAL_FRACTION
        to the power of the budget's fraction done plus, for a grid model, the decades past
        `decay_start`, (step - start) / LR_DECADE_STEPS; that extra decay stops at
        LR_MIN_FRACTION. The decades count steps, so a --steps run and a time budget that
        take as many steps and decide their refinement at the same step end at the same
        rate. The vanilla NeRF keeps its recipe's decay (the jitter above is a voxel
        grid's, measured on it). The colour tables may anneal instead (`lr_scales`)."""
        plain = LR_FINAL_FRACTION ** fraction
        start = self.decay_start(state)
        if start is None or state.step <= start:
            return plain
        extra = LR_FINAL_FRACTION ** ((state.step - start) / LR_DECADE_STEPS)
        return min(plain, max(plain * extra, LR_MIN_FRACTION))

    def lr_scales(self, state, fraction: float) -> "RateScales":
        """Each parameter group's rate as a fraction of its base, by the group's name
        (`RateScales`): `lr_scale` for all, except that once surface
        opacity has turned on (`LoopState.anneal_from`, the share of the budget done then)
        the colour tables anneal, geometrically from the plain rate at that share to
        LR_MIN_FRACTION at the budget's end (never above the density's rate). The density
        keeps `lr_scale`: its outlines move after the switch, which takes the rate. Primitives
        128 px, idle pairs: the colour alone annealed, 46.54 / 46.56 dB at 600 / 1200 s
        against 46.20 / 46.49 (interior 45.03 at both, against 43.08 / 44.69; outline alpha
        RMS 0.035 at both); every table annealed, 45.76 / 46.36 (the 600-s outline's RMS
        0.0344 -> 0.0417) (docs/results.md, "Past the switch")."""
        scale = self.lr_scale(state, fraction)
        colour = scale
        if state.anneal_from:
            share = min(max((fraction - state.anneal_from) / (1.0 - state.anneal_from), 0.0), 1.0)
            at_switch = LR_FINAL_FRACTION ** state.anneal_from
            colour = min(scale, at_switch * (LR_MIN_FRACTION / at_switch) ** share)
        return RateScales(scale, colour)

    def decay_start(self, state) -> Optional[int]:
        """The step the extra decay counts from: LR_DECADE_STEPS, or for a run that refines
        at half its budget (`refinement_due`: edges, refine_grid) the step it decided at
        when that is later; None while that decision is still to come, and for a model
        without a grid (no extra decay)."""
        if not self.grid:
            return None
        if self.refines_at_half:
            return max(LR_DECADE_STEPS, state.edge_points_step) if state.edge_points_step else None
        return LR_DECADE_STEPS

    # --- what the grid's stages bring -------------------------------------------------

    def visibility_due(self, state, fraction: float) -> bool:
        """Whether hidden cells are measured (and skipped) before this step: at each of
        VISIBILITY_AT, a grid model only."""
        return self.grid and state.visibility_done < len(VISIBILITY_AT) \
            and fraction >= VISIBILITY_AT[state.visibility_done]

    @staticmethod
    def occupancy_due(state) -> bool:
        """Whether the occupancy grid is updated before this step: every OCCUPANCY_EVERY steps,
        once the grid has grown (all cells live while coarse), unless the budget keeps the
        start grid to the end."""
        return state.step % OCCUPANCY_EVERY == 0 and (state.stage >= 1 or state.last_stage == 0)

    def colour_head_due(self, state) -> bool:
        """Whether the residual colour head is decided now (LoopState.colour_head 0: not yet):
        once the final grid has trained MIN_STAGE_STEPS steps (it has settled)."""
        return state.colour_head == 0 and self.grid and state.stage == state.last_stage \
            and state.stage_steps >= MIN_STAGE_STEPS

    # --- half the budget --------------------------------------------------------------

    def refinement_due(self, state, fraction: float, trial_pending: bool) -> Optional[bool]:
        """Whether a converged run refines from now on: an `edges` run's edge pixels train
        through FINE_EDGE_POINTS_PER_AXIS^2 points instead of 2 x 2, and a --refine-grid run
        grows its grid one stage past the final one (`grows_past_final`). Decided once, at the
        first step at or past FINE_EDGE_POINTS_AT of the budget (after any growth on trial is
        judged: trial_pending), yes when the final grid has trained FINE_EDGE_POINTS_MIN_STEPS
        steps by then. A run that reaches that bar only later has too little budget left for
        the slower steps to repay (primitives 120 s reached it with 13% of the budget left).
        Returns None when there is nothing to decide (neither applies, decided already, too
        early, a trial pending)."""
        if not self.refines_at_half or state.edge_points_step or trial_pending \
                or fraction < FINE_EDGE_POINTS_AT:
            return None
        return state.stage == state.last_stage and state.stage_steps >= FINE_EDGE_POINTS_MIN_STEPS

    def finer_points_due(self, state, fraction: float) -> Optional[bool]:
        """Whether an `edges` run's edge pixels train through FINER_EDGE_POINTS_PER_AXIS^2
        points from now on: decided once (LoopState.finer_points_step), at the first step at
        or past FINER_EDGE_POINTS_AT of the budget, yes when they have trained
        FINE_EDGE_POINTS_MIN_STEPS steps through 3 x 3 points by then (the half-budget
        refinement's rule, one rung up: a run that reaches it only later has too little budget
        left to repay the slower steps). None when there is nothing to decide (not an edges
        run, no 3 x 3 points, decided already, too early)."""
        if not self.edges or state.edge_points != FINE_EDGE_POINTS_PER_AXIS or state.finer_points_step \
                or fraction < FINER_EDGE_POINTS_AT:
            return None
        return state.step - state.edge_points_step >= FINE_EDGE_POINTS_MIN_STEPS

    def grows_past_final(self, state) -> bool:
        """After refinement_due said yes: whether the grid grows one stage past the final one
        (the growth then comes as any other, on trial for a time budget). A --refine-grid run
        at its final stage only (one whose budget undid that growth is not, and gets no
        second trial), and only when the refined grid is finer (not at the resolution cap).
        A yes means the final grid has trained (FINE_EDGE_POINTS_MIN_STEPS steps), so the
        grid is the final stage's."""
        return self.refine_grid and state.stage == self.stages \
            and self.refined_resolution > self.resolution_at(state.stage)

    # --- what config.json says was decided --------------------------------------------

    def refine_grid_reason(self, state, resolution: int) -> str:
        """The account of whether a --refine-grid run grew past its final grid (`resolution`:
        the grid it ended with)."""
        when = f"at {100 * FINE_EDGE_POINTS_AT:.0f}% of the budget"
        final, finer = self.final_resolution, self.refined_resolution
        if resolution > final:
            return (f"{final} -> {resolution} voxels from step {state.edge_points_step}: {when} the "
                    f"final grid had trained {FINE_EDGE_POINTS_MIN_STEPS} steps or more")
        kept = f"kept {resolution} voxels"
        if not state.edge_points_step:
            return f"{kept}: the run ended before {100 * FINE_EDGE_POINTS_AT:.0f}% of its budget"
        if state.last_stage < self.stages:
            return f"{kept}: the budget could not train the footprint's {final} voxels, nor {finer}"
        not_converged = (f"{when} (step {state.edge_points_step}) the final grid had trained fewer than "
                         f"{FINE_EDGE_POINTS_MIN_STEPS} steps")
        undone = f"the budget left could not give {finer} voxels {MIN_STEPS_AT_FINER} steps (its growth was undone)"
        if self.edges:  # the same decision set the edge points: they say which it was
            return f"{kept}: " + (undone if state.edge_points != EDGE_POINTS_PER_AXIS else not_converged)
        return f"{kept}: {not_converged}, or {undone}"

    @staticmethod
    def edge_points_reason(state) -> str:
        """The account of the points an `edges` run trained its edge pixels through."""
        when = f"at {100 * FINE_EDGE_POINTS_AT:.0f}% of the budget"
        if state.edge_points != EDGE_POINTS_PER_AXIS:
            fine = FINE_EDGE_POINTS_PER_AXIS
            finer = f"{100 * FINER_EDGE_POINTS_AT:.0f}% of the budget"
            if state.edge_points == FINER_EDGE_POINTS_PER_AXIS:
                rung = (f", then {state.edge_points} x {state.edge_points} from step {state.finer_points_step}: at "
                        f"{finer} they had trained {FINE_EDGE_POINTS_MIN_STEPS} steps or more through {fine} x {fine}")
            elif state.finer_points_step:
                rung = (f"; kept at {finer} (step {state.finer_points_step}): fewer than "
                        f"{FINE_EDGE_POINTS_MIN_STEPS} steps through them by then")
            else:
                rung = f"; the run ended before {finer}"
            return (f"{EDGE_POINTS_PER_AXIS} x {EDGE_POINTS_PER_AXIS} to step {state.edge_points_step}, then "
                    f"{fine} x {fine}: {when} the final grid had trained "
                    f"{FINE_EDGE_POINTS_MIN_STEPS} steps or more" + rung)
        if state.edge_points_step:
            return (f"{state.edge_points} x {state.edge_points} throughout: {when} (step {state.edge_points_step}) "
                    f"the final grid had trained fewer than {FINE_EDGE_POINTS_MIN_STEPS} steps")
        return (f"{state.edge_points} x {state.edge_points} throughout: the run ended before "
                f"{100 * FINE_EDGE_POINTS_AT:.0f}% of its budget")
