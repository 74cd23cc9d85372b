"""The model: a set of 3D Gaussians, where they start, and Adam over them.

Parameters (3DGS's, activated when rendered):

    means           [N, 3]      world positions
    log_scales      [N, 3]      scales = exp(log_scales), standard deviations along the axes
    quats           [N, 4]      rotation (w, x, y, z), normalised when projected
    opacity_logits  [N]         opacity = sigmoid(logit)
    sh_dc           [N, 1, 3]   degree-0 SH coefficient (splat.sh)
    sh_rest         [N, 15, 3]  degrees 1-3 (trained from zero as the degree is raised)

Initialisation (Kerbl et al. 2023, from points with colours): a Gaussian per point, isotropic
with scale the root mean squared distance to its 3 nearest other points, rotation identity,
opacity 0.1, DC colour the point's colour, higher SH zero. `initial_points` reads the
dataset's points (sparse/0/points3D.txt, core.colmap_text; their kind is scene.json's
"points"; at most init_count of them, a seeded subset), or draws `none`'s init_count
uniformly in the scene bounds with random colours; init_count defaults to one per 4 pixels of
a training view (SplatConfig.initial_count).

`GaussianAdam` is Adam with one parameter group per attribute (each its own learning rate)
that follows the set as densification clones, splits and prunes it: moments of kept
Gaussians move with them, new ones start at zero (the 3DGS code's optimizer surgery).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from nerfgauge.core import colmap_text
from nerfgauge.core.dataset import Dataset
from nerfgauge.core.errors import InputError
from nerfgauge.splat.config import PIXELS_PER_INITIAL_GAUSSIAN, SplatConfig
from nerfgauge.splat.ply import REST_PER_CHANNEL, GaussianArrays
from nerfgauge.splat.render import Rendered, render
from nerfgauge.splat.sh import rgb_to_dc

ATTRIBUTES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")
SPARSE = "sparse/0"  # the dataset's COLMAP model (generate.export)
MODEL_FILES = ("cameras.txt", "images.txt", "points3D.txt")
POINTS_FILE = f"{SPARSE}/points3D.txt"
INITIAL_OPACITY = 0.1
NEIGHBOURS = 3
MIN_SQUARED_SPACING = 1e-7  # the 3DGS code's floor: coincident points get a tiny, finite scale
POINTS_SEED_TAG = 5050  # `none`'s points: default_rng([seed, POINTS_SEED_TAG])


@dataclass
class Gaussians:
    """The parameters (module docstring), leaf tensors of one dtype and device."""

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    opacity_logits: torch.Tensor
    sh_dc: torch.Tensor
    sh_rest: torch.Tensor

    def __len__(self) -> int:
        return self.means.shape[0]

    def tensors(self) -> dict:
        return {name: getattr(self, name) for name in ATTRIBUTES}

    def activated(self) -> tuple:
        """(means, scales, quats, opacities, sh [N, 16, 3]): splat.render.render's arguments."""
        sh = torch.cat([self.sh_dc, self.sh_rest], dim=1)  # [N, 16, 3]
        return self.means, torch.exp(self.log_scales), self.quats, torch.sigmoid(self.opacity_logits), sh

    def render(self, camera, background: torch.Tensor, sh_degree: int, backend: str = "cpu",
               retain_means2d_grad: bool = False) -> Rendered:
        """splat.render.render of these Gaussians, activated."""
        return render(*self.activated(), camera, background, sh_degree, backend=backend,
                      retain_means2d_grad=retain_means2d_grad)

    def to_arrays(self) -> GaussianArrays:
        """float32 numpy copies, in the PLY's terms (splat.ply)."""
        as_numpy = lambda t: t.detach().cpu().float().numpy()  # noqa: E731
        return GaussianArrays(as_numpy(self.means), as_numpy(self.log_scales), as_numpy(self.quats),
                              as_numpy(self.opacity_logits), np.concatenate([as_numpy(self.sh_dc),
                                                                             as_numpy(self.sh_rest)], axis=1))

    @classmethod
    def from_arrays(cls, arrays: GaussianArrays, device="cpu", requires_grad: bool = False) -> "Gaussians":
        tensor = lambda a: torch.tensor(np.asarray(a), dtype=torch.float32, device=device,  # noqa: E731
                                        requires_grad=requires_grad)
        sh = np.asarray(arrays.sh, np.float32)
        rest = np.zeros((len(sh), REST_PER_CHANNEL, 3), np.float32)
        rest[:, :sh.shape[1] - 1] = sh[:, 1:1 + REST_PER_CHANNEL]
        return cls(tensor(arrays.means), tensor(arrays.log_scales), tensor(arrays.quats),
                   tensor(arrays.opacity_logits), tensor(sh[:, :1]), tensor(rest))


