"""Saving and loading models and training state, loadable with `weights_only=True`.

model.pt holds only plain types and tensors: {"format", "version", "model", "config",
"state", ...}. A compact model is saved pruned: only allocated grid nodes touching an
occupied cell are stored (float16, or 8 bits with --quantise int8), with the occupancy
mask; the rest load as empty space. Boolean masks are stored as zlib-compressed bits
(`pack_mask`): a surface's mask is mostly runs of zeros.

checkpoint.pt holds everything the training step reads, at full precision, so a resumed
run continues bit for bit: the model's state_dict (float32 as trained), Adam's state, the
ray-sampling generator, the loop's counters and schedules, and the run's recipe (dataset
manifest hash and every setting that shapes the trajectory), against which a resume is
checked.
"""

from __future__ import annotations

import io
import math
import zlib
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch
from nerfgauge.nerf.config import FLAGS, TrainConfig, step_ratio_of
from nerfgauge.nerf.schedule import EDGE_POINTS_PER_AXIS
from nerfgauge.nerf.grid_field import VoxelGridField, node_mask
from nerfgauge.nerf.models import CompactNeRF, VanillaNeRF
from nerfgauge.nerf.parametrisation import Space

from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_bytes_atomic

FORMAT = "nerfgauge-model"
VERSION = 2  # version 1 stored a dense grid or byte-per-node masks
CHECKPOINT_FORMAT = "nerfgauge-checkpoint"
CHECKPOINT_VERSION = 2  # version 1 was a float16 model payload inside a "nerfgauge-model"
FORMATS = {"model": (FORMAT, VERSION), "checkpoint": (CHECKPOINT_FORMAT, CHECKPOINT_VERSION)}


@dataclass
class LoopState:
    """The training loop's counters and schedules, all saved in checkpoint.pt and restored
    on resume, so a resumed run continues exactly.

    step, seconds: steps and training seconds done (validation and checkpointing excluded);
    next_eval: the training second of the next val PSNR point; logged_step: the step of the
    last log entry; visibility_done: visibility measurements done (of schedule.VISIBILITY_AT);
    stage: coarse-to-fine growths done; stage_steps, stage_seconds: steps and seconds at
    this resolution; last_stage: the finest stage the run will take (a time budget stops
    growing when a finer grid could not be trained); colour_head: the residual colour head's
    decision (TrainConfig.colour_head), made once the final grid has trained MIN_STAGE_STEPS
    steps: 0 not yet, 1 added, -1 not; edge_points: rays per axis through an `edges` run's
    edge pixels (nerf.schedule.EDGE_POINTS_PER_AXIS, then FINE_EDGE_POINTS_PER_AXIS, then
    FINER_EDGE_POINTS_PER_AXIS), and
    edge_points_step the step the half-budget refinement (those points, and a grid past the
    final one: last_stage + 1) was decided at (0: not yet; schedule.Schedule.refinement_due);
    finer_points_step: the step the rung to FINER_EDGE_POINTS_PER_AXIS was decided at (0: not
    yet; schedule.Schedule.finer_points_due);
    surface_step: the step surface opacity turned on at that decision (0: off;
    TrainConfig.surface_opacity); anneal_from: the share of the budget done when it did, from
    which the colour tables' learning rate anneals to its floor by the budget's end (0: no
    anneal; schedule.Schedule.lr_scales)."""

    step: int = 0
    seconds: float = 0.0
    next_eval: float = 0.0
    visibility_done: int = 0
    stage: int = 0
    stage_steps: int = 0
    logged_step: int = -1
    stage_seconds: float = 0.0
    last_stage: int = 0
    colour_head: int = 0
    edge_points: int = EDGE_POINTS_PER_AXIS
    edge_points_step: int = 0
    finer_points_step: int = 0
    surface_step: int = 0
    anneal_from: float = 0.0

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_saved(cls, saved: dict) -> "LoopState":
        """From a checkpoint's "loop" entry, checked by load_training_checkpoint."""
        return cls(**{item.name: saved[item.name] for item in fields(cls)})


