"""Image files as the project writes and reads them: 8-bit sRGB PNG, float32 EXR (and,
from other tools, JPEG).

Every write is atomic (nerfgauge.core.files.atomic_path) and read back before the rename: the
file must be whole and its header must state the size (and EXR channels) written
(nerfgauge.core.complete), as OpenEXR does not report a write that failed on a full disk.
PNG colour is straight (not premultiplied) alpha, as in NeRF-synthetic; EXR colour is linear
and premultiplied, as EXR expects.

Reading, for every image nerfgauge reads (ours or another tool's, ground truth or
predictions), in this order:

1. the file is opened (a regular file only) and only its header is read (`image_header`:
   PNG's IHDR, JPEG's frame header, EXR's attributes; at most IMAGE_METADATA_BYTES): the
   signature must match the extension, each side be at most MAX_IMAGE_SIDE pixels, the
   decoded pixels at most MAX_DECODED_BYTES, and (when given) the size the caller expects
   (nerfgauge.core.validate);
2. the file's size on disk (fstat) must be at most what that header's pixels can take
   (`file_limit`: IMAGE_FILE_FACTOR times the pixels stored raw, plus
   IMAGE_METADATA_BYTES), so a 2 GiB file behind a 32x32 header is refused unread; a
   dataset's reader compares the size with its manifest first;
3. only then is the file read and decoded. Pillow is reached through one function,
   `open_pillow`, which turns its decompression-bomb warning and error into one
   InputError line (a header that passed step 1 never triggers them; a texture read
   without our size check may).

Reading takes the file's bytes when the caller already has them (the dataset reader
hashes them against the manifest first), so a file is read once.
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import struct
import sys
import tempfile
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import OpenEXR
from PIL import Image

from nerfgauge.core import bounded, complete, validate
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import atomic_path
from nerfgauge.core.outputs import png_kind_info

SMALL_EXR_BYTES = 1 << 20
# What an image file may hold besides its pixels (text chunks, EXIF, ICC profiles, an EXR
# preview), and where its header must end: 16 MiB, far above any camera's or renderer's
# metadata (EXIF segments are at most 64 KiB each).
IMAGE_METADATA_BYTES = 16 << 20
# An image file holds at most this many times its pixels stored raw (at the file's own
# channels and sample size), plus the metadata: PNG's deflate adds 5 bytes per 16 KiB
# block at worst, an EXR stores a chunk raw when compression would not shrink it (a
# tiled ripmap holds 4 times the pixels), and JPEG's entropy coding of noise stays under
# 4 bytes per sample. A file larger than that is not the image its header describes.
IMAGE_FILE_FACTOR = 4
_EXR_MULTIPART, _EXR_DEEP = 0x1000, 0x800  # version flags (OpenEXR file layout)
_JPEG_FRAMES = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}  # SOF0..SOF15
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # by IHDR colour type
_PILLOW_LOCK = threading.Lock()  # warnings.catch_warnings swaps the process's filters


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 transfer function on [0, 1] (values are clipped first)."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    """`linear_to_srgb` inverted (IEC 61966-2-1 decoding); encoded in [0, 1]. Same shape
    out, float32 kept, any other dtype as float64."""
    encoded = np.asarray(encoded)
    encoded = encoded if encoded.dtype in (np.float32, np.float64) else encoded.astype(np.float64)
    return np.where(encoded <= 0.04045, encoded / 12.92, ((encoded + 0.055) / 1.055) ** 2.4).astype(encoded.dtype)


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


# --- reading: header first, then the size, then the bytes --------------------------------


@dataclass(frozen=True)
class ImageHeader:
    """What an image file's header declares: its format ("PNG", "JPEG", "EXR"), size in
    pixels, channels, and the bytes its pixels take stored raw (at its own sample size)."""

    format: str
    width: int
    height: int
    channels: int
    raw_bytes: int

    def file_limit(self) -> int:
        """The most bytes a file with this header may hold (IMAGE_FILE_FACTOR, module docstring)."""
        return IMAGE_FILE_FACTOR * self.raw_bytes + IMAGE_METADATA_BYTES


class _ShortHeader(Exception):
    """The header did not parse from the bytes given: read more of the file, or, when there
    is no more, refuse it for `reason`."""

    def __init__(self, reason: str = "truncated: the file ends inside its header"):
        super().__init__(reason)
        self.reason = reason


def _unreadable(path, reason: str):
    raise InputError(f"cannot read image {path}: {reason}")


def _png_header(data: bytes, path) -> ImageHeader:
    if len(data) < 33:
        raise _ShortHeader
    length, kind, width, height, depth, colour = struct.unpack(">I4sIIBB", data[8:26])
    channels = _PNG_CHANNELS.get(colour)
    if kind != b"IHDR" or length != 13 or channels is None or depth not in (1, 2, 4, 8, 16):
        _unreadable(path, "its first chunk is not a valid IHDR header")
    return ImageHeader("PNG", width, height, channels, height * (1 + -(-width * channels * depth // 8)))


def _jpeg_header(data: bytes, path) -> ImageHeader:
    """The frame header (SOFn) of a JPEG, found by walking its marker segments."""
    at = 2
    while True:
        if at + 4 > len(data):
            raise _ShortHeader
        if data[at] != 0xFF:
            _unreadable(path, f"JPEG marker expected at byte {at}")
        marker = data[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # segments without a length
            at += 2
            continue
        if marker in (0xD9, 0xDA):
            _unreadable(path, "JPEG has no frame header before its scan")
        length = int.from_bytes(data[at + 2:at + 4], "big")
        if length < 2:
            _unreadable(path, f"JPEG segment at byte {at} has length {length}")
        if marker in _JPEG_FRAMES:
            if at + 10 > len(data):
                raise _ShortHeader
            precision, height, width, channels = struct.unpack(">BHHB", data[at + 4:at + 10])
            return ImageHeader("JPEG", width, height, channels, width * height * channels * (2 if precision > 8 else 1))
        at += 2 + length


def _exr_header(data: bytes, path) -> ImageHeader:
    """The header of a single-part EXR (scanlines or tiles), read by nerfgauge.core.complete's parser."""
    try:
        attributes, flags, _ = complete.exr_header(io.BytesIO(data), len(data), path, refuse=_exr_short)
    except _ShortHeader as short:
        if len(data) >= complete.EXR_HEADER_LIMIT:  # as far as the parser reads: no more to try
            _unreadable(path, f"{short.reason} (EXR headers longer than {complete.EXR_HEADER_LIMIT >> 20} MiB "
                              "are not read)")
        raise
    if flags & (_EXR_MULTIPART | _EXR_DEEP):
        _unreadable(path, "multi-part and deep EXR files are not read (one part of scanlines or tiles is)")
    width, height = complete.exr_data_window(attributes, path, refuse=_unreadable)
    channels = max(len(complete.exr_channel_names(attributes)), 1)
    return ImageHeader("EXR", width, height, channels, max(width, 0) * max(height, 0) * channels * 4)  # float32 at most