def logit(p: float) -> float:
    return float(np.log(p / (1 - p)))


def initial_gaussians(xyz: np.ndarray, rgb: np.ndarray) -> GaussianArrays:
    """One Gaussian per point (module docstring). xyz: [N, 3]; rgb: [N, 3] in [0, 1]."""
    n = len(xyz)
    if n == 0:
        raise InputError("no points to start the Gaussians from")
    if n > NEIGHBOURS:
        distances, _ = cKDTree(xyz).query(xyz, k=NEIGHBOURS + 1)  # [N, 4]: the point itself first
        squared = np.maximum((distances[:, 1:] ** 2).mean(axis=1), MIN_SQUARED_SPACING)  # [N]
    else:  # too few points for neighbours: a hundredth of their spread, or of a unit scene
        spread = float(np.ptp(xyz, axis=0).max()) if n > 1 else 0.0
        squared = np.full(n, max((0.01 * (spread or 1.0)) ** 2, MIN_SQUARED_SPACING))
    log_scales = np.repeat(0.5 * np.log(squared)[:, None], 3, axis=1)  # [N, 3]
    quats = np.zeros((n, 4))
    quats[:, 0] = 1.0
    sh = np.zeros((n, 1 + REST_PER_CHANNEL, 3))
    sh[:, 0, :] = rgb_to_dc(torch.from_numpy(np.asarray(rgb, np.float64))).numpy()
    return GaussianArrays(np.asarray(xyz, np.float32), log_scales.astype(np.float32), quats.astype(np.float32),
                          np.full(n, logit(INITIAL_OPACITY), np.float32), sh.astype(np.float32))


