"""The 2D toy problem of positional encoding (Tancik et al. 2020, "Fourier features"):
memorise an image with an MLP, with and without positional encoding.

An MLP mapping pixel coordinates (x, y) in [0, 1]^2 to RGB is fitted to one image for a
fixed number of full-batch Adam steps, once on the raw coordinates and once on their
positional encoding (`nerf.encoding`). A plain MLP is biased towards low frequencies and
learns only a blurred image; the encoding lets the same network reproduce fine stripes.
The image is procedural (seeded): a smooth colour field plus oriented sinusoid gratings
and curved (circular) stripes of 4-10 cycles per image, below the 32-cycle Nyquist limit
of 64 pixels, so the detail is real signal, not aliasing.

Both fits share the seed, the hidden layers' initialisation and the optimiser; only the
first layer's input differs. Randomness comes from a numpy Generator (the image) and a
torch.Generator (the weights), both built from `seed`; nothing is seeded globally.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from nerfgauge.nerf.encoding import encoded_size, positional_encoding
from torch import nn

from nerfgauge.core import owned
from nerfgauge.core.files import atomic_path, write_json
from nerfgauge.core.outputs import png_kind_info

TOY_PE_KIND = "toy-pe"  # toy_pe.png's and toy_pe.json's kind (core.outputs)


@dataclass(frozen=True)
class ToyPEConfig:
    """Everything that determines a toy-pe run; saved as JSON beside its picture."""

    size: int = 64  # image is size x size pixels
    steps: int = 200  # full-batch Adam steps per fit
    seed: int = 0
    n_frequencies: int = 6  # L of the encoding: 2^5 pi x has 16 cycles per image
    hidden: int = 64
    layers: int = 2  # hidden layers
    learning_rate: float = 5e-3

    def __post_init__(self):
        for name in ("size", "steps", "n_frequencies", "hidden", "layers", "seed"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool):
                raise ValueError(f"{name} must be an integer, got {value!r}")
        if self.size < 8:
            raise ValueError(f"size must be >= 8 pixels, got {self.size}")
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.n_frequencies < 1:
            raise ValueError(f"n_frequencies must be >= 1, got {self.n_frequencies}")
        if self.hidden < 1 or self.layers < 1:
            raise ValueError(f"hidden and layers must be >= 1, got {self.hidden} and {self.layers}")
        if not self.learning_rate > 0:
            raise ValueError(f"learning_rate must be > 0, got {self.learning_rate}")


@dataclass(frozen=True)
class ToyPEResult:
    config: ToyPEConfig
    psnr_no_pe: float  # dB, on the training pixels (memorisation)
    psnr_pe: float
    target: np.ndarray  # [size, size, 3] float32 in [0, 1]
    fit_no_pe: np.ndarray  # [size, size, 3]
    fit_pe: np.ndarray  # [size, size, 3]

    @property
    def gap(self) -> float:
        """PSNR(PE) - PSNR(no PE), dB."""
        return self.psnr_pe - self.psnr_no_pe


def make_image(size: int, rng: np.random.Generator) -> np.ndarray:
    """A procedural high-frequency RGB image, [size, size, 3] float32 in (0, 1).

    Per channel: a smooth field (a linear ramp and a Gaussian blob), three oriented
    gratings sin(2 pi f (x cos th + y sin th) + phi) and one ring pattern
    sin(2 pi f |p - c| + phi), with f in [4, 10] cycles per image, squashed by a sigmoid.
    """
    y, x = (np.mgrid[0:size, 0:size] + 0.5) / size  # [size, size] each, pixel centres, row 0 at top
    image = np.empty((size, size, 3))
    for c in range(3):
        slope = rng.uniform(-1.5, 1.5, size=2)
        blob_centre = rng.uniform(0.2, 0.8, size=2)
        smooth = slope[0] * (x - 0.5) + slope[1] * (y - 0.5)
        smooth += 2.0 * np.exp(-((x - blob_centre[0]) ** 2 + (y - blob_centre[1]) ** 2) / 0.08) - 0.5
        detail = np.zeros((size, size))
        for _ in range(3):
            angle, frequency, phase = rng.uniform(0, np.pi), rng.uniform(4, 10), rng.uniform(0, 2 * np.pi)
            detail += np.sin(2 * np.pi * frequency * (x * np.cos(angle) + y * np.sin(angle)) + phase)
        ring_centre, frequency, phase = rng.uniform(0.2, 0.8, size=2), rng.uniform(6, 10), rng.uniform(0, 2 * np.pi)
        detail += 1.5 * np.sin(2 * np.pi * frequency * np.hypot(x - ring_centre[0], y - ring_centre[1]) + phase)
        image[..., c] = 1.0 / (1.0 + np.exp(-(1.5 * smooth + 0.8 * detail)))
    return image.astype(np.float32)


def pixel_coordinates(size: int) -> torch.Tensor:
    """(x, y) of every pixel centre in [0, 1]^2, row-major: [size * size, 2] float32."""
    centres = (torch.arange(size, dtype=torch.float32) + 0.5) / size
    y, x = torch.meshgrid(centres, centres, indexing="ij")
    return torch.stack([x, y], dim=-1).reshape(-1, 2)


def make_mlp(in_dim: int, hidden: int, layers: int, generator: torch.Generator) -> nn.Sequential:
    """ReLU MLP in_dim -> hidden (x layers) -> 3 with a sigmoid, initialised from `generator`.

    Same scheme as nn.Linear's default (Kaiming-uniform weights, uniform biases), drawn
    from the given generator so runs are reproducible without a global seed.
    """
    modules: list[nn.Module] = []
    dims = [in_dim] + [hidden] * layers
    for d_in, d_out in zip(dims[:-1], dims[1:]):
        modules += [nn.Linear(d_in, d_out), nn.ReLU()]
    modules += [nn.Linear(dims[-1], 3), nn.Sigmoid()]
    with torch.no_grad():
        for module in modules:
            if isinstance(module, nn.Linear):
                nn.init.kaiming_uniform_(module.weight, a=math.sqrt(5), generator=generator)
                bound = 1.0 / math.sqrt(module.in_features)
                module.bias.uniform_(-bound, bound, generator=generator)
    return nn.Sequential(*modules)


def psnr(prediction: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR in dB for values in [0, 1]."""
    mse = float(torch.mean((prediction - target) ** 2))
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def fit_image(features: torch.Tensor, target: torch.Tensor, config: ToyPEConfig, generator: torch.Generator
              ) -> torch.Tensor:
    """Fit an MLP features [P, F] -> target [P, 3] by full-batch Adam on MSE. Returns the fit [P, 3]."""
    model = make_mlp(features.shape[-1], config.hidden, config.layers, generator)
    optimiser = torch.optim.Adam(model.parameters(), lr=config.learning_rate)
    for _ in range(config.steps):
        loss = torch.mean((model(features) - target) ** 2)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        return model(features)