def _exr_short(path, reason: str):
    """complete.exr_header's refusal while reading: the header may go on past the bytes given."""
    raise _ShortHeader(reason)


_HEADERS = {"PNG": (validate.MAGIC[".png"], _png_header), "JPEG": (validate.MAGIC[".jpg"], _jpeg_header),
            "EXR": (validate.MAGIC[".exr"], _exr_header)}


def _parse_header(data: bytes, path) -> ImageHeader:
    """The header at the start of `data`; _ShortHeader when `data` ends inside it."""
    validate.image_magic(data, path)  # the signature matches the extension
    for magic, parse in _HEADERS.values():
        if data.startswith(magic):
            return parse(data, path)
    if len(data) < 8:
        raise _ShortHeader
    _unreadable(path, f"not a PNG, JPEG or EXR file (starts {data[:8].hex(' ')})")


def check_header(header: ImageHeader, path, expected_size=None) -> ImageHeader:
    """Refuse a header whose size is above MAX_IMAGE_SIDE a side or MAX_DECODED_BYTES
    decoded, or (expected_size: Intrinsics or (width, height)) not the expected one."""
    validate.image_size(header.width, header.height, path)
    validate.decoded_size(header.width, header.height, header.channels, path)
    if expected_size is not None:
        validate.header_matches(header.width, header.height, expected_size, path)
    return header


