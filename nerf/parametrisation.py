"""Scene parametrisations: where the compact field's grid lives, and how rays are sampled.

- bounded: the grid spans the scene's AABB in world units (the original compact NeRF).
- contracted: mip-NeRF 360's contraction about a centre, after scaling so the inner
  region (radius R) is the unit ball: y = (x - centre) / R,
      c(y) = y if |y| <= 1 else (2 - 1/|y|) y / |y|,
  so all of space maps into the ball of radius 2 and the grid spans [-2, 2]^3. Rays are
  sampled uniformly in t inside the inner ball and uniformly in disparity beyond it.
- forward: a forward-facing capture's frustum in a reference camera frame (camera
  centroid, mean viewing direction f, right r, up u):
      p = (x - origin) @ [r, u, f] = (a, b, z),   g(p) = (a / z, b / z, k log z),
  angles across, log-depth along: a grid cell is a constant fraction of its depth, so
  relative depth error is the same at 0.2 and at 50 (NDC's inverse-depth spacing makes
  far cells z^2-coarse). Rays are sampled uniformly in k log z.

Density is stored per grid unit: the field divides by `world_per_unit(x)`, the world
length of one grid unit along the marching direction at x, so a grid value means the same
opacity per marching step everywhere, and sigma stays a world-space density (per world
unit, independent of direction). Depth is always a world distance along the ray.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from nerfgauge.core.errors import InputError

PARAMETRISATIONS = ("bounded", "contracted", "forward")
LOG_DEPTH_SCALE = 0.25  # k: a log-depth grid unit spans 1/k times the angle unit -> depth cells ~2x across cells
CONTRACTED_EXTENT = 2.0


# --------------------------------------------------------------------------------------
# pure maps


def contract(y: torch.Tensor) -> torch.Tensor:
    """mip-NeRF 360 contraction. y [..., 3] (inner region = unit ball) -> [..., 3], |c| < 2.
    Finite for every finite y; |y| -> inf maps to |c| -> 2."""
    scale = y.abs().amax(dim=-1, keepdim=True).clamp_min(1e-30)  # no overflow of |y|^2 for huge y
    unit = y / scale
    r = scale * unit.norm(dim=-1, keepdim=True)
    return torch.where(r <= 1, y, (2 - 1 / r) * unit / unit.norm(dim=-1, keepdim=True))


def uncontract(c: torch.Tensor) -> torch.Tensor:
    """Inverse of `contract` for |c| < 2. c [..., 3] -> y [..., 3] (|c| -> 2 gives |y| -> inf)."""
    s = c.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.where(s <= 1, c, c / (s * (2 - s)))


def contract_jacobian(y: torch.Tensor) -> torch.Tensor:
    """d contract / d y. y [n, 3] -> [n, 3, 3]. Outside the unit ball, with r = |y|,
    J = (2/r - 1/r^2) I + (2/r^3 - 2/r^2) y y^T / r."""
    r = y.norm(dim=-1).clamp_min(1e-12)[:, None, None]
    eye = torch.eye(3, dtype=y.dtype, device=y.device).expand(y.shape[0], 3, 3)
    outer = y[:, :, None] * y[:, None, :]
    outside = (2 / r - 1 / r ** 2) * eye + (2 / r ** 3 - 2 / r ** 2) * outer / r
    return torch.where(r <= 1, eye, outside)


def log_perspective(p: torch.Tensor, k: float = LOG_DEPTH_SCALE) -> torch.Tensor:
    """Camera-frame points p [..., 3] = (a, b, z), z > 0 -> (a/z, b/z, k log z) [..., 3]."""
    a, b, z = p.unbind(-1)
    return torch.stack([a / z, b / z, k * torch.log(z)], dim=-1)


def log_perspective_inverse(g: torch.Tensor, k: float = LOG_DEPTH_SCALE) -> torch.Tensor:
    """Inverse of `log_perspective`: g [..., 3] -> p [..., 3] with z = exp(g_z / k) > 0."""
    u, v, w = g.unbind(-1)
    z = torch.exp(w / k)
    return torch.stack([u * z, v * z, z], dim=-1)


def log_perspective_jacobian(p: torch.Tensor, k: float = LOG_DEPTH_SCALE) -> torch.Tensor:
    """d log_perspective / d p. p [n, 3] -> [n, 3, 3]."""
    a, b, z = p.unbind(-1)
    zero = torch.zeros_like(z)
    return torch.stack([torch.stack([1 / z, zero, -a / z ** 2], -1),
                        torch.stack([zero, 1 / z, -b / z ** 2], -1),
                        torch.stack([zero, zero, k / z], -1)], dim=-2)


# --------------------------------------------------------------------------------------
# spaces


@dataclass
class Space:
    """A parametrisation with its numbers. kind: one of PARAMETRISATIONS; box [2, 3]: the
    grid's extent in grid coordinates; centre [3], radius (contracted); origin [3], frame
    [3, 3] (rows r, u, f) (forward)."""

    kind: str
    box: list
    centre: list | None = None
    radius: float | None = None
    origin: list | None = None
    frame: list | None = None

    def to_json(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if v is not None}

    @staticmethod
    def from_json(data: dict) -> "Space":
        if not isinstance(data, dict) or data.get("kind") not in PARAMETRISATIONS:
            raise ValueError(f"unknown space {data!r}")
        return Space(**data)

    def _tensors(self, like: torch.Tensor):
        t = lambda v: torch.tensor(v, dtype=like.dtype, device=like.device)  # noqa: E731
        if self.kind == "contracted":
            return t(self.centre), float(self.radius)
        if self.kind == "forward":
            return t(self.origin), t(self.frame)
        return None, None

    def to_grid(self, x: torch.Tensor) -> torch.Tensor:
        """World points [n, 3] -> grid coordinates [n, 3] (differentiable)."""
        if self.kind == "bounded":
            return x
        a, b = self._tensors(x)
        if self.kind == "contracted":
            return contract((x - a) / b)
        return log_perspective(self._camera(x, a, b))

    @staticmethod
    def _camera(x, origin, frame):
        p = (x - origin) @ frame.t()
        return torch.cat([p[:, :2], p[:, 2:].clamp_min(1e-6)], dim=1)

    def world_per_unit(self, x: torch.Tensor) -> torch.Tensor:
        """World length of one grid unit along the marching direction at x [n, 3]. Returns [n]
        (1 for bounded). Differentiable."""
        if self.kind == "bounded":
            return torch.ones_like(x[:, 0])
        a, b = self._tensors(x)
        if self.kind == "contracted":
            r2 = (((x - a) / b) ** 2).sum(-1)
            return b * r2.clamp_min(1.0)
        return self._camera(x, a, b)[:, 2] / LOG_DEPTH_SCALE

    @torch.no_grad()
    def ray_edges(self, origins: torch.Tensor, directions: torch.Tensor, grid_step: float) -> torch.Tensor:
        """Sample interval edges t [n_rays, m + 1] (non-decreasing; zero-length intervals are
        padding) so one interval is about `grid_step` grid units long. Not differentiable."""
        if self.kind == "contracted":
            centre, radius = self._tensors(origins)
            o = (origins - centre) / radius  # unit-ball frame; t in units of radius
            b = (o * directions).sum(-1)
            disc = b * b - ((o * o).sum(-1) - 1)
            root = disc.clamp_min(0).sqrt()
            crosses = disc > 0
            t_exit = torch.where(crosses, -b + root, (-b).clamp_min(0)).clamp_min(0)
            # where the ray enters the ball: 0 from inside it; for a ray that misses it, its
            # closest approach (no inner part)
            t_enter = torch.where(crosses, (-b - root).clamp_min(0), t_exit)
            # before the ball (a camera outside it): disparity-uniform towards the ball, the
            # mirror of the shell beyond it, u = 1 / (1 + t_enter - t) from 1 / (1 + t_enter) to 1
            far_start = float(t_enter.max()) if len(o) else 0.0
            n_pre = max(0, math.ceil((1 - 1 / (1 + far_start)) / grid_step))
            u = (1 - torch.arange(n_pre, -1, -1, dtype=o.dtype, device=o.device) * grid_step).clamp_min(grid_step)
            pre_edges = (t_enter[:, None] - (1 / u[None, :] - 1)).clamp_min(0)  # ends at t_enter
            inner = max(1, math.ceil(float((t_exit - t_enter).max()) / grid_step)) if len(o) else 1
            k = torch.arange(inner + 1, dtype=o.dtype, device=o.device) * grid_step
            inner_edges = torch.minimum(t_enter[:, None] + k[None, :], t_exit[:, None])
            # disparity-uniform beyond: u = 1 / (1 + t - t_exit) from 1 to grid_step
            n_outer = max(1, math.ceil((1 - grid_step) / grid_step))
            u = 1 - torch.arange(1, n_outer + 1, dtype=o.dtype, device=o.device) * grid_step
            u = u.clamp_min(grid_step)
            outer_edges = t_exit[:, None] + (1 / u[None, :] - 1)
            return torch.cat([pre_edges, inner_edges, outer_edges], dim=1) * radius
        origin, frame = self._tensors(origins)
        oz = (origins - origin) @ frame[2]
        dz = directions @ frame[2]
        w0, w1 = self.box[0][2], self.box[1][2]
        n = max(1, math.ceil((w1 - w0) / grid_step))
        z = torch.exp(torch.linspace(w0, w1, n + 1, dtype=origins.dtype, device=origins.device) / LOG_DEPTH_SCALE)
        facing = dz > 1e-6
        t = (z[None, :] - oz[:, None]) / torch.where(facing, dz, torch.ones_like(dz))[:, None]
        t = torch.where(facing[:, None], t.clamp_min(0), torch.zeros_like(t))
        return t


def cameras_in_box(aabb: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Which cameras c2w [n, 4, 4] have their centre in `aabb` [2, 3] (faces included): [n] bool."""
    positions = np.asarray(c2w)[:, :3, 3]
    return ((positions >= aabb[0]) & (positions <= aabb[1])).all(axis=1)