def run_toy_pe(config: ToyPEConfig = ToyPEConfig(), out_path: Path | None = None) -> ToyPEResult:
    """Fit the image without and with positional encoding; optionally save target | no PE | PE.

    out_path: a .png path; a JSON of the config and PSNRs is written beside it (same stem).
    """
    target_np = make_image(config.size, np.random.default_rng(config.seed))
    target = torch.from_numpy(target_np).reshape(-1, 3)  # [P, 3]
    xy = pixel_coordinates(config.size)  # [P, 2]
    encoded = positional_encoding(xy, config.n_frequencies)  # [P, 2 (1 + 2L)]
    assert encoded.shape[-1] == encoded_size(2, config.n_frequencies)
    fits = {}
    for name, features in (("no_pe", xy), ("pe", encoded)):
        # A fresh generator per fit from the same seed: both start from the same draws.
        generator = torch.Generator().manual_seed(config.seed)
        fits[name] = fit_image(features, target, config, generator)
    shape = (config.size, config.size, 3)
    result = ToyPEResult(
        config=config,
        psnr_no_pe=psnr(fits["no_pe"], target),
        psnr_pe=psnr(fits["pe"], target),
        target=target_np,
        fit_no_pe=fits["no_pe"].reshape(shape).numpy(),
        fit_pe=fits["pe"].reshape(shape).numpy(),
    )
    if out_path is not None:
        save_comparison(result, Path(out_path))
    return result


def comparison_image(result: ToyPEResult, scale: int = 4, gap: int = 4) -> np.ndarray:
    """target | no PE | PE side by side on white, each upscaled `scale`x (nearest): uint8 [H, W, 3]."""
    panels = [np.repeat(np.repeat(image, scale, axis=0), scale, axis=1)
              for image in (result.target, result.fit_no_pe, result.fit_pe)]
    height = panels[0].shape[0]
    spacer = np.ones((height, gap, 3), np.float32)
    row = np.concatenate([panels[0], spacer, panels[1], spacer, panels[2]], axis=1)
    return np.round(np.clip(row, 0.0, 1.0) * 255).astype(np.uint8)


def save_comparison(result: ToyPEResult, path: Path) -> None:
    """Write the comparison PNG and a JSON of the config and PSNRs (atomically: temporary name, fsync, rename)."""
    from PIL import Image  # PIL: only when the figure is written

    owned.make_folder(path.parent)

    def finite(value):  # a perfect fit has infinite PSNR, which JSON cannot hold: null
        return value if math.isfinite(value) else None

    summary = {"config": asdict(result.config), "psnr_no_pe": finite(result.psnr_no_pe),
               "psnr_pe": finite(result.psnr_pe), "gap_db": finite(result.gap), "png": path.name,
               "tool": "nerfgauge", "kind": TOY_PE_KIND}
    with atomic_path(path) as temporary:  # marked as ours: a rerun may replace it (core.outputs)
        Image.fromarray(comparison_image(result)).save(temporary, format="PNG", pnginfo=png_kind_info(TOY_PE_KIND))
    write_json(path.with_suffix(".json"), summary)
