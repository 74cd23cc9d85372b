"""An equirectangular (latitude-longitude) HDR/EXR image as the scene's light.

Row 0 is the zenith (+Z), the last row the nadir; column 0 and the centre column follow
Mitsuba's envmap convention once generate/ maps Mitsuba's +Y up to our +Z up, and
`rotation` turns the map about +Z (degrees, counter-clockwise seen from above).
"""

from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nerfgauge.core import arguments, bounded, validate
from nerfgauge.core.errors import InputError
from nerfgauge.core.images import read_exr

ENVMAP_SUFFIXES = (".exr", ".hdr")
# An envmap file is read whole before its header is checked: at most float32 RGBA at
# MAX_IMAGE_SIDE a side uncompressed (what validate bounds decoding to), plus its header.
MAX_ENVMAP_BYTES = validate.MAX_DECODED_BYTES + (1 << 20)


@dataclass(frozen=True)
class EnvironmentMap:
    """path, sha256 of its bytes, rotation about +Z in degrees, size. The pixels (linear
    RGB [H, W, 3] float32) are an attribute outside the dataclass fields, so scene.json
    records the file and its hash rather than the pixels."""

    path: str
    sha256: str
    rotation: float
    width: int
    height: int


def read_envmap(path, rotation: float = 0.0) -> EnvironmentMap:
    """Read an .exr (R, G, B channels) or Radiance .hdr latitude-longitude map.
    Anything that is not such an image is a one-line InputError."""
    path = Path(arguments.encodable_path(path, "envmap"))
    if not math.isfinite(float(rotation)):
        raise InputError(f"envmap rotation must be a finite number of degrees, got {rotation!r}")
    if not path.is_file():
        raise InputError(f"envmap not found: {path}")
    if path.suffix.lower() not in ENVMAP_SUFFIXES:
        raise InputError(f"envmap {path} has unsupported extension {path.suffix!r}; use one of "
                         f"{', '.join(ENVMAP_SUFFIXES)} (an equirectangular HDR image)")
    data = bounded.read_bytes(path, MAX_ENVMAP_BYTES, "envmap")
    pixels = _read_exr_rgb(path, data) if path.suffix.lower() == ".exr" else read_radiance_hdr(path, data)
    height, width = pixels.shape[:2]
    if width < 2 or height < 1:
        raise InputError(f"envmap {path} is {width}x{height} pixels; an equirectangular map needs at least 2x1")
    if not np.isfinite(pixels).all() or (pixels < 0).any():
        raise InputError(f"envmap {path} has negative, NaN or inf pixels; radiance must be finite and >= 0")
    validate.radiance(pixels, f"envmap {path}")
    light = EnvironmentMap(str(path), hashlib.sha256(data).hexdigest(), float(rotation), int(width), int(height))
    object.__setattr__(light, "pixels", np.ascontiguousarray(pixels, np.float32))
    return light


def _read_exr_rgb(path: Path, data: bytes) -> np.ndarray:
    channels, _ = read_exr(path, data)
    if "RGB" in channels or "RGBA" in channels:
        packed = channels.get("RGB", channels.get("RGBA"))
        return np.asarray(packed, np.float32)[..., :3]
    if not {"R", "G", "B"} <= set(channels):
        raise InputError(f"envmap {path} has channels {', '.join(sorted(channels))}; expected R, G and B")
    return np.stack([channels[c] for c in "RGB"], -1).astype(np.float32)


def read_radiance_hdr(path: Path, data: bytes) -> np.ndarray:
    """Decode a Radiance RGBE (.hdr) image: flat or new-style run-length encoded scanlines,
    orientation "-Y H +X W" (the one every writer uses). Returns [H, W, 3] float32."""
    def bad(why):
        return InputError(f"envmap {path} is not a Radiance .hdr image ({why})")

    if not (data.startswith(b"#?RADIANCE") or data.startswith(b"#?RGBE")):
        raise bad("no #?RADIANCE signature")
    end = data.find(b"\n\n")
    if end < 0:
        raise bad("no end of header")
    header = data[:end].decode("ascii", errors="replace")
    if "FORMAT=" in header and "32-bit_rle_rgbe" not in header:
        raise bad("only the 32-bit_rle_rgbe format is read")
    line_end = data.find(b"\n", end + 2)
    match = re.fullmatch(rb"-Y (\d+) \+X (\d+)", data[end + 2:line_end].strip())
    if line_end < 0 or not match:
        raise bad("expected a '-Y H +X W' resolution line")
    height, width = int(match.group(1)), int(match.group(2))
    if not (0 < width <= 32768 and 0 < height <= 32768):
        raise bad(f"size {width}x{height} out of range")
    stream, pos = np.frombuffer(data, np.uint8), line_end + 1
    out = np.empty((height, width, 4), np.uint8)
    try:
        for row in range(height):
            head = stream[pos:pos + 4]
            if width < 8 or width > 32767 or len(head) < 4 or head[0] != 2 or head[1] != 2 or head[2] & 0x80:
                flat = stream[pos:pos + 4 * width]
                if len(flat) < 4 * width:
                    raise bad("truncated pixels")
                out[row] = flat.reshape(width, 4)
                pos += 4 * width
                continue
            pos += 4
            for channel in range(4):
                column = 0
                while column < width:
                    count = int(stream[pos])
                    if count > 128:
                        count -= 128
                        out[row, column:column + count, channel] = stream[pos + 1]
                        pos += 2
                    else:
                        if count == 0:
                            raise bad("zero-length run")
                        out[row, column:column + count, channel] = stream[pos + 1:pos + 1 + count]
                        pos += 1 + count
                    column += count
                if column != width:
                    raise bad("run crosses a scanline")
    except (IndexError, ValueError):
        raise bad("truncated pixels") from None
    exponent = out[..., 3].astype(np.int32)
    scale = np.where(exponent > 0, np.ldexp(1.0, exponent - 136), 0.0)  # 2^(e - 128) / 256
    return (out[..., :3].astype(np.float64) * scale[..., None]).astype(np.float32)
