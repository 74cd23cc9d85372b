"""Image files as the project writes and reads them: 8-bit sRGB PNG, float32 EXR.

Every write is atomic (nerfgauge.core.files.atomic_path). PNG colour is straight (not premultiplied) alpha, as in
NeRF-synthetic; EXR colour is linear and premultiplied, as EXR expects.
"""

from __future__ import annotations

import numpy as np
import OpenEXR
from PIL import Image

from nerfgauge.core.errors import InputError
from nerfgauge.core.files import atomic_path


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 transfer function on [0, 1] (values are clipped first)."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def premultiplied_to_png_rgba(rgba_linear: np.ndarray) -> np.ndarray:
    """Linear premultiplied RGBA [H, W, 4] -> 8-bit sRGB straight-alpha RGBA [H, W, 4] uint8."""
    alpha = np.clip(rgba_linear[..., 3:4], 0.0, 1.0)
    straight = np.divide(rgba_linear[..., :3], alpha, out=np.zeros_like(rgba_linear[..., :3]), where=alpha > 0)
    out = np.concatenate([linear_to_srgb(straight), alpha], axis=-1)
    return np.round(out * 255.0).astype(np.uint8)


def write_png(path, image: np.ndarray) -> None:
    """uint8 [H, W], [H, W, 3] or [H, W, 4]."""
    if image.dtype != np.uint8:
        raise ValueError(f"write_png needs uint8, got {image.dtype}")
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG")


def read_png(path) -> np.ndarray:
    """Returns float32 in [0, 1], [H, W] or [H, W, C] as stored."""
    try:
        with Image.open(path) as image:
            array = np.asarray(image)
    except (OSError, ValueError) as error:
        raise InputError(f"cannot read image {path}: {error}") from None
    if array.dtype == np.uint16:
        return array.astype(np.float32) / 65535.0
    return array.astype(np.float32) / 255.0


def write_exr(path, channels: dict, attributes: dict | None = None) -> None:
    """channels: name -> float32 [H, W] (or [H, W, k] for grouped names like "RGBA").

    attributes: extra string header entries (e.g. which depth the file holds).
    """
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(attributes or {})
    arrays = {name: np.ascontiguousarray(value, dtype=np.float32) for name, value in channels.items()}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, arrays) as exr:
            exr.write(str(tmp))


def read_exr(path) -> tuple[dict, dict]:
    """Returns (channels: name -> float32 array, header dict)."""
    try:
        with OpenEXR.File(str(path)) as exr:
            header = dict(exr.header())
            channels = {name: np.array(ch.pixels, dtype=np.float32) for name, ch in exr.channels().items()}
    except Exception as error:  # OpenEXR raises RuntimeError/OSError variants
        raise InputError(f"cannot read EXR {path}: {str(error).splitlines()[0] if str(error) else type(error).__name__}") from None
    return channels, header


def read_exr_single(path) -> np.ndarray:
    """The one channel of a single-channel EXR (depth files). Returns [H, W] float32."""
    channels, _ = read_exr(path)
    if len(channels) != 1:
        raise InputError(f"{path} should hold one channel, has {sorted(channels)}")
    (values,) = channels.values()
    return values