def header_of_bytes(data: bytes, path, expected_size=None) -> ImageHeader:
    """The checked header of an image whose bytes are in `data`."""
    try:
        return check_header(_parse_header(data, path), path, expected_size)
    except _ShortHeader as short:
        _unreadable(path, f"{short.reason} ({len(data)} bytes)")


def _header_of_file(handle, size: int, path) -> ImageHeader:
    """The header of an open image file, reading 4 KiB (a PNG's header is 33 bytes, ours EXR's
    about 400), then 4 times more while the header goes on, up to IMAGE_METADATA_BYTES."""
    budget = 1 << 12
    while True:
        handle.seek(0)
        data = handle.read(min(budget, IMAGE_METADATA_BYTES))
        try:
            return _parse_header(data, path)
        except _ShortHeader as short:
            if len(data) == size:
                _unreadable(path, f"{short.reason} ({size} bytes)")
            if budget >= IMAGE_METADATA_BYTES:
                _unreadable(path, f"no image header within its first {IMAGE_METADATA_BYTES >> 20} MiB")
            budget *= 4


def image_header(path, expected_size=None) -> ImageHeader:
    """The checked header of the image file at `path`; nothing past the header is read."""
    with bounded.open_regular(path) as (handle, size):
        return check_header(_header_of_file(handle, size, path), path, expected_size)


def file_limit(path, expected_size=None):
    """A limit for bounded.read_bytes: reads and checks the open file's header, then
    returns the most bytes that header's pixels can take (ImageHeader.file_limit)."""
    def limit(handle, size: int) -> int:
        header = check_header(_header_of_file(handle, size, path), path, expected_size)
        if size > header.file_limit():
            raise InputError(f"{path}: the file is {bounded.size_text(size)}, more than a {header.width}x"
                             f"{header.height} {header.format} can hold (at most {bounded.size_text(header.file_limit())}: "
                             f"{IMAGE_FILE_FACTOR} times its pixels stored raw, plus {IMAGE_METADATA_BYTES >> 20} MiB)")
        return header.file_limit()
    return limit


def read_image_bytes(path, expected_size=None) -> bytes:
    """The bytes of an image file, read after its header and its size have been checked
    (the module docstring's steps 1 and 2)."""
    return bounded.read_bytes(path, file_limit(path, expected_size), "image file")


def open_pillow(data: bytes, path, formats=None) -> Image.Image:
    """Pillow's Image.open on `data` (lazily: the header only), the one place the project
    calls it. Pillow's DecompressionBombWarning (above 89 million pixels; printed on
    stderr as two lines) and DecompressionBombError (twice that) become one InputError, as
    does any other failure to open. formats: Pillow format names allowed (None: any)."""
    try:
        with _PILLOW_LOCK, warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            return Image.open(io.BytesIO(data), formats=None if formats is None else list(formats))
    except (Image.DecompressionBombWarning, Image.DecompressionBombError) as error:
        raise InputError(f"{path}: {str(error).splitlines()[0]} (refused as a decompression bomb)") from None
    except Image.UnidentifiedImageError:  # its text names the BytesIO object, not the file
        _unreadable(path, f"not a readable {' or '.join(formats) if formats else 'image'} file")
    except (OSError, ValueError, SyntaxError, EOFError, struct.error) as error:
        _unreadable(path, str(error).splitlines()[0] if str(error) else type(error).__name__)


