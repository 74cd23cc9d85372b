"""Automatic choices decided by a short trial where the rule that makes them is unsure (issue 52).

A rule picks a setting from what the capture is (nerf.config.resolve). Its thresholds were
measured on a few captures; where a capture's statistics sit between the points the rule
was checked at, or the capture is of a kind it was never checked on, the rule says so (for
the parametrisation: nerf.parametrisation.parametrisation_doubt, beside its thresholds) and
the choice is made by measurement instead:

- each candidate (the rule's own pick first) is resolved as if forced on the command line
  and trains the first TRIAL_SHARE of the run (of its steps, or of its time budget) from
  the run's seed: exactly the start of the run it would be if forced;
- each is scored on the val views through the render path (`val_psnr`: whole frames as
  `nerfgauge render` writes them, not the strided centre rays of the log's val PSNR);
- the best continues its own run from where its trial stopped, so its trial steps are not
  lost and a `--steps` run ends with the model the forced run of that candidate trains,
  tensor for tensor; each other candidate's trial is the cost (TRIAL_SHARE of the run
  each). A candidate within TRIAL_TIE_DB of the rule's pick does not replace it.
- a time budget is a promise about training seconds, so the trial is paid from it: with n
  candidates each runs as if forced with budget / (1 + (n - 1) TRIAL_SHARE)
  (`candidate_config`), and the trial and the winner's run together train the budget. A
  --steps run keeps its steps (its model then equals the forced run's) and the others'
  trial steps are extra.

config.json's auto_reasons says a trial decided, the share, each candidate's val PSNR, and
"trials" holds the same as numbers. The run's recipe names the candidates and the share
(`trial_recipe`), so a resumed run is checked against the same trial and continues the
winner its checkpoint holds; a run killed during the trial has no checkpoint yet and starts
over (the same trial again, for a --steps run). A setting given on the command line never
goes to trial.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from nerfgauge.nerf.config import CHANGE_STEP, TrainConfig
from nerfgauge.nerf.frames import EDGES_ONLY, PIXEL_SAMPLES, box_frame, compiled_render_threads
from nerfgauge.nerf.parametrisation import parametrisation_doubt
from nerfgauge.nerf.rendering import composite

# Each candidate trains this share of the run's steps or budget before it is scored. Set
# before measuring (not tuned): at bench hard's 400 steps a quarter is 100 steps, the start
# grid's first stage (nerf.schedule.MIN_STAGE_STEPS), where a space that gives the content
# coarse cells should already show; two candidates cost the run 1.25x its steps.
TRIAL_SHARE = 0.25
# A candidate must beat the rule's own pick by more than this on the val views to replace
# it (val PSNR of a few views moves by about this much between neighbouring steps).
TRIAL_TIE_DB = 0.1


@dataclass(frozen=True)
class Trial:
    """A choice put on trial. field: the TrainConfig field ("parametrisation"); candidates:
    its values, the rule's own pick first (it wins ties); why: why the rule is unsure;
    share: of the run each candidate trains before it is scored."""

    field: str
    candidates: tuple
    why: str
    share: float = TRIAL_SHARE


def parametrisation_trial(config: TrainConfig, aabb: np.ndarray, c2w: np.ndarray,
                          opaque: Optional[float]) -> Optional[Trial]:
    """The parametrisation's trial for this capture, or None: when it is set on the command
    line, for a model without the compact grid (the space is the grid's), or where the rule
    is sure (parametrisation_doubt)."""
    if config.parametrisation is not None or config.model != "compact":
        return None
    doubt = parametrisation_doubt(aabb, c2w, opaque)
    if doubt is None:
        return None
    candidates, why = doubt
    return Trial("parametrisation", tuple(candidates), why)


def candidate_config(config: TrainConfig, trial: Trial, value) -> TrainConfig:
    """The requested config with the trial's field set to `value`, as if forced (nerf.config.resolve
    then resolves everything that follows from it), and for a time budget that budget's share
    of one candidate (`candidate_budget`)."""
    changes = {trial.field: value}
    if config.steps is None:
        changes["budget_seconds"] = candidate_budget(config.budget_seconds, trial)
    return dataclasses.replace(config, **changes)


def candidate_budget(budget_seconds: float, trial: Trial) -> float:
    """Training seconds of each candidate's own run, so the trial (every other candidate's
    share of such a run) and the winner's run add up to `budget_seconds`."""
    return budget_seconds / (1 + (len(trial.candidates) - 1) * trial.share)


def trial_recipe(trial: Trial, recipes: list) -> dict:
    """One recipe for a run whose choice is on trial, from each candidate's own recipe
    (nerf.train.run_recipe, in the trial's order): the settings every candidate shares,
    and under "trial" the share and, for each candidate, the settings that are its own."""
    common = {key: value for key, value in recipes[0].items()
              if all(key in other and other[key] == value for other in recipes[1:])}
    own = {str(recipe[trial.field]): {key: value for key, value in recipe.items() if key not in common}
           for recipe in recipes}
    return common | {"trial": {"field": trial.field, "share": trial.share, "candidates": own}}


