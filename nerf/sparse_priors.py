"""Sparse captures: how many train views see each part of the scene, and the priors that
carve the space few of them constrain.

A grid fitted to few views explains each view with density anywhere along its rays, so
between the views the geometry stays wrong (bench hard's inside, 40 views from the middle
of a room: 30.1 dB on its train views, 20.5 on held-out ones; BENCHMARKS.md). The priors
below act on rays no train view cast, from viewpoints near the train cameras (InfoNeRF,
Kim et al. 2022; RegNeRF, Niemeyer et al. 2022): they ask each such ray to be either empty
or opaque (the binary entropy of its opacity) and to end in one compact interval (the
distortion loss), plus total variation on the grid's density and colour features, so
floaters that only the train views' own rays pass over cost something.

Whether a capture is sparse is read from its cameras alone (a real capture has no depth):
`views_per_point` is the median number of train cameras whose image holds a point drawn
uniformly in the scene's box, over the points at least one of them holds. Occlusion is not
known, so this counts what a view could see, an upper bound on what it saw.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from nerfgauge.core.camera import project
from nerfgauge.nerf.parametrisation import CLOSED_SHARE, cameras_in_box

# The capture is sparse when a point of the box is in the images of fewer train views than
# this (the median over points some view holds). Object-centred captures hold every point
# in all of their views. From inside a room (BENCHMARKS.md, "Sparse captures") the priors
# gained at 40 views (4 images a point) and 80 (7: +1.5 dB at 400 steps, +0.6 at 1200) and
# lost at 120 (11: +0.1 dB at 400 steps, -1.6 at 1200): the bar lies between 7 and 11.
SPARSE_VIEWS_PER_POINT = 9
VIEWS_PER_POINT_SAMPLES = 4096  # points drawn in the box (seeded: the choice is reproducible)
PRIOR_RAYS = 1024  # rays from unseen viewpoints a step
PRIOR_ENTROPY = 0.01  # weight of the opacity's binary entropy on them
PRIOR_DISTORTION = 0.01  # weight of the distortion loss on them
PRIOR_TV = 1e-3  # weight of the grid density's total variation ...
PRIOR_COLOUR_TV = 3e-3  # ... and of its colour features
# Voxel learning rate of a run with the priors (TrainConfig.lr's default, 0.1, otherwise;
# `nerf.config.resolve`): the priors keep the field from the floaters a larger step would
# leave, and a sparse capture's few rays a voxel need larger steps to be fitted within the
# run. bench hard's inside (40 views, 400 steps): 23.28 dB at 0.1, 24.05 at 0.2, 24.11 at 0.3;
# the same scene from another seed, in no bench: 19.72 at 0.1, 20.98 at 0.3 (BENCHMARKS.md,
# "A finer grid in the second half": "Inside at 40 views: the priors' learning rate").
PRIOR_LEARNING_RATE = 0.3
OPACITY_EPS = 1e-4  # keeps the entropy's logarithms finite at opacity 0 and 1


def views_per_point(aabb: np.ndarray, c2w: np.ndarray, intrinsics, seed: int = 0) -> Optional[float]:
    """The median, over points drawn uniformly in `aabb` [2, 3] that at least one camera
    holds in its image, of how many of the cameras c2w [n, 4, 4] (OpenGL axes) hold them.
    0.0 when no camera holds any point; None when the box's extent is not finite (a
    scene.json out of range: the run's own checks name it)."""
    aabb = np.asarray(aabb, np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        extent = aabb[1] - aabb[0]
    if not np.all(np.isfinite(extent)):
        return None
    points = aabb[0] + np.random.default_rng(seed).random((VIEWS_PER_POINT_SAMPLES, 3)) * extent
    counts = np.zeros(len(points), dtype=np.int64)
    for camera in c2w:
        u, v, _ = project(points, camera, intrinsics)
        with np.errstate(invalid="ignore"):
            counts += (u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height)
    seen = counts[counts > 0]
    return float(np.median(seen)) if len(seen) else 0.0


def cameras_inside(aabb: np.ndarray, c2w: np.ndarray) -> float:
    """The share of the cameras c2w [n, 4, 4] whose centre lies in `aabb` [2, 3] (a
    capture from inside the scene: a room from its middle). 0.0 without cameras."""
    inside = cameras_in_box(aabb, c2w)
    return float(inside.mean()) if len(inside) else 0.0


def sparse_priors_for(setting: Optional[bool], views: Optional[float], kind: Optional[str] = None,
                      inside: Optional[float] = None, opaque: Optional[float] = None) -> tuple[bool, str]:
    """Whether a run trains with the sparse-capture priors, and why: as set; else on for an
    open capture from inside the scene (`inside`, the share of train cameras in the box, at
    least 1/2; `opaque`, the share of training pixels with alpha 1, below CLOSED_SHARE) in
    bounded space (`kind`) when a point of the box is in fewer than SPARSE_VIEWS_PER_POINT
    train images (`views`, the median of `views_per_point`); off when any of these is
    unknown (`opaque` may be: a capture without alpha counts as open).

    Measured (BENCHMARKS.md, "Sparse captures"), 400 steps: inside at 40 views (4 images a
    point) 23.28 dB against 20.58 without, at 80 (7) 22.53 against 21.07 (1200 steps: 22.17
    against 21.59), at 120 (11) 27.59 against 27.53 but 29.29 against 30.92 at 1200 steps,
    hence the bar below 11. Elsewhere they lost: room (a closed room from inside, 40 views,
    3 a point, a scene outside bench hard) 17.10 against 19.56; in contracted space 3.4 dB
    on far-reaching (40 views, 4 a point); around an object, primitives' sparse lists of 6
    and 9 views (600 steps) 1.8 and 3.0 dB. Where every ray ends on content (a closed room,
    an unbounded world) the entropy and the total variation cannot tell it from haze, and
    around an object the total variation smooths what the few views do resolve."""
    if setting is not None:
        return setting, "set on the command line"
    if views is None or kind is None or inside is None:
        return False, "off: the train views' coverage is not known"
    coverage = f"a point of the box is in {views:g} train images (median)"
    if views >= SPARSE_VIEWS_PER_POINT:
        return False, f"{coverage}, >= {SPARSE_VIEWS_PER_POINT}: off"
    lost = f"{coverage}, < {SPARSE_VIEWS_PER_POINT}, but"
    if kind != "bounded":
        return False, f"{lost} in {kind} space the priors lost wherever measured: off"
    if inside < 0.5:
        return False, (f"{lost} the cameras look at the scene from outside ({100 * inside:.0f}% stand in the box), "
                       "where the priors lost wherever measured: off")
    if opaque is not None and opaque >= CLOSED_SHARE:
        return False, (f"{lost} the capture is closed ({100 * opaque:.2f}% of training pixels opaque), where the "
                       "priors lost wherever measured: off")
    return True, (f"{coverage}, < {SPARSE_VIEWS_PER_POINT}, from inside an open scene ({100 * inside:.0f}% of the "
                  "cameras stand in the box): a sparse capture, priors on rays from unseen viewpoints")


def origin_spread(origins: torch.Tensor) -> float:
    """The RMS distance of the train rays' origins [N, 3] from their mean, per axis: the
    camera centres' spread, each weighted by its pixels (the unseen viewpoints' offsets)."""
    centred = origins.double() - origins.double().mean(dim=0)
    return float(torch.sqrt((centred ** 2).sum(dim=1).mean() / 3))


def unseen_rays(origins: torch.Tensor, directions: torch.Tensor, spread: float, n: int,
                generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """`n` rays from viewpoints no train camera stands at: a random train ray's direction
    from its camera centre moved by a normal draw of standard deviation `spread` per axis.
    origins, directions: the train rays [N, 3]. Returns (origins, directions) [n, 3]."""
    index = torch.randint(origins.shape[0], (n,), generator=generator)
    offsets = torch.randn((n, 3), generator=generator) * spread
    return origins[index] + offsets, directions[index]


def opacity_entropy(opacity: torch.Tensor) -> torch.Tensor:
    """Binary entropy (nats) of each ray's opacity [n] -> [n]: 0 for an empty or an opaque
    ray, log 2 at opacity 1/2."""
    o = opacity.clamp(OPACITY_EPS, 1 - OPACITY_EPS)
    return -(o * torch.log(o) + (1 - o) * torch.log(1 - o))


def prior_loss(model, origins: torch.Tensor, directions: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """The priors of a compact model (nerf.models.CompactNeRF) on rays [n, 3] from unseen
    viewpoints: PRIOR_ENTROPY x the mean binary entropy of their opacity + PRIOR_DISTORTION
    x their mean distortion, and the grid's total variation, PRIOR_TV x its density's +
    PRIOR_COLOUR_TV x its colour features'. A scalar."""
    out = model.render(origins, directions, generator=generator, training=True)
    loss = (PRIOR_ENTROPY * opacity_entropy(out.opacity).mean() + PRIOR_TV * model.field.total_variation("density")
            + PRIOR_COLOUR_TV * model.field.total_variation("features"))
    if out.distortion is not None:
        loss = loss + PRIOR_DISTORTION * out.distortion.mean()
    return loss