def _decoded(path, decode):
    """decode() with Pillow's errors while decoding pixels turned into one InputError line."""
    try:
        return decode()
    except InputError:
        raise
    except (OSError, ValueError, SyntaxError, EOFError, struct.error) as error:
        _unreadable(path, str(error).splitlines()[0] if str(error) else type(error).__name__)


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
    Intrinsics or (width, height) the header must state. The header is checked before any
    pixel is decoded (module docstring)."""
    data = read_image_bytes(path, expected_size) if data is None else data
    header_of_bytes(data, path, expected_size)
    if not _png_chunks_complete(data):  # Pillow decodes a file cut inside or before its end chunk
        raise InputError(f"cannot read image {path}: truncated (its chunks do not end with the empty end chunk)")

    def decode():
        with open_pillow(data, path, ("PNG",)) as image:
            if image.mode in ("P", "PA"):
                image = image.convert("RGBA" if "transparency" in image.info or image.mode == "PA" else "RGB")
            elif image.mode == "1":
                image = image.convert("L")
            return np.asarray(image)

    array = _decoded(path, decode)
    if array.dtype == np.uint16 or array.dtype == np.int32:  # 16-bit PNG ("I;16" or "I")
        return array.astype(np.float32) / 65535.0
    return array.astype(np.float32) / 255.0


def read_jpeg(path, data: Optional[bytes] = None, expected_size=None) -> np.ndarray:
    """A JPEG as sRGB float32 [H, W, 3] in [0, 1]; data, expected_size: as for read_png."""
    data = read_image_bytes(path, expected_size) if data is None else data
    header_of_bytes(data, path, expected_size)

    def decode():
        with open_pillow(data, path, ("JPEG",)) as image:
            return np.asarray(image.convert("RGB"))

    return _decoded(path, decode).astype(np.float32) / 255.0


def read_colour(path, data: Optional[bytes] = None, expected_size=None) -> np.ndarray:
    """A PNG (as stored, read_png) or, by its extension, a JPEG (read_jpeg)."""
    reader = read_jpeg if Path(path).suffix.lower() in (".jpg", ".jpeg") else read_png
    return reader(path, data, expected_size)


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
            try:
                exr.write(str(tmp))
            except RuntimeError as error:  # OpenEXR's IO errors carry the OS's text, not its errno
                raise _os_error_from_openexr(error, path) from None


def _os_error_from_openexr(error: RuntimeError, path) -> OSError:
    """The OSError an OpenEXR write failure stands for (its message names the OS's
    strerror, e.g. "No space left on device"), so that the CLI reports a full disk as one."""
    message = str(error)
    for number in sorted(errno.errorcode):
        if os.strerror(number) in message:
            return OSError(number, os.strerror(number), str(path))
    return OSError(errno.EIO, f"OpenEXR could not write it: {message}", str(path))


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
    data = read_image_bytes(path, expected_size) if data is None else data
    header_of_bytes(data, path, expected_size)
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


def read_exr_single(path, data: Optional[bytes] = None, expected_size=None, name: Optional[str] = None) -> np.ndarray:
    """The one channel of a single-channel EXR (depth files); `name`: the channel it must
    be called (a format that names it, as nerfgauge's ground truth names its depth "Z"),
    or any. Returns [H, W] float32."""
    channels, _ = read_exr(path, data, expected_size)
    if len(channels) != 1:
        raise InputError(f"{path} should hold one channel, has {sorted(channels)}")
    if name is not None and next(iter(channels)) != name:
        raise InputError(f"{path} should hold the channel {name!r}, has {next(iter(channels))!r}")
    (values,) = channels.values()
    if values.ndim != 2:  # OpenEXR groups R, G, B into one [H, W, 3] "RGB" entry
        raise InputError(f"{path} should hold one channel, has {values.shape[-1]} grouped as {next(iter(channels))!r}")
    return values