def trial_steps(config: TrainConfig, share: float) -> str:
    """The trial's length in words: steps of a --steps run, else seconds of its budget
    (`config`: a candidate's, whose time budget is its share of the run's)."""
    if config.steps is not None:
        return f"{math.ceil(share * config.steps)} of {config.steps} steps"
    return f"{share * config.budget_seconds:.3g} of {config.budget_seconds:.3g} training seconds"


def trial_cost(trial: Trial, config: TrainConfig) -> str:
    """Who paid for the other candidates' trials, in words (`config`: the winner's)."""
    if config.steps is not None:
        return "the others' trial steps were extra"
    total = config.budget_seconds * (1 + (len(trial.candidates) - 1) * trial.share)
    return (f"the trial was paid from the {total:.3g}-s budget: each candidate's run had "
            f"{config.budget_seconds:.3g} s of it")


def pick(trial: Trial, scores: dict) -> str:
    """The candidate that continues: the best val PSNR, unless it beats the rule's own pick
    (the first candidate) by TRIAL_TIE_DB or less."""
    first = trial.candidates[0]
    best = max(trial.candidates, key=lambda value: scores[value])  # the first of equals
    return best if scores[best] > scores[first] + TRIAL_TIE_DB else first


def trial_reason(trial: Trial, config: TrainConfig, scores: dict, chosen, views: int, split: str) -> str:
    """auto_reasons' line for a choice a trial made."""
    scored = ", ".join(f"{value} {scores[value]:.2f} dB" if math.isfinite(scores[value]) else f"{value} diverged"
                       for value in trial.candidates)
    return (f"{chosen} by trial ({trial.why}): each of {', '.join(map(str, trial.candidates))} trained "
            f"{trial_steps(config, trial.share)} ({100 * trial.share:g}% of the run) from seed {config.seed}, then "
            f"scored on {views} {split} views: {scored}; the rule's own pick was {trial.candidates[0]} (it keeps ties "
            f"within {TRIAL_TIE_DB:g} dB); {chosen} continues its own run, {trial_cost(trial, config)}")


def trial_record(trial: Trial, config: TrainConfig, scores: dict, chosen) -> dict:
    """config.json's "trials" entry for one trial: the same as its reason, as numbers."""
    return {"field": trial.field, "why": trial.why, "share": trial.share, "chosen": chosen,
            "rule_pick": trial.candidates[0], "val_psnr": {str(value): scores[value] if math.isfinite(scores[value]) else None  # None: diverged
                         for value in trial.candidates},
            "steps": math.ceil(trial.share * config.steps) if config.steps is not None else None,
            "seconds": trial.share * config.budget_seconds if config.steps is None else None}


class RayCount:
    """`model` whose render counts the rays it is asked for; every other attribute is the
    model's, so a render path that asks whether it renders compiled still finds out."""

    def __init__(self, model):
        self.model, self.rays = model, 0

    def render(self, origins, directions, *args, **kwargs):
        self.rays += int(directions.shape[0])
        return self.model.render(origins, directions, *args, **kwargs)

    def __getattr__(self, name):
        return getattr(self.model, name)


def val_psnr(model, cameras, val_rays, device, filters: dict, rays: dict | None = None) -> dict:
    """PSNR (composited on white) of whole val frames through the render path, by filter:
    {name: (rays per axis on a pixel, only on the centre render's edge pixels[, the change
    step: nerf.frames.box_frame])} -> {name: dB}, the PSNR of the mean squared error over the
    views. cameras, val_rays: the val views (nerf.train.prepare_run). rays: a dict to fill
    with each filter's rays per pixel (what its render costs), when given."""
    pixels = cameras.intrinsics.width * cameras.intrinsics.height
    errors = dict.fromkeys(filters, 0.0)
    counted = dict.fromkeys(filters, 0)
    model.eval()
    counting = RayCount(model)
    # a compiled render on the threads torch trains with (and torch's own on one meanwhile)
    with torch.no_grad(), compiled_render_threads(model, device, torch.get_num_threads()):
        for index in range(val_rays.n_views):
            rgba = val_rays.rgba[index * pixels:(index + 1) * pixels].to(device)
            target = rgba[:, :3] * rgba[:, 3:] + (1 - rgba[:, 3:])
            for name, (per_axis, edges_only, *step) in filters.items():
                before = counting.rays
                rgb, opacity, _ = box_frame(counting, cameras, index, per_axis, None, 1, device, edges_only=edges_only,
                                            change_step=step[0] if step else CHANGE_STEP)
                counted[name] += counting.rays - before
                white = composite(rgb, opacity, torch.ones(3, device=device)).clamp(0, 1)
                errors[name] += float(((white - target) ** 2).mean())
    model.train()  # both callers go on with a model in training mode (a trial's winner trains on)
    if rays is not None:
        rays.update({name: count / max(pixels * val_rays.n_views, 1) for name, count in counted.items()})
    return {name: -10 * math.log10(max(error / max(val_rays.n_views, 1), 1e-10)) for name, error in errors.items()}


def render_path(config: TrainConfig) -> dict:
    """`val_psnr`'s filter for how `nerfgauge render` renders a run of `config` before an
    `edges` run's render filter is chosen (nerf.frames.PIXEL_SAMPLES, EDGES_ONLY)."""
    return {"render": (PIXEL_SAMPLES[config.pixel_filter], config.pixel_filter in EDGES_ONLY)}