def read_dataset_points(ds: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """(xyz [N, 3], rgb [N, 3] in [0, 1]) of the dataset's COLMAP model (SPARSE), read and
    cross-checked as any COLMAP model is (core.colmap_text.read_model: cameras, images,
    tracks)."""
    texts = {name: ds.read_bytes(f"{SPARSE}/{name}", limit=colmap_text.MAX_TEXT_BYTES) for name in MODEL_FILES}
    model = colmap_text.read_model(texts, {name: str(ds.root / SPARSE / name) for name in MODEL_FILES})
    colours = model.colours
    if colours.size and (colours.min() < 0 or colours.max() > 255):
        raise InputError(f"{ds.root / POINTS_FILE}: point colours must be 0 to 255")
    return model.points, colours / 255.0


def dataset_points_kind(ds: Dataset) -> str | None:
    """The kind of initial points the dataset holds (scene.json "points".kind), None if none."""
    record = ds.scene.get("points") if isinstance(ds.scene, dict) else None
    kind = record.get("kind") if isinstance(record, dict) else None
    if kind is None or POINTS_FILE not in ds.manifest_files:
        return None
    return kind if isinstance(kind, str) else None


def initial_points(ds: Dataset, config: SplatConfig) -> tuple[np.ndarray, np.ndarray, str]:
    """(xyz [N, 3], rgb [N, 3] in [0, 1], what they are) for config.init (module docstring)."""
    held = dataset_points_kind(ds)
    intrinsics = ds.cameras("train").intrinsics
    count = config.initial_count(intrinsics.width, intrinsics.height)
    why = "--init-count" if config.init_count is not None else \
        f"one per {PIXELS_PER_INITIAL_GAUSSIAN} pixels of a {intrinsics.width} x {intrinsics.height} view"
    init = config.init if config.init != "auto" else (held if held not in (None, "none") else "none")
    if init == "none":
        if ds.bounds is None:
            raise InputError(f"--init none: dataset {ds.root} has no scene bounds (scene.json \"bounds\") to draw "
                             "the points in; give a dataset with its COLMAP points (--init surface, sfm or random)")
        aabb = np.asarray(ds.bounds, np.float64)
        rng = np.random.default_rng([config.seed, POINTS_SEED_TAG])
        xyz = aabb[0] + (aabb[1] - aabb[0]) * rng.random((count, 3))
        rgb = rng.random((count, 3))
        return xyz, rgb, f"none: {count} points uniform in the scene bounds, random colours ({why})"
    if held != init:
        have = f"holds {held} points" if held else "holds no COLMAP points"
        raise InputError(f"--init {init}: dataset {ds.root} {have} (scene.json \"points\"); add them with "
                         f"`nerfgauge export colmap {ds.root} --points {init}`, or pass --init auto or none")
    xyz, rgb = read_dataset_points(ds)
    if len(xyz) == 0:
        raise InputError(f"--init {init}: {ds.root / POINTS_FILE} holds no points")
    if len(xyz) <= count:
        return xyz, rgb, f"{init}: the dataset's {len(xyz)} points ({POINTS_FILE}; at most {count}: {why})"
    chosen = np.sort(np.random.default_rng([config.seed, POINTS_SEED_TAG]).permutation(len(xyz))[:count])
    return xyz[chosen], rgb[chosen], (f"{init}: {count} of the dataset's {len(xyz)} points "
                                      f"({POINTS_FILE}; a seeded random subset: {why})")


class GaussianAdam:
    """Adam over the Gaussians' attributes, one group each, that follows the set as it changes."""

    def __init__(self, gaussians: Gaussians, rates: dict, eps: float = 1e-15):
        for name in ATTRIBUTES:
            getattr(gaussians, name).requires_grad_(True)
        self.gaussians = gaussians
        groups = [{"params": [getattr(gaussians, name)], "lr": rates[name], "name": name} for name in ATTRIBUTES]
        # fused: the same update in one kernel per tensor (30,000 Gaussians: 2.8 ms a step
        # against 19 ms for torch's default loop over elementwise ops, one thread)
        self.optimizer = torch.optim.Adam(groups, lr=0.0, eps=eps, fused=True)

    def group(self, name: str) -> dict:
        return next(g for g in self.optimizer.param_groups if g["name"] == name)

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    def step(self) -> None:
        self.optimizer.step()

    def _swap(self, name: str, tensor: torch.Tensor, moments) -> None:
        """Put `tensor` (a new leaf) in place of attribute `name`, with Adam moments
        moments(old moment) -> new moment (None: fresh state)."""
        group = self.group(name)
        old = group["params"][0]
        state = self.optimizer.state.pop(old, None)
        new = tensor.detach().requires_grad_(True)
        group["params"][0] = new
        if state and moments is not None:
            self.optimizer.state[new] = {key: moments(value) if torch.is_tensor(value) and value.dim() > 0 else value
                                         for key, value in state.items()}
        setattr(self.gaussians, name, new)

    @torch.no_grad()
    def keep(self, mask: torch.Tensor) -> None:
        """Keep only the Gaussians where `mask` [N] is True, with their moments."""
        for name in ATTRIBUTES:
            self._swap(name, getattr(self.gaussians, name)[mask], lambda moment: moment[mask])

    @torch.no_grad()
    def append(self, new: dict) -> None:
        """Add Gaussians {attribute: [M, ...]} at the end, their moments zero."""
        for name in ATTRIBUTES:
            extra = new[name]
            self._swap(name, torch.cat([getattr(self.gaussians, name), extra]),
                       lambda moment: torch.cat([moment, torch.zeros_like(extra)]))

    @torch.no_grad()
    def replace(self, name: str, values: torch.Tensor) -> None:
        """Set attribute `name` to `values` (same shape), its moments zero (3DGS's opacity reset)."""
        self._swap(name, values, lambda moment: torch.zeros_like(moment))
