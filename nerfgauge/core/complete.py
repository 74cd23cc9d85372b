"""Is a file just written complete? Checked on the temporary before it is renamed into place.

A library that writes a file itself does not always report a failed write: OpenEXR's final
flush on a full disk fails silently, and an empty or truncated EXR would be fsynced and
renamed into place (a 0-byte `r_000_depth.exr` that looks finished). So `files.atomic_path`
checks what is on disk before the rename:

- bytes written by us: the size on disk equals the size meant (`check_size`);
- anything else: not empty, and when it is a PNG or an EXR (recognised by its signature),
  its structure read back from the file (`check_complete`):
  - PNG: every chunk's length fits, and the file ends with the IEND chunk;
  - EXR (single-part scanline, what nerfgauge writes): the header parses, and the chunk
    offset table and every chunk it points to lie inside the file, the last ending at its
    end. Tiled and multi-part files get the header check only.
- `check_image_header` compares the header's size (and EXR channel names) with what the
  writer meant, read back from the temporary.

Only the header, the offset table and each chunk's 8-byte leader are read (a few KiB, even
for large files). A failed check raises `IncompleteWrite` (an InputError: one line, exit 2)
naming the file and the reason.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

from nerfgauge.core.errors import InputError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
EXR_MAGIC = b"\x76\x2f\x31\x01"
EXR_HEADER_LIMIT = 1 << 20  # our headers are < 1 KiB; a longer one is not ours to judge
# scanlines per chunk by compression (OpenEXR's table: NO, RLE, ZIPS, ZIP, PIZ, PXR24, B44,
# B44A, DWAA, DWAB, HTJ2K256, HTJ2K32)
EXR_LINES_PER_CHUNK = {0: 1, 1: 1, 2: 1, 3: 16, 4: 32, 5: 16, 6: 32, 7: 32, 8: 32, 9: 256, 10: 256, 11: 32}


class IncompleteWrite(InputError):
    """A write that did not complete (full disk, quota, a library that hid the error)."""


def _refuse(path, reason: str):
    raise IncompleteWrite(f"{path}: the write did not complete ({reason}); nothing was written there "
                          "(is the disk full?)")


def check_size(path, expected: int, shown=None) -> None:
    """The file at `path` holds exactly `expected` bytes. `shown`: the path named in the error."""
    size = os.stat(path).st_size
    if size != expected:
        _refuse(shown or path, f"{size} of {expected} bytes on disk")


def check_complete(path, shown=None) -> None:
    """The file at `path` is not empty, and a PNG or EXR is structurally whole (module docstring)."""
    shown = shown or path
    with open(path, "rb") as handle:
        size = os.fstat(handle.fileno()).st_size
        if size == 0:
            _refuse(shown, "the file is empty")
        head = handle.read(8)
        if len(head) < 8 and (PNG_SIGNATURE.startswith(head) or EXR_MAGIC.startswith(head[:4])):
            _refuse(shown, f"the file ends after {len(head)} bytes, inside an image signature")
        if head == PNG_SIGNATURE:
            _png_complete(handle, size, shown)
        elif head[:4] == EXR_MAGIC:
            _exr_complete(handle, size, shown)


def _png_complete(handle, size: int, shown) -> None:
    at = 8
    while True:
        handle.seek(at)
        leader = handle.read(8)
        if len(leader) < 8:
            _refuse(shown, f"PNG ends inside a chunk header at byte {at} of {size}, before IEND")
        length, kind = struct.unpack(">I4s", leader)
        end = at + 12 + length  # length, type, data, CRC
        if end > size:
            _refuse(shown, f"PNG chunk {kind!r} at byte {at} runs past the end of the file ({size} bytes)")
        if kind == b"IEND":
            if end != size:
                _refuse(shown, f"PNG has {size - end} bytes after IEND")
            return
        at = end


def exr_header(handle, size: int, shown, refuse=_refuse) -> tuple[dict, int, int]:
    """({attribute name: (type, raw bytes)}, version flags, offset of the first byte after
    the header) of an open EXR file (single-part headers). refuse(shown, reason): raises;
    a reader passes its own (the default says a write did not complete)."""
    handle.seek(0)
    data = handle.read(min(size, EXR_HEADER_LIMIT))
    if len(data) < 8 or data[:4] != EXR_MAGIC:
        refuse(shown, "EXR signature missing")
    flags = struct.unpack("<I", data[4:8])[0]
    attributes, at = {}, 8

    def cut_short(what: str) -> str:
        if len(data) >= size:  # the whole file was read: it ends inside its header
            return f"EXR file is truncated inside its header ({size} bytes): {what}"
        return f"EXR header is longer than the {EXR_HEADER_LIMIT} bytes read: {what}"

    def text():
        nonlocal at
        end = data.find(b"\0", at)
        if end < 0:
            refuse(shown, cut_short("a name has no end"))
        value, at = data[at:end], end + 1
        return value

    while True:
        name = text()
        if not name:
            return attributes, flags, at
        kind = text()
        if at + 4 > len(data):
            refuse(shown, cut_short(f"the size of attribute {name.decode(errors='replace')!r} is cut off"))
        length = struct.unpack("<i", data[at:at + 4])[0]
        at += 4
        if length < 0 or at + length > len(data):
            refuse(shown, cut_short(f"attribute {name.decode(errors='replace')!r} runs past its end"))
        attributes[name.decode(errors="replace")] = (kind.decode(errors="replace"), data[at:at + length])
        at += length


def exr_data_window(attributes: dict, shown, refuse=_refuse) -> tuple[int, int]:
    kind, raw = attributes.get("dataWindow", (None, b""))
    if kind != "box2i" or len(raw) != 16:
        refuse(shown, "EXR header has no dataWindow")
    x0, y0, x1, y1 = struct.unpack("<iiii", raw)
    return x1 - x0 + 1, y1 - y0 + 1


def exr_channel_names(attributes: dict) -> list[str]:
    kind, raw = attributes.get("channels", (None, b""))
    names, at = [], 0
    while kind == "chlist" and at < len(raw) and raw[at] != 0:
        end = raw.index(b"\0", at)
        names.append(raw[at:end].decode(errors="replace"))
        at = end + 1 + 16  # pixel type, pLinear + reserved, xSampling, ySampling
    return names


def _exr_complete(handle, size: int, shown) -> None:
    attributes, flags, at = exr_header(handle, size, shown)
    if flags & 0x1200:  # tiled (0x200) or multi-part (0x1000): the header check only
        return
    width, height = exr_data_window(attributes, shown)
    compression = attributes.get("compression", (None, b"\0"))[1][:1]
    lines = EXR_LINES_PER_CHUNK.get(compression[0] if compression else 0)
    if lines is None or width <= 0 or height <= 0:
        return
    chunks = -(-height // lines)
    table_end = at + 8 * chunks
    if table_end > size:
        _refuse(shown, f"EXR ends inside its offset table ({size} of at least {table_end} bytes)")
    handle.seek(at)
    offsets = struct.unpack(f"<{chunks}Q", handle.read(8 * chunks))
    last = 0
    for index, offset in enumerate(offsets):
        if offset < table_end or offset + 8 > size:
            _refuse(shown, f"EXR chunk {index} of {chunks} is missing (offset {offset}, file {size} bytes)")
        handle.seek(offset)
        _, packed = struct.unpack("<ii", handle.read(8))
        if packed < 0 or offset + 8 + packed > size:
            _refuse(shown, f"EXR chunk {index} of {chunks} runs past the end of the file ({size} bytes)")
        last = max(last, offset + 8 + packed)
    if last != size:
        _refuse(shown, f"EXR chunks end at byte {last}, the file at {size}")


def check_image_header(path, width: int, height: int, channels=None, shown=None) -> None:
    """The PNG or EXR at `path` states `width` x `height` (and, for EXR, `channels`, a set
    of names) in its header, read back from the file."""
    shown = shown or path
    with open(path, "rb") as handle:
        size = os.fstat(handle.fileno()).st_size
        head = handle.read(24)
        if head[:8] == PNG_SIGNATURE:
            if len(head) < 24 or head[12:16] != b"IHDR":
                _refuse(shown, "PNG has no IHDR header")
            found = struct.unpack(">II", head[16:24])
            if found != (width, height):
                _refuse(shown, f"PNG header states {found[0]}x{found[1]}, {width}x{height} were written")
        elif head[:4] == EXR_MAGIC:
            attributes, _, _ = exr_header(handle, size, shown)
            found = exr_data_window(attributes, shown)
            if found != (width, height):
                _refuse(shown, f"EXR dataWindow states {found[0]}x{found[1]}, {width}x{height} were written")
            if channels is not None and set(exr_channel_names(attributes)) != set(channels):
                _refuse(shown, f"EXR header lists channels {sorted(exr_channel_names(attributes))}, "
                               f"{sorted(channels)} were written")
        else:
            _refuse(shown, f"{Path(path).name} is neither PNG nor EXR")
