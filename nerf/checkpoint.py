"""Saving and loading models and training state, loadable with `weights_only=True`.

model.pt holds only plain types and tensors: {"format", "version", "model", "config",
"state", ...}. A compact model is saved pruned: only grid nodes touching an occupied cell
are stored (float16), with the occupancy mask; the rest load as empty space.
"""

from __future__ import annotations

import io
from pathlib import Path

import torch
import torch.nn.functional as F
from nerfgauge.nerf.config import TrainConfig

from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_bytes_atomic

FORMAT = "nerfgauge-model"
VERSION = 1
EMPTY_RAW = -30.0  # softplus(-30 + shift) ~ 1e-13: no density where nothing was stored


def save_atomic(obj, path) -> int:
    """torch.save to a temporary name, then rename. Returns the file size in bytes."""
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    write_bytes_atomic(path, buffer.getvalue())
    return len(buffer.getvalue())


def load_checked(path, what: str = "model") -> dict:
    """torch.load(weights_only=True) with one-line errors for missing, corrupt or foreign files."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} file not found: {path}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # corrupt zip, pickle refused by weights_only, truncated file
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise InputError(f"{path} is not a readable nerfgauge {what}: {first[:200]}") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise InputError(f"{path} is not a nerfgauge {what} (format {payload.get('format') if isinstance(payload, dict) else type(payload).__name__!r})")
    if payload.get("version") != VERSION:
        raise InputError(f"{path} has model format version {payload.get('version')!r}; this nerfgauge reads {VERSION}")
    return payload


def node_mask(occupancy: torch.Tensor) -> torch.Tensor:
    """Grid nodes that are a corner of an occupied cell. occupancy [nz-1, ny-1, nx-1] ->
    [nz, ny, nx] bool."""
    padded = F.pad(occupancy[None, None].float(), (1, 1, 1, 1, 1, 1))
    return F.max_pool3d(padded, kernel_size=2, stride=1)[0, 0] > 0


def model_payload(model, config: TrainConfig, prune: bool) -> dict:
    """Everything needed to rebuild `model` for rendering, pruned if asked."""
    from nerfgauge.nerf.models import CompactNeRF

    payload = {"format": FORMAT, "version": VERSION, "model": config.model, "config": config.to_json()}
    if isinstance(model, CompactNeRF):
        field = model.field
        grid = field.grid.detach().cpu()[0]  # [C, nz, ny, nx]
        payload["resolution"] = field.resolution
        payload["aabb"] = field.aabb.cpu().tolist()
        payload["occupancy"] = model.occupancy.cpu()
        payload["visible"] = model.visible.cpu()
        payload["head"] = {k: v.cpu() for k, v in field.head.state_dict().items()} if field.head is not None else {}
        if prune:
            keep = node_mask(model.occupancy.cpu())
            payload["grid_shape"] = list(grid.shape)
            payload["node_mask"] = keep
            payload["node_values"] = grid[:, keep].t().contiguous().half()  # [kept, C]
        else:
            payload["grid"] = grid.half()
    else:
        payload["state"] = {k: v.cpu() for k, v in model.state_dict().items()}
    return payload


def build_model(config: TrainConfig, aabb: torch.Tensor, resolution: int | None = None):
    """A fresh model for `config` (resolved), at `resolution` (compact) or its start."""
    from nerfgauge.nerf.grid_field import VoxelGridField
    from nerfgauge.nerf.models import CompactNeRF, VanillaNeRF

    if config.model == "vanilla":
        return VanillaNeRF(aabb, config.n_coarse, config.n_fine, config.width, config.depth)
    field = VoxelGridField(aabb, resolution or config.start_resolution, config.final_resolution,
                           config.view_dependent, config.feature_channels, config.step_ratio)
    return CompactNeRF(field, use_occupancy=config.occupancy)


def load_model(path):
    """Rebuild a model from model.pt. Returns (model, TrainConfig)."""
    payload = load_checked(path)
    try:
        return model_from_payload(payload), TrainConfig(**payload["config"])
    except (KeyError, TypeError, ValueError, RuntimeError) as error:
        raise InputError(f"{path} is a damaged nerfgauge model: {str(error).splitlines()[0][:200]}") from None


def model_from_payload(payload: dict):
    """The model described by a payload of `model_payload`."""
    config = TrainConfig(**payload["config"])
    if config.model == "vanilla":
        aabb = payload["state"]["aabb"]
        model = build_model(config, aabb)
        model.load_state_dict(payload["state"])
        return model
    aabb = torch.tensor(payload["aabb"], dtype=torch.float32)
    model = build_model(config, aabb, payload["resolution"])
    field = model.field
    if "node_values" in payload:
        shape = payload["grid_shape"]
        grid = torch.zeros(shape)
        grid[0] = EMPTY_RAW
        grid[:, payload["node_mask"]] = payload["node_values"].float().t()
    else:
        grid = payload["grid"].float()
    if tuple(grid.shape) != tuple(field.grid.shape[1:]):
        raise ValueError(f"grid shape {tuple(grid.shape)} does not match resolution {payload['resolution']}")
    field.grid.data.copy_(grid[None])
    if field.head is not None:
        field.head.load_state_dict(payload["head"])
    model.occupancy = payload["occupancy"].bool()
    model.visible = payload["visible"].bool()
    return model