def choose_parametrisation(requested: str | None, aabb: np.ndarray, c2w: np.ndarray,
                           opaque: float | None = None) -> tuple[str, str]:
    """(kind, reason) from what the capture is, unless `requested` names one.

    opaque: the share of training pixels whose alpha is 1 (every ray ends on content), or
    None when unknown. The reason states the evidence, so a wrong pick can be traced in
    the run's config.json.

    Cameras inside the AABB:
    - the capture is closed (CLOSED_SHARE of the pixels opaque: no ray leaves the content)
      and the cameras look outwards (no common focus ahead of them) -> bounded: everything
      the cameras can see lies within the box around them (a room), so one grid holds it,
      however far the walls are from the cameras' cluster. Contraction would give the walls
      the coarse outer shell: a closed room from inside scored 5.3 dB lower contracted
      (issue 34; BENCHMARKS.md "Parametrisation by what the capture is").
    - else an AABB reaching more than NEAR_AABB_FACTOR camera radii beyond them (an open
      world: distant terrain, sky) -> contracted;
    - else bounded (near content: measured on `inside`, bounded led contracted by about
      2 dB of val PSNR at every step compared).
    Cameras outside it: all on one side looking within FORWARD_SPREAD degrees of one
    direction -> forward; else bounded. Where this rule is unsure, `parametrisation_doubt`
    says so and nerf.trials measures its pick against the alternative."""
    if requested is not None:
        if requested not in PARAMETRISATIONS:
            raise InputError(f"unknown parametrisation {requested!r}; choose one of {', '.join(PARAMETRISATIONS)}")
        return requested, "set on the command line"
    inside = cameras_in_box(aabb, c2w)
    if inside.any():
        reach, cams = box_reach(aabb, c2w)
        where = f"{int(inside.sum())} of {len(inside)} cameras stand inside the AABB"
        outwards, focus_ahead = looks_outwards(c2w)
        seen = "" if opaque is None else f"{100 * opaque:.2f}% of training pixels opaque"
        if opaque is not None and opaque >= CLOSED_SHARE and outwards:
            return "bounded", (f"{where} and look outwards, and the capture is closed ({seen}: no ray leaves the "
                               f"content): all of it within the box around them, {reach / cams:.1f}x their "
                               "reach (one grid)")
        why_open = ("" if opaque is None else f"; {seen}" + (", but the cameras look at a common point "
                    f"{focus_ahead:.3g} ahead" if opaque >= CLOSED_SHARE else ": the capture is open"))
        if reach > NEAR_AABB_FACTOR * cams:
            return "contracted", f"{where}, which reaches {reach / cams:.0f}x beyond them (far content){why_open}"
        return "bounded", (f"{where}, all of it within {NEAR_AABB_FACTOR:g}x their reach (near content: one "
                           f"grid){why_open}")
    spread, ahead, _ = forward_cone(aabb, c2w)
    if spread <= FORWARD_SPREAD and ahead > 0:
        return "forward", (f"forward-facing: viewing directions within {spread:.1f} degrees of their mean and the "
                           f"whole AABB ahead of every camera (nearest corner {ahead:.3g} ahead)")
    return "bounded", "cameras outside the AABB looking at it from several sides"