# counters added after checkpoint version 2 first shipped, and their value in older files
LOOP_DEFAULTS = {"stage_seconds": 0.0, "last_stage": 3, "colour_head": -1, "edge_points": EDGE_POINTS_PER_AXIS,
                 "edge_points_step": 0, "finer_points_step": 0, "surface_step": 0, "anneal_from": 0.0}


def save_atomic(obj, path) -> int:
    """torch.save to a temporary name, then rename. Returns the file size in bytes."""
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    write_bytes_atomic(path, buffer.getvalue())
    return len(buffer.getvalue())


def load_checked(path, what: str = "model") -> dict:
    """torch.load(weights_only=True) with one-line errors for missing, corrupt or foreign
    files. what: "model" (model.pt) or "checkpoint" (checkpoint.pt)."""
    path = Path(path)
    expected_format, expected_version = FORMATS[what]
    if not path.is_file():
        raise InputError(f"{what} file not found: {path}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # corrupt zip, pickle refused by weights_only, truncated file
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise InputError(f"{path} is not a readable nerfgauge {what}: {first[:200]}") from None
    found = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
    if not isinstance(payload, dict) or found != expected_format:
        raise InputError(f"{path} is not a nerfgauge {what} (format {found!r})")
    if payload.get("version") != expected_version:
        raise InputError(f"{path} has {what} format version {payload.get('version')!r}; this nerfgauge reads "
                         f"{expected_version}")
    return payload


def pack_mask(mask: torch.Tensor) -> dict:
    """A bool tensor as {"shape": [...], "bits": uint8 tensor of zlib-compressed packed bits}."""
    bits = np.packbits(mask.detach().cpu().numpy().astype(bool).reshape(-1))
    packed = zlib.compress(bits.tobytes(), 9)
    return {"shape": list(mask.shape), "bits": torch.frombuffer(bytearray(packed), dtype=torch.uint8)}


def unpack_mask(packed: dict, shape) -> torch.Tensor:
    """Inverse of `pack_mask`, checked to have `shape`. ValueError on damage."""
    if not isinstance(packed, dict) or list(packed.get("shape", [])) != list(shape) \
            or not isinstance(packed.get("bits"), torch.Tensor) or packed["bits"].dtype != torch.uint8:
        raise ValueError(f"a stored mask does not have the grid's shape {list(shape)}")
    try:
        bits = np.frombuffer(zlib.decompress(packed["bits"].numpy().tobytes()), dtype=np.uint8)
    except zlib.error:
        raise ValueError("a stored mask does not decompress") from None
    count = int(np.prod(shape))
    if bits.size != (count + 7) // 8:
        raise ValueError(f"a stored mask holds {bits.size * 8} bits, the grid {count}")
    return torch.from_numpy(np.unpackbits(bits, count=count).astype(bool).reshape(shape))


def quantise_per_channel(values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """8-bit storage with a per-channel offset and scale: values [n, C] float ->
    (codes [n, C] uint8, offset [C], scale [C]) with values ~ offset + codes * scale,
    error at most scale / 2 per entry (scale = channel range / 255)."""
    low = values.amin(dim=0) if values.shape[0] else values.new_zeros(values.shape[1])
    high = values.amax(dim=0) if values.shape[0] else values.new_zeros(values.shape[1])
    scale = ((high - low) / 255).clamp_min(1e-12)
    codes = torch.round((values - low) / scale).clamp(0, 255).to(torch.uint8)
    return codes, low.float(), scale.float()


def dequantise_per_channel(codes: torch.Tensor, offset: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Inverse of `quantise_per_channel`: codes [n, C] uint8 -> values [n, C] float32."""
    return offset + codes.float() * scale


def model_payload(model, config: TrainConfig, prune: bool) -> dict:
    """Everything needed to rebuild `model` for rendering, pruned if asked."""
    payload = {"format": FORMAT, "version": VERSION, "model": config.model, "config": config.to_json()}
    if isinstance(model, CompactNeRF):
        field = model.field
        payload["resolution"] = field.resolution
        payload["aabb"] = field.aabb.cpu().tolist()
        if field.space is not None:
            payload["space"] = field.space.to_json()
        payload["occupancy"] = pack_mask(model.occupancy)
        payload["visible"] = pack_mask(model.visible)
        payload["head"] = {k: v.cpu() for k, v in field.head.state_dict().items()} if field.head is not None else {}
        if model.rise_steps > 0:  # surface opacity (absent: density opacity, as every older model)
            payload["rise_steps"] = float(model.rise_steps)
        keep = field.index.cpu() > 0
        if prune:
            keep &= node_mask(model.occupancy.cpu())
        payload["grid_shape"] = [1 + field.channels, *field.shape]
        payload["node_mask"] = pack_mask(keep)
        values = field.node_values(keep).cpu()  # [kept, C]
        if config.quantise == "int8":
            payload["node_values_q"], payload["node_offset"], payload["node_scale"] = quantise_per_channel(values)
        else:
            payload["node_values"] = values.half()
    else:
        payload["state"] = {k: v.cpu() for k, v in model.state_dict().items()}
    return payload


def build_model(config: TrainConfig, aabb: torch.Tensor, resolution: int | None = None, init_seed: int = 0,
                space=None, allocate: bool = True):
    """A fresh model for `config` (resolved), at `resolution` (compact) or its start.
    space: the compact grid's `nerf.parametrisation.Space` (None or bounded: over `aabb`;
    otherwise the grid spans space.box and `aabb` is not used). allocate=False: a compact
    grid with no node allocated yet (its values are loaded next).
    nn.Linear draws its initial weights from torch's global generator: it is seeded with
    `init_seed` inside fork_rng, so building a model never changes the caller's global RNG."""
    with torch.random.fork_rng(devices=[]):
        torch.random.manual_seed(init_seed)
        if config.model == "vanilla":
            return VanillaNeRF(aabb, config.n_coarse, config.n_fine, config.width, config.depth)
        if space is not None and space.kind != "bounded":
            aabb = torch.tensor(space.box, dtype=torch.float32)
        field = VoxelGridField(aabb, resolution or config.start_resolution, config.final_resolution,
                               config.view_dependent, config.feature_channels, step_ratio_of(config), space=space,
                               allocate=allocate)
        return CompactNeRF(field, use_occupancy=config.occupancy, sparse=config.prune)


def load_model(path):
    """Rebuild a model from model.pt. Returns (model, TrainConfig)."""
    payload = load_checked(path)
    try:
        config = config_of(payload)
        config.validate()  # the saved settings drive rendering: a damaged value is refused here
        return model_from_payload(payload), config
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError) as error:  # InputError is a ValueError
        raise InputError(f"{path} is a damaged nerfgauge model: {str(error).splitlines()[0][:200]}") from None


def config_of(payload: dict) -> TrainConfig:
    """A payload's TrainConfig; a model saved before `pixel_filter` existed trained through
    pixel centres."""
    return TrainConfig(**{"pixel_filter": "centre", **payload["config"]})


def model_from_payload(payload: dict):
    """The model described by a payload of `model_payload`."""
    config = config_of(payload)
    if config.model == "vanilla":
        aabb = payload["state"]["aabb"]
        model = build_model(config, aabb)
        model.load_state_dict(payload["state"])
        return model
    aabb = torch.tensor(payload["aabb"], dtype=torch.float32)
    space = Space.from_json(payload["space"]) if "space" in payload else None
    if (space.kind if space is not None else "bounded") != (config.parametrisation or "bounded"):
        raise ValueError(f"its grid's parametrisation does not match its config's {config.parametrisation!r}")
    model = build_model(config, aabb, payload["resolution"], space=space, allocate=False)
    field = model.field
    shape = payload["grid_shape"]
    if not config.view_dependent and payload["head"]:  # a diffuse grid that took the residual colour head
        field.add_residual_head(int(shape[0]) - 1)
    if list(shape) != [1 + field.channels, *field.shape]:
        raise ValueError(f"grid shape {tuple(shape)} does not match resolution {payload['resolution']}")
    mask = unpack_mask(payload["node_mask"], shape[1:])
    if "node_values_q" in payload:
        values = dequantise_per_channel(payload["node_values_q"], payload["node_offset"], payload["node_scale"])
    else:
        values = payload["node_values"].float()
    field.load_nodes(mask, values)
    if field.head is not None:
        field.head.load_state_dict(payload["head"])
    cells = [n - 1 for n in field.shape]
    model.occupancy = unpack_mask(payload["occupancy"], cells)
    model.visible = unpack_mask(payload["visible"], cells)
    rise_steps = payload.get("rise_steps", 0.0)
    if not isinstance(rise_steps, float) or not 0.0 <= rise_steps <= 64.0:
        raise ValueError(f"its surface opacity's length {rise_steps!r} is not a number of steps in [0, 64]")
    model.rise_steps = rise_steps
    return model


# --------------------------------------------------------------------------------------
# training checkpoints


def training_checkpoint(model, optimizer, generator: torch.Generator, config: TrainConfig, recipe: dict,
                        loop: LoopState) -> dict:
    """Everything a resumed run needs to continue exactly where this one is."""
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    field = getattr(model, "field", None)
    return {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "config": config.to_json(),
            "recipe": recipe, "model": {"kind": config.model, "resolution": getattr(field, "resolution", None),
                                        "state": state,
                                        "space": field.space.to_json() if getattr(field, "space", None) else None},
            "optimizer": optimizer.state_dict(), "generator": generator.get_state(),
            "loop": loop.to_json()}


def recipe_difference(saved: dict, current: dict) -> str:
    """What differs between two run recipes, as a phrase for a one-line message."""
    parts = []
    for key in sorted(set(saved) | set(current)):
        if saved.get(key) != current.get(key):
            if key == "dataset_sha256":
                parts.append(f"another dataset (manifest.json sha256 {str(saved.get(key))[:12]}..., "
                             f"this dataset's is {str(current.get(key))[:12]}...)")
            else:
                hint = f"; {FLAGS[key]} sets it" if key in FLAGS else ""
                parts.append(f"{key} {saved.get(key)!r} (this command: {current.get(key)!r}{hint})")
    return "; ".join(parts[:3]) + ("; ..." if len(parts) > 3 else "")


def load_training_checkpoint(path, recipe: dict) -> dict:
    """checkpoint.pt, checked to be complete and made by a run of `recipe`; InputError
    (one line) otherwise."""
    payload = load_checked(path, "checkpoint")
    saved_recipe = payload.get("recipe")
    if not isinstance(saved_recipe, dict):
        raise InputError(f"{path} is a damaged nerfgauge checkpoint: it has no recipe")
    if saved_recipe != recipe:
        raise InputError(f"{path} comes from another run: {recipe_difference(saved_recipe, recipe)}; "
                         "refusing to resume it")
    model, optimizer, loop = payload.get("model"), payload.get("optimizer"), payload.get("loop")
    problem = None
    if not isinstance(model, dict) or not isinstance(model.get("state"), dict):
        problem = "no model state"
    elif not isinstance(optimizer, dict) or not {"state", "param_groups"} <= set(optimizer):
        problem = "no optimizer state"
    elif not isinstance(payload.get("generator"), torch.Tensor) or payload["generator"].dtype != torch.uint8:
        problem = "no generator state"
    elif not isinstance(loop, dict):
        problem = "no loop state"
    else:
        for item in fields(LoopState):
            name, real = item.name, isinstance(item.default, float)  # a float counter also takes an int
            value = loop.setdefault(name, LOOP_DEFAULTS[name]) if name in LOOP_DEFAULTS else loop.get(name)
            if not isinstance(value, (int, float) if real else int) or isinstance(value, bool) \
                    or (name == "edge_points" and value < 1) \
                    or (name == "anneal_from" and not 0.0 <= value < 1.0):
                problem = f"loop value {name} is {value!r}"
                break
    if problem is not None:
        raise InputError(f"{path} is a damaged nerfgauge checkpoint: {problem}")
    return payload


def restore_model(payload: dict, config: TrainConfig, aabb: torch.Tensor, path, space=None):
    """The model saved in a training checkpoint, every tensor as it was saved. Keys, shapes
    and dtypes are checked against a model built for `config` first, so a damaged file is
    one line, not a traceback."""
    saved = payload["model"]
    resolution = saved.get("resolution")
    if config.model == "compact" and not (isinstance(resolution, int) and 4 <= resolution <= 1024):
        raise InputError(f"{path} is a damaged nerfgauge checkpoint: grid resolution {resolution!r}")
    saved_space = saved.get("space")
    wanted_space = space.to_json() if space is not None and space.kind != "bounded" else None
    if saved_space != wanted_space:
        raise InputError(f"{path} holds a grid of another parametrisation "
                         f"({(saved_space or {}).get('kind', 'bounded')}, this run: {config.parametrisation}); "
                         "refusing to resume it")
    model = build_model(config, aabb, resolution, space=space, allocate=False)
    features = saved["state"].get("field.features")
    if config.model == "compact" and not config.view_dependent and "field.head.0.weight" in saved["state"] \
            and isinstance(features, torch.Tensor) and features.ndim == 2:
        try:  # added when the grid reached its final size
            model.field.add_residual_head(features.shape[1])
        except ValueError as error:
            raise InputError(f"{path} is a damaged nerfgauge checkpoint: {error}") from None
    rows = saved["state"].get("field.density_table")
    if config.model == "compact" and isinstance(rows, torch.Tensor) and rows.ndim == 2 and rows.shape[0] >= 1:
        model.field.reserve(rows.shape[0])  # the sparse grid's allocated rows, as saved
    expected = model.state_dict()
    state = saved["state"]
    missing, unexpected = sorted(set(expected) - set(state)), sorted(set(state) - set(expected))
    if missing or unexpected:
        what = f"missing {', '.join(missing[:3])}" if missing else f"unexpected {', '.join(unexpected[:3])}"
        raise InputError(f"{path} is a damaged nerfgauge checkpoint: model state {what}")
    for name, tensor in expected.items():
        value = state[name]
        if not isinstance(value, torch.Tensor) or value.shape != tensor.shape or value.dtype != tensor.dtype:
            found = f"{tuple(value.shape)} {value.dtype}" if isinstance(value, torch.Tensor) else type(value).__name__
            raise InputError(f"{path} is a damaged nerfgauge checkpoint: {name} is {found}, expected "
                             f"{tuple(tensor.shape)} {tensor.dtype} at resolution {resolution}")
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise InputError(f"{path} is a damaged nerfgauge checkpoint: {name} holds NaN or inf")
    model.load_state_dict(state)
    if config.model == "compact":
        try:
            model.field.check_index()
        except ValueError as error:
            raise InputError(f"{path} is a damaged nerfgauge checkpoint: {error}") from None
    return model


def check_adam_step(value, index: int) -> None:
    """Adam's step count: one finite number >= 0 (torch keeps it as a float tensor; it
    adds 1 before the bias correction 1 - beta**step, so a step below 0 divides by zero),
    as a float or wide integer tensor: bool fails mid-step (found by a fresh fuzz seed), uint8
    wraps to 0 after 255 steps and the correction divides by zero."""
    if isinstance(value, bool) or not isinstance(value, (int, float, torch.Tensor)):
        raise ValueError(f"optimizer step of parameter {index} should be a number, is {type(value).__name__}")
    if isinstance(value, torch.Tensor):
        if value.numel() != 1:
            raise ValueError(f"optimizer step of parameter {index} should be one number, has shape {tuple(value.shape)}")
        if not (value.is_floating_point() or value.dtype in (torch.int32, torch.int64)):
            raise ValueError(f"optimizer step of parameter {index} is {value.dtype}, expected a float or a wide integer")
        value = value.item()
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"optimizer step of parameter {index} is {value}, expected a finite count >= 0")


