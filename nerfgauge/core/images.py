"""Image files as the project writes and reads them: 8-bit sRGB PNG, float32 EXR.

Every write is atomic (nerfgauge.core.files.atomic_path) and read back before the rename: the
file must be whole and its header must state the size (and EXR channels) written
(nerfgauge.core.complete), as OpenEXR does not report a write that failed on a full disk.
PNG colour is straight (not premultiplied) alpha, as in NeRF-synthetic; EXR colour is linear
and premultiplied, as EXR expects.

Reading checks before decoding (nerfgauge.core.validate): the file's signature matches its
extension, and the header's size is at most MAX_IMAGE_SIDE pixels a side (and, when given,
the size the caller expects). Reading takes the file's bytes when the caller already has
them (the dataset reader hashes them against the manifest first), so a file is read once.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import tempfile
import threading
from pathlib import Path
from typing import Optional

import numpy as np
import OpenEXR
from PIL import Image, PngImagePlugin

from nerfgauge.core import complete, validate
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import atomic_path
from nerfgauge.core.outputs import png_kind_info

SMALL_EXR_BYTES = 1 << 20


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


def _verified_image(width: int, height: int, channels=None):
    """atomic_path's check for an image: structurally whole, and the header read back from
    the temporary states the size (and EXR channels) that were written."""
    def verify(tmp, shown):
        complete.check_complete(tmp, shown=shown)
        complete.check_image_header(tmp, width, height, channels, shown=shown)
    return verify


def write_png(path, image: np.ndarray, kind: str | None = None) -> None:
    """uint8 [H, W], [H, W, 3] or [H, W, 4]. kind: a nerfgauge output kind stored as a text
    chunk (core.outputs.PNG_KEY), for images written at a path the user chose."""
    if image.dtype != np.uint8:
        raise ValueError(f"write_png needs uint8, got {image.dtype}")
    info = None
    if kind is not None:
        info = png_kind_info(kind)
    with atomic_path(path, verify=_verified_image(image.shape[1], image.shape[0])) as tmp:
        Image.fromarray(image).save(tmp, format="PNG", pnginfo=info)


def _file_bytes(path) -> bytes:
    try:
        return Path(path).read_bytes()
    except FileNotFoundError:
        raise InputError(f"missing file: {path}") from None
    except OSError as error:
        raise InputError(f"cannot read {path}: {error.strerror or error}") from None


def _png_chunks_complete(data: bytes) -> bool:
    """The chunks after the signature (length, type, data, CRC each) end exactly at the end
    of `data`, the last one empty (IEND): a file cut anywhere fails. Chunk contents and
    CRCs are Pillow's to check (and the manifest's hash)."""
    position, last_length = 8, None
    while position + 12 <= len(data):
        last_length = int.from_bytes(data[position:position + 4], "big")
        position += 12 + last_length
    return position == len(data) and last_length == 0


def read_png(path, data: Optional[bytes] = None, expected_size=None) -> np.ndarray:
    """Returns float32 in [0, 1], [H, W] or [H, W, C] as stored (palette and 1-bit images
    expanded). data: the file's bytes if already read (and verified); expected_size:
    Intrinsics or (width, height) the header must state.

    The signature and the header's size are checked before any pixel is decoded
    (nerfgauge.core.validate: at most MAX_IMAGE_SIDE pixels a side), so Pillow's
    decompression-bomb warning and error never arise.
    """
    data = _file_bytes(path) if data is None else data
    validate.image_magic(data, path)
    if not _png_chunks_complete(data):  # Pillow decodes a file cut inside or before its end chunk
        raise InputError(f"cannot read image {path}: truncated (its chunks do not end with the empty end chunk)")
    try:
        # The PNG plugin's constructor reads the header only; unlike Image.open it has no
        # decompression-bomb check of its own (ours, stricter, runs before any decoding).
        with PngImagePlugin.PngImageFile(io.BytesIO(data)) as image:
            validate.image_size(*image.size, path)
            if expected_size is not None:
                validate.header_matches(*image.size, expected_size, path)
            if image.mode in ("P", "PA"):
                image = image.convert("RGBA" if "transparency" in image.info or image.mode == "PA" else "RGB")
            elif image.mode == "1":
                image = image.convert("L")
            array = np.asarray(image)
    except InputError:
        raise
    except (OSError, ValueError, SyntaxError, EOFError, Image.DecompressionBombError) as error:
        raise InputError(f"cannot read image {path}: {error}") from None
    if array.dtype == np.uint16 or array.dtype == np.int32:  # 16-bit PNG ("I;16" or "I")
        return array.astype(np.float32) / 65535.0
    return array.astype(np.float32) / 255.0


def write_exr(path, channels: dict, attributes: dict | None = None) -> None:
    """channels: name -> float32 [H, W] (or [H, W, k] for grouped names like "RGBA").

    attributes: extra string header entries (e.g. which depth the file holds).
    """
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(attributes or {})
    arrays = {name: np.ascontiguousarray(value, dtype=np.float32) for name, value in channels.items()}
    height, width = next(iter(arrays.values())).shape[:2]
    names = set()  # the channels the header must list: "RGBA" [H, W, 4] is stored as R, G, B, A
    for name, value in arrays.items():
        if value.ndim == 2:
            names.add(name)
        elif name in ("RGB", "RGBA") and value.shape[2] == len(name):
            names |= set(name)
        else:  # other grouped names are named by the binding's own rules: size checked only
            names = None
            break
    with atomic_path(path, verify=_verified_image(width, height, names)) as tmp:
        with OpenEXR.File(header, arrays) as exr:
            exr.write(str(tmp))


# Scanlines per chunk of each EXR compression (the header's "compression" byte), from the
# OpenEXR file layout: NO, RLE, ZIPS, ZIP, PIZ, PXR24, B44, B44A, DWAA, DWAB.
_EXR_LINES_PER_CHUNK = {0: 1, 1: 1, 2: 1, 3: 16, 4: 32, 5: 16, 6: 32, 7: 32, 8: 32, 9: 256}


def exr_truncation(data: bytes) -> Optional[str]:
    """Why a single-part scanline EXR is cut short (a chunk its offset table lists lies
    past the end of `data`), or None. OpenEXR reports such a file while decoding, and its
    C library also writes a line of its own to stderr; this check comes first. Tiled,
    multi-part, deep and unknown-compression files are left to OpenEXR (None)."""
    if len(data) < 8 or data[4] != 2 or data[5] & 0x1E:  # version 2, single-part scanline only
        return None
    position, compression, window = 8, None, None
    try:
        while True:
            name_end = data.index(b"\0", position)
            if name_end == position:  # the empty name that ends the header
                position += 1
                break
            type_end = data.index(b"\0", name_end + 1)
            size = int.from_bytes(data[type_end + 1:type_end + 5], "little", signed=True)
            if size < 0 or type_end + 5 + size > len(data):
                return "its header is cut short"
            value = data[type_end + 5:type_end + 5 + size]
            name = data[position:name_end]
            if name == b"compression" and size == 1:
                compression = value[0]
            elif name == b"dataWindow" and size == 16:
                window = np.frombuffer(value, "<i4")
            position = type_end + 5 + size
    except ValueError:  # no NUL: the header itself is cut
        return "its header is cut short"
    if compression not in _EXR_LINES_PER_CHUNK or window is None:
        return None
    chunks = -(-(int(window[3]) - int(window[1]) + 1) // _EXR_LINES_PER_CHUNK[compression])
    if chunks <= 0 or position + 8 * chunks > len(data):
        return "its offset table is cut short"
    offsets = np.frombuffer(data, "<u8", chunks, position).astype(np.int64)  # each: y (int32), size (int32), data
    if (offsets + 8 > len(data)).any() or (offsets < position).any():
        return f"chunk {int(np.argmax((offsets + 8 > len(data)) | (offsets < position)))} lies past its end"
    sizes = np.array([int.from_bytes(data[o + 4:o + 8], "little", signed=True) for o in offsets], np.int64)
    past = (sizes < 0) | (offsets + 8 + sizes > len(data))
    return f"chunk {int(np.argmax(past))} of {chunks} is cut short" if past.any() else None


_STDERR_LOCK = threading.Lock()


@contextlib.contextmanager
def _library_stderr(messages: list):
    """Run a block with file descriptor 2 sent to a temporary file, its text appended to
    `messages`: OpenEXR's C library prints its complaints about a damaged file there itself
    (a fresh fuzz seed: "EXR_ERR_BAD_CHUNK_LEADER ..." lines before our one-line error), and
    a command's stderr must stay one line. One block at a time (the descriptor is the
    process's); other threads' writes to stderr in the meantime land in the file too."""
    with _STDERR_LOCK, tempfile.TemporaryFile() as capture:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(capture.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            capture.seek(0)
            messages.append(capture.read().decode("utf-8", "replace"))


def read_exr(path, data: Optional[bytes] = None, expected_size=None) -> tuple[dict, dict]:
    """Returns (channels: name -> float32 array, header dict). data, expected_size: as for
    read_png. The signature and the dataWindow's size are checked before pixels are read.

    The pixels are decoded from `data` through a stream where OpenEXR's binding accepts one
    (3.5+); older bindings read `path` again (from the page cache) after the check.
    """
    data = _file_bytes(path) if data is None else data
    validate.image_magic(data, path)
    library = []  # what OpenEXR's C library printed while reading (_library_stderr)
    try:
        with _library_stderr(library):
            return _read_exr(path, data, expected_size)
    except InputError:
        raise
    except Exception as error:  # OpenEXR raises RuntimeError/OSError variants
        said = str(error).splitlines()[0] if str(error) else type(error).__name__
        printed = next((line.strip() for line in "".join(library).splitlines() if line.strip()), "")
        raise InputError(f"cannot read EXR {path}: {said}" + (f" ({printed[:160]})" if printed else "")) from None


def _read_exr(path, data: bytes, expected_size) -> tuple[dict, dict]:
    """read_exr's decoding (its errors turned into one line by read_exr)."""
    try:
        sources = (io.BytesIO(data), io.BytesIO(data))
        with OpenEXR.File(sources[0], header_only=True) as exr:
            header = dict(exr.header())
    except TypeError:  # a binding without stream support
        sources = (str(path), str(path))
        with OpenEXR.File(sources[0], header_only=True) as exr:
            header = dict(exr.header())
    low, high = (np.asarray(corner, np.int64) for corner in header["dataWindow"])
    width, height = (int(n) for n in high - low + 1)
    validate.image_size(width, height, path)
    validate.decoded_size(width, height, len(header.get("channels", ())), path)  # every channel as float32
    cut = exr_truncation(data)
    if cut is not None:
        raise InputError(f"cannot read EXR {path}: truncated ({cut})")
    if expected_size is not None:
        validate.header_matches(width, height, expected_size, path)
    # Small files decode faster on one thread (measured: 0.23 ms against 0.41 ms for a
    # 128x128 depth EXR through a stream); large ones keep OpenEXR's default pool.
    threads = 1 if len(data) < SMALL_EXR_BYTES else -1
    with OpenEXR.File(sources[1], header_only=False, num_threads=threads) as exr:
        channels = {name: np.array(ch.pixels, dtype=np.float32) for name, ch in exr.channels().items()}
    return channels, header


def read_exr_single(path, data: Optional[bytes] = None, expected_size=None) -> np.ndarray:
    """The one channel of a single-channel EXR (depth files). Returns [H, W] float32."""
    channels, _ = read_exr(path, data, expected_size)
    if len(channels) != 1:
        raise InputError(f"{path} should hold one channel, has {sorted(channels)}")
    (values,) = channels.values()
    if values.ndim != 2:  # OpenEXR groups R, G, B into one [H, W, 3] "RGB" entry
        raise InputError(f"{path} should hold one channel, has {values.shape[-1]} grouped as {next(iter(channels))!r}")
    return values