def box_reach(aabb: np.ndarray, c2w: np.ndarray) -> tuple[float, float]:
    """(how far the AABB reaches from the contraction centre, the cameras' radius about it:
    1.1 x the farthest camera), for cameras among the content."""
    centre, _ = contraction_frame(aabb, c2w)
    cams = 1.1 * float(np.linalg.norm(c2w[:, :3, 3] - centre, axis=1).max())
    return float(np.maximum(aabb[1] - centre, centre - aabb[0]).max()), cams


def forward_cone(aabb: np.ndarray, c2w: np.ndarray) -> tuple[float, float, float]:
    """(the largest angle in degrees between a camera's viewing direction and their mean,
    the nearest AABB corner's distance ahead of the cameras along that mean (negative: a
    corner behind one), the farthest corner's distance over the nearest's: the box's depth
    ratio, inf when a corner is not ahead)."""
    positions, forward = c2w[:, :3, 3], -c2w[:, :3, 2]
    mean = forward.mean(axis=0)
    mean = mean / max(np.linalg.norm(mean), 1e-12)
    spread = float(np.degrees(np.arccos(np.clip(forward @ mean, -1, 1))).max())
    corners = np.array([[aabb[i][0], aabb[j][1], aabb[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    depths = (corners[None] - positions[:, None]) @ mean  # [cameras, corners]
    ahead = float(depths.min())
    return spread, ahead, float(depths.max()) / ahead if ahead > 0 else math.inf


# When the rule above is unsure (issue 52): its thresholds were measured on a few captures,
# so where a capture's statistics lie between the points the rule was checked at, or the
# capture is of a kind it was never checked on, its pick is tried against the alternative
# instead of trusted (nerf.trials: both train the first share of the run from the same
# seed, scored on the val views; the better continues). Stated before the captures that
# check it were measured (scenes/checks.py, the issue 52 ones):
# - cameras inside the box: its reach in camera radii (NEAR_AABB_FACTOR decides). The pick
#   was measured right at about REACH_CHECKED's ends: inside, 4.7-5.1x as its views are
#   dealt (bench hard's 40 of 58: 5.08x; bounded 2 dB above contracted), and far-reaching,
#   28.4x (contracted; an orbit). Between them it is unsure.
# - cameras inside an open capture looking outwards at far content (contracted): never
#   checked. inside's content is near, far-reaching's cameras look at a common point and
#   room is closed; a courtyard seen from within is such a capture. Always a trial.
# - forward-facing: measured at box depth ratios of 8.7 (forward-near: forward 4.6 dB above
#   bounded) and 450 (depth-range); below FORWARD_DEPTH_RATIO_CHECKED (a close-up, with
#   little depth for log depth to spread its cells over) unsure.
# - the forward cone: every forward capture measured had parallel cameras (0 degrees);
#   within FORWARD_SPREAD_MARGIN degrees of FORWARD_SPREAD either way unsure.
REACH_CHECKED = (5.5, 25.0)
FORWARD_SPREAD = 30.0
FORWARD_SPREAD_MARGIN = 10.0
FORWARD_DEPTH_RATIO_CHECKED = 8.0


def parametrisation_doubt(aabb: np.ndarray, c2w: np.ndarray,
                          opaque: float | None = None) -> tuple[tuple[str, str], str] | None:
    """Where `choose_parametrisation`'s automatic pick for this capture is unsure (the
    margins above): ((its pick, the alternative to try), why, one phrase); None where it
    is sure."""
    pick = choose_parametrisation(None, aabb, c2w, opaque)[0]
    if cameras_in_box(aabb, c2w).any():
        if pick == "bounded" and opaque is not None and opaque >= CLOSED_SHARE and looks_outwards(c2w)[0]:
            return None  # a closed room: checked (room, 12x, bounded 3.5 dB above contracted)
        reach, cams = box_reach(aabb, c2w)
        other = "bounded" if pick == "contracted" else "contracted"
        if pick == "contracted" and looks_outwards(c2w)[0]:
            return (pick, other), (f"cameras inside an open capture looking outwards at content {reach / cams:.1f}x "
                                   "their reach: a kind of capture the rule was never checked on")
        if REACH_CHECKED[0] < reach / cams < REACH_CHECKED[1]:
            return (pick, other), (f"the box reaches {reach / cams:.1f}x the cameras' reach, between the "
                                   f"{REACH_CHECKED[0]:g}x and {REACH_CHECKED[1]:g}x the rule was checked at")
        return None
    spread, ahead, depth_ratio = forward_cone(aabb, c2w)
    if ahead > 0 and abs(spread - FORWARD_SPREAD) < FORWARD_SPREAD_MARGIN:
        return (pick, "bounded" if pick == "forward" else "forward"), (
            f"viewing directions within {spread:.1f} degrees of their mean, within {FORWARD_SPREAD_MARGIN:g} of "
            f"the {FORWARD_SPREAD:g} the rule stops at")
    if pick == "forward" and depth_ratio < FORWARD_DEPTH_RATIO_CHECKED:
        return (pick, "bounded"), (f"the box's far side is {depth_ratio:.1f}x as far as its near side, below the "
                                   f"{FORWARD_DEPTH_RATIO_CHECKED:g}x forward space was checked at (a close-up)")
    return None


# The share of training pixels that must be opaque for a capture to count as closed: a
# closed room's renders are opaque everywhere (alpha is exact coverage); 0.1% leaves room
# for a stray pixel of a foreign dataset. A capture with sky is far below (inside: the sky
# above the ring; far-reaching: above the hills).
CLOSED_SHARE = 0.999


def looks_outwards(c2w: np.ndarray) -> tuple[bool, float]:
    """(True when the cameras do not look at a common point ahead of them, the median
    distance of that point ahead of the cameras along their axes). An orbit's axes meet
    ahead of every camera at about its radius; cameras in a cluster looking outwards have
    their least-squares meeting point within the cluster (or none: parallel axes)."""
    focus = axes_focus(c2w)
    if focus is None:
        return True, 0.0
    positions, forward = c2w[:, :3, 3], -c2w[:, :3, 2]
    forward = forward / np.linalg.norm(forward, axis=1, keepdims=True)
    ahead = float(np.median(((focus - positions) * forward).sum(axis=1)))
    cluster = float(np.linalg.norm(positions - positions.mean(axis=0), axis=1).max())
    return ahead <= cluster, ahead


def check_targets(aabb: np.ndarray, c2w: np.ndarray) -> None:
    """One-line InputError when no camera's optical axis passes through the bounds."""
    origins, forward = c2w[:, :3, 3], -c2w[:, :3, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (aabb[0] - origins) / forward
        t1 = (aabb[1] - origins) / forward
    t0 = np.nan_to_num(t0, nan=-np.inf)
    t1 = np.nan_to_num(t1, nan=np.inf)
    near = np.maximum(np.minimum(t0, t1).max(axis=1), 0)
    far = np.maximum(t0, t1).min(axis=1)
    if not (far >= near).any():
        raise InputError(f"the scene bounds {aabb.tolist()} contain no camera target: no training camera "
                         "looks into them (check scene.json bounds against the cameras)")


# An orbit's inner ball: this many times the half-width of the view at the centre, so
# content a little off the focus plane stays in it. far-reaching 128 px, 120 s, by the
# ball's radius (half-width 1.2, cameras at 3.2): 1.2 -> 26.17 dB, 2.0 -> 26.99, the
# cameras' 3.5 -> 26.22 (BENCHMARKS.md).
VIEW_BALL_FACTOR = 1.5
NEAR_AABB_FACTOR = 8.0  # an AABB reaching at most this many camera radii is all near content


def axes_focus(c2w: np.ndarray) -> np.ndarray | None:
    """The point nearest (least squares) to every camera's optical axis, [3], or None when
    the axes are (nearly) parallel. c2w [n, 4, 4]."""
    positions, forward = c2w[:, :3, 3], -c2w[:, :3, 2]
    forward = forward / np.linalg.norm(forward, axis=1, keepdims=True)
    projectors = np.eye(3)[None] - forward[:, :, None] * forward[:, None, :]  # [n, 3, 3]: off-axis part
    a = projectors.sum(axis=0)
    if np.linalg.eigvalsh(a).min() < 0.05 * len(c2w):  # axes within ~13 degrees of one direction
        return None
    return np.linalg.solve(a, (projectors @ positions[:, :, None]).sum(axis=0))[:, 0]


def contraction_frame(aabb: np.ndarray, c2w: np.ndarray, tan_half_fov: float | None = None) -> tuple[np.ndarray, float]:
    """(centre [3], inner radius) of the contraction for cameras among the content.

    Centre: where the optical axes meet (an orbit's target; outward-looking cameras: about
    their centroid), kept inside the AABB; the cameras' centroid when the axes are parallel
    (the AABB's centre may be far from anything the cameras see).
    Radius: the inner (linear, finest) ball holds the cameras (1.1 x the farthest); when the
    whole AABB lies within NEAR_AABB_FACTOR of that, it is all near content and the ball
    also reaches the AABB's faces (a room), else content beyond the cameras is contracted (an
    AABB of far terrain would otherwise spread the grid over it). An orbit around that far
    content (every camera looks at the centre, `tan_half_fov` given: the narrower half
    angle of the view) gets the ball every view holds around the centre, nearest camera
    distance x tan_half_fov x VIEW_BALL_FACTOR: the cameras then sit in the contracted shell, and the grid's
    finest cells go to what the orbit looks at, not to the air the cameras fly through."""
    aabb = np.asarray(aabb, dtype=float)
    focus = axes_focus(c2w)
    centre = np.clip(c2w[:, :3, 3].mean(axis=0) if focus is None else focus, aabb[0], aabb[1])
    offsets = c2w[:, :3, 3] - centre
    distances = np.linalg.norm(offsets, axis=1)
    cams = 1.1 * float(distances.max())
    reach = float(np.maximum(aabb[1] - centre, centre - aabb[0]).max())
    if reach <= NEAR_AABB_FACTOR * cams:
        return centre, max(reach, cams, 1e-3)
    if focus is not None and tan_half_fov is not None and tan_half_fov > 0:
        forward = -c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
        towards = -(offsets * forward).sum(axis=1) / np.maximum(distances, 1e-12)  # cos(axis, to centre)
        if bool((towards >= 1 / math.sqrt(1 + tan_half_fov ** 2)).all()):  # the centre is in every view
            return centre, max(min(cams, VIEW_BALL_FACTOR * float(distances.min()) * tan_half_fov), 1e-3)
    return centre, max(cams, 1e-3)


def make_space(kind: str, aabb: np.ndarray, c2w: np.ndarray, origins: torch.Tensor | None = None,
               directions: torch.Tensor | None = None, tan_half_fov: float | None = None) -> Space:
    """The numbers of a parametrisation for this dataset. aabb [2, 3]; c2w [n, 4, 4];
    origins, directions [m, 3]: (a subset of) the training rays (forward: the frustum's extent)."""
    if kind == "bounded":
        return Space("bounded", np.asarray(aabb, dtype=float).tolist())
    positions = c2w[:, :3, 3]
    box = [[-CONTRACTED_EXTENT] * 3, [CONTRACTED_EXTENT] * 3]
    if kind == "contracted":
        centre, radius = contraction_frame(aabb, c2w, tan_half_fov)
        return Space("contracted", box, centre=centre.tolist(), radius=radius)
    origin = positions.mean(axis=0)
    f = (-c2w[:, :3, 2]).mean(axis=0)
    f = f / np.linalg.norm(f)
    up = c2w[:, :3, 1].mean(axis=0)
    r = np.cross(f, up)
    r = r / np.linalg.norm(r)
    u = np.cross(r, f)
    frame = np.stack([r, u, f])
    corners = np.array([[aabb[i][0], aabb[j][1], aabb[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    depths = (corners - origin) @ f
    spread = float(np.linalg.norm(positions - origin, axis=1).max())
    z_near = max(float(depths.min()), 2 * spread, 1e-3)
    z_far = float(depths.max())
    if origins is None:
        extent = 1.0
    else:
        o = (origins.double().numpy() - origin) @ frame.T
        d = directions.double().numpy() @ frame.T
        extent = 0.0
        for z in (z_near, z_far):
            t = (z - o[:, 2]) / np.maximum(d[:, 2], 1e-6)
            extent = max(extent, float(np.abs((o[:, :2] + t[:, None] * d[:, :2]) / z).max()))
        extent *= 1.02
    box = [[-extent, -extent, LOG_DEPTH_SCALE * math.log(z_near)], [extent, extent, LOG_DEPTH_SCALE * math.log(z_far)]]
    return Space("forward", box, origin=origin.tolist(), frame=frame.tolist())