def _split_grid_group(saved: dict, optimizer: torch.optim.Optimizer) -> dict:
    """A checkpoint written before the compact model's density and colour tables were Adam
    groups of their own (one unnamed group of both, then the head's) in the groups the
    model has now: the same settings and moments per parameter, so a run killed before the
    change resumes exactly. Anything else is returned as it is (and checked after)."""
    groups, now = saved.get("param_groups"), optimizer.param_groups
    try:
        old = (len(groups) == len(now) - 1 and [len(group["params"]) for group in now[:2]] == [1, 1]
               and len(groups[0]["params"]) == 2 and "name" not in groups[0])
    except (TypeError, KeyError):
        return saved
    if not old:
        return saved
    first = groups[0]  # named after loading, as any older file's groups are (restore_optimizer)
    split = [first | {"params": [first["params"][i]]} for i in (0, 1)]
    return saved | {"param_groups": split + list(groups[1:])}


def restore_optimizer(optimizer: torch.optim.Optimizer, saved: dict, path) -> None:
    """Load Adam's state after checking it fits the optimizer's parameters (torch checks
    group sizes, not the moments' shapes: a wrong shape would fail later, mid-step)."""
    saved = _split_grid_group(saved, optimizer)
    groups = saved["param_groups"]
    params = [p for group in optimizer.param_groups for p in group["params"]]
    try:
        saved_ids = [i for group in groups for i in group["params"]]
        if len(groups) != len(optimizer.param_groups) or len(saved_ids) != len(params):
            raise ValueError(f"{len(saved_ids)} parameters in {len(groups)} groups, the model has {len(params)} "
                             f"in {len(optimizer.param_groups)}")
        for index, param in zip(saved_ids, params):
            for key, value in saved["state"].get(index, {}).items():
                if key != "step" and (not isinstance(value, torch.Tensor) or value.shape != param.shape):
                    raise ValueError(f"optimizer {key} of parameter {index} has shape "
                                     f"{tuple(getattr(value, 'shape', ()))}, expected {tuple(param.shape)}")
                if key != "step" and value.dtype != param.dtype:
                    raise ValueError(f"optimizer {key} of parameter {index} is {value.dtype}, expected {param.dtype}")
                if key == "step":
                    check_adam_step(value, index)
                if isinstance(value, torch.Tensor) and value.is_floating_point() and not bool(torch.isfinite(value).all()):
                    raise ValueError(f"optimizer {key} of parameter {index} holds NaN or inf")
        names = [group.get("name") for group in optimizer.param_groups]
        optimizer.load_state_dict(saved)
        for group, name in zip(optimizer.param_groups, names):  # an older file's groups have none
            group.setdefault("name", name)
    except (ValueError, TypeError, KeyError, AttributeError) as error:
        raise InputError(f"{path} is a damaged nerfgauge checkpoint: {str(error).splitlines()[0][:200]}") from None


def restore_generator(generator: torch.Generator, state: torch.Tensor, path) -> None:
    if state.shape != generator.get_state().shape:
        raise InputError(f"{path} is a damaged nerfgauge checkpoint: generator state of {state.numel()} bytes")
    try:
        generator.set_state(state)
    except RuntimeError as error:
        raise InputError(f"{path} is a damaged nerfgauge checkpoint: {str(error).splitlines()[0][:200]}") from None
