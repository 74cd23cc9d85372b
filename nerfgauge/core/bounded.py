"""Bounded readers: every JSON, TOML, .npy and gzip file nerfgauge reads goes through here.

Python's parsers and numpy trust what a file says about itself: json and tomllib recurse
once per nesting level (a file of 100,000 "[" ends in a RecursionError traceback), and
numpy allocates whatever shape a .npy header declares, gzip inflates whatever it is
given. Each reader here refuses, with one InputError line naming the file and the limit,
before the expensive step:

- size: the file (or the bytes already read) is at most a named limit, checked on the
  size the file system gives for the opened descriptor (fstat) before anything is read,
  so a huge file is never read into memory; the limit may be a function of the opened
  file (a manifest's record of its size, or a cap an image's header implies), and only a
  regular file is opened (a FIFO would block, a device never end);
- nesting: the brackets of a JSON or TOML text (outside strings and comments) nest at
  most MAX_NESTING deep, counted by a linear scan before the parser runs; the parsed
  TOML (whose dotted keys nest without brackets) is measured again after parsing;
- .npy: the header is parsed first, the dtype must be a plain number type and the shape
  small enough (at most `max_elements` values), and the file must hold exactly what the
  header says, before any value is read;
- gzip: inflated in blocks and refused as soon as the output passes the limit, so a
  small file that inflates to gigabytes is never held whole.

Decoding errors stay what they were (json.JSONDecodeError, tomllib.TOMLDecodeError,
UnicodeDecodeError), so each caller keeps its own message for a malformed file.
"""

from __future__ import annotations

import contextlib
import gzip
import io
import json
import os
import re
import stat
import tomllib
import zlib
from pathlib import Path

import numpy as np

from nerfgauge.core.errors import InputError, input_error_from_os

# Ten times deeper than any document nerfgauge reads or writes (the deepest, a scene file
# or a metrics.json, nests 5 levels), and far below the ~1000 levels at which Python's
# json and tomllib raise RecursionError (they recurse once per level).
MAX_NESTING = 64
# The largest JSON nerfgauge writes is transforms.json: ~450 bytes a frame, 4.5 MB for
# 10,000 frames. 64 MiB is 14 times that; it parses into about 1 GB of Python objects,
# which a machine that can train on such a dataset holds.
MAX_JSON_BYTES = 64 << 20
# TOML files are hand-written (scene files, suites, thresholds): a few kB. tomllib is pure
# Python (about 2 MB/s here), so 4 MiB still parses in about two seconds.
MAX_TOML_BYTES = 4 << 20
# A .npy or .npy.gz prediction holds one [H, W] or [H, W, C] plane of at most
# MAX_IMAGE_SIDE pixels a side (nerfgauge.core.validate), C <= 4, float64: 2 GiB. Readers
# that know the frame's size pass a tighter bound (the expected [H, W, C] values).
MAX_NPY_ELEMENTS = 8192 * 8192 * 4
# A .npy header is at most 64 KiB in format 1.0 (uint16 length); format 2+ allows 4 GiB,
# which no array we accept needs.
MAX_NPY_HEADER = 1 << 16
_INFLATE_BLOCK = 1 << 20

_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*(?:"|\Z)', re.S)
# TOML: multi-line strings first, then one-line basic and literal strings, then comments.
_TOML_SKIP = re.compile(r'"""[\s\S]*?(?:"""|\Z)|\'\'\'[\s\S]*?(?:\'\'\'|\Z)'
                        r'|"[^"\\\n]*(?:\\.[^"\\\n]*)*(?:"|$)|\'[^\'\n]*(?:\'|$)|#[^\n]*', re.M)
# What precedes each "=": a key, starting after , { [ or at a line start. The start is anchored:
# unanchored, a 200,000-bracket "]]]...]" line was scanned again from each of its characters.
_TOML_KEY = re.compile(r"(?:^|(?<=[,{\[]))[^,{\[\n=]*=", re.M)
_TOML_HEADER = re.compile(r"^[ \t]*\[\[?([^\]\n]*)\]", re.M)
_OPEN = np.frombuffer(b"[{", np.uint8)
_CLOSE = np.frombuffer(b"]}", np.uint8)


def size_text(count: int) -> str:
    """A byte count for messages: "2 GiB", "16 MiB", "512 bytes"."""
    for unit, shift in (("GiB", 30), ("MiB", 20), ("KiB", 10)):
        if count >= 1 << shift:
            return f"{count / (1 << shift):.3g} {unit}"
    return f"{count} bytes"


def check_size(count: int, limit: int, source, what: str) -> None:
    if count > limit:
        raise InputError(f"{source}: {what} is {size_text(count)}, above the limit of {size_text(limit)}")


@contextlib.contextmanager
def open_regular(path):
    """Yield (binary file, size in bytes from fstat) for `path`, refused (InputError)
    unless it is a regular file. Opened without blocking (O_NONBLOCK), so a FIFO is refused
    instead of waiting for a writer; a device or socket is refused too (/dev/zero would
    never end)."""
    path = Path(path)
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise InputError(f"missing file: {path}") from None
    except OSError as error:
        raise input_error_from_os(error) from None
    with os.fdopen(descriptor, "rb") as handle:
        status = os.fstat(descriptor)
        if stat.S_ISDIR(status.st_mode):
            raise InputError(f"{path} is a folder, expected a file")
        if not stat.S_ISREG(status.st_mode):
            raise InputError(f"{path} is not a regular file (a device, FIFO or socket); refused")
        yield handle, status.st_size


def read_bytes(path, limit, what: str = "file") -> bytes:
    """The bytes of `path`, refused (InputError) when it is larger than `limit`, checked
    on the opened file's size (fstat) before reading, and on what was read (a file may
    grow meanwhile). limit: bytes, or limit(handle, size) -> bytes, called with the opened
    file and its size before anything else is read: it may compare the size with a record
    (a manifest) or read a header to derive the cap, and raise InputError itself."""
    with open_regular(path) as (handle, size):
        try:
            cap = limit(handle, size) if callable(limit) else limit
            check_size(size, cap, path, what)
            handle.seek(0)
            data = handle.read(min(size, cap) + 1)  # one byte more shows a file that grew past the cap
        except OSError as error:
            raise input_error_from_os(error) from None
    check_size(len(data), cap, path, what)
    return data


def nesting_depth(text: str, skip: re.Pattern | None = _JSON_STRING) -> int:
    """The deepest nesting of [ and { in `text` outside what `skip` matches (strings,
    comments). Linear time; numpy counts the brackets block by block."""
    data = np.frombuffer((skip.sub("", text) if skip else text).encode("utf-8", "surrogatepass"), np.uint8)
    depth = deepest = 0
    for start in range(0, len(data), _INFLATE_BLOCK):
        block = data[start:start + _INFLATE_BLOCK]
        step = np.isin(block, _OPEN).astype(np.int64) - np.isin(block, _CLOSE)
        if not step.any():
            continue
        running = np.cumsum(step) + depth
        deepest, depth = max(deepest, int(running.max())), int(running[-1])
    return deepest


def _value_depth(value) -> int:
    """The nesting depth of parsed lists and dicts (1 for a flat one), without recursion."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, dict):
            children = item.values()
        elif isinstance(item, list):
            children = item
        else:
            continue
        deepest = max(deepest, depth)
        if deepest > MAX_NESTING:
            break
        stack.extend((child, depth + 1) for child in children if isinstance(child, (dict, list)))
    return deepest


def _refuse_depth(depth: int, source, kind: str) -> None:
    if depth > MAX_NESTING:
        raise InputError(f"{source}: {kind} nests {depth} levels deep; at most {MAX_NESTING} are read")


def _text(data, source, limit: int, kind: str) -> str:
    check_size(len(data), limit, source, f"the {kind} document")
    return data.decode("utf-8") if isinstance(data, (bytes, bytearray, memoryview)) else data


def loads_json(data, source, *, limit: int = MAX_JSON_BYTES, **options):
    """json.loads(data, **options) for a text or bytes from `source`, after the size and
    nesting checks. Malformed JSON raises json.JSONDecodeError as json.loads does."""
    text = _text(data, source, limit, "JSON")
    _refuse_depth(nesting_depth(text), source, "JSON")
    try:
        return json.loads(text, **options)
    except RecursionError:  # only when called from deep in the stack already
        raise InputError(f"{source}: JSON nests too deeply to parse") from None


def toml_key_depth(bare: str) -> int:
    """The most parts of a dotted key (`a.b.c = 1`, `[a.b.c]`: 3) in TOML text whose
    strings and comments are already removed (quoted parts count by their dots)."""
    keys = _TOML_KEY.findall(bare) + _TOML_HEADER.findall(bare)
    return max((key.count(".") + 1 for key in keys), default=0)


def loads_toml(data, source, *, limit: int = MAX_TOML_BYTES) -> dict:
    """tomllib.loads for a text or bytes from `source`, after the size and nesting checks
    (before parsing, on brackets and on dotted keys: tomllib keeps every prefix of a dotted
    key, so 200,000 parts took 20 GB; after, on the parsed tables)."""
    text = _text(data, source, limit, "TOML")
    bare = _TOML_SKIP.sub("", text)
    _refuse_depth(max(nesting_depth(bare, None), toml_key_depth(bare)), source, "TOML")
    try:
        document = tomllib.loads(text)
    except RecursionError:
        raise InputError(f"{source}: TOML nests too deeply to parse") from None
    _refuse_depth(_value_depth(document), source, "TOML")
    return document


def read_toml(path, what: str = "TOML file") -> tuple[dict, bytes]:
    """(document, bytes) of a TOML file, bounded as loads_toml; InputError if unreadable."""
    data = read_bytes(path, MAX_TOML_BYTES, what)
    return loads_toml(data, path), data


# --- numpy arrays and gzip -----------------------------------------------------------------


def inflate_gzip(path, limit: int) -> bytes:
    """The inflated content of a gzip file, refused as soon as it passes `limit` bytes."""
    out, total = [], 0
    try:
        with open_regular(path) as (raw, _), gzip.GzipFile(fileobj=raw, mode="rb") as handle:
            while block := handle.read(_INFLATE_BLOCK):
                total += len(block)
                if total > limit:
                    raise InputError(f"{path}: inflates to more than {size_text(limit)}, the most this file can hold "
                                     "(refused while inflating)")
                out.append(block)
    except (OSError, EOFError, zlib.error) as error:
        raise InputError(f"{path}: not a readable gzip file ({error})") from None
    return b"".join(out)


def npy_bytes_limit(max_elements: int) -> int:
    """The most bytes a .npy of at most `max_elements` float64 values takes (with its header)."""
    return MAX_NPY_HEADER + 8 * max_elements


def read_npy(source, data: bytes | None = None, *, max_elements: int = MAX_NPY_ELEMENTS) -> np.ndarray:
    """A .npy array from `data` (or the file `source`), checked before any value is read:
    format 1.0-3.0, a plain numeric dtype (no objects, so no pickle), at most
    `max_elements` values and 3 dimensions, and exactly the bytes the header declares."""
    if data is None:
        data = read_bytes(source, npy_bytes_limit(max_elements), ".npy file")
    stream = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(stream)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(stream)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(stream, max_header_size=MAX_NPY_HEADER)
        else:
            raise ValueError(f"unknown .npy format version {version}")
    except (ValueError, EOFError, SyntaxError, TypeError) as error:
        raise InputError(f"cannot read {source}: not a .npy file ({str(error).splitlines()[0] if str(error) else error})") from None
    if dtype.hasobject or dtype.kind not in "biuf" or dtype.subdtype is not None or dtype.names is not None:
        raise InputError(f"cannot read {source}: dtype {dtype} is not a plain number type")
    if len(shape) > 3 or any(n < 0 for n in shape):
        raise InputError(f"cannot read {source}: shape {shape} (at most 3 dimensions are read)")
    count = 1
    for n in shape:
        count *= int(n)
    if count > max_elements:
        raise InputError(f"cannot read {source}: header declares shape {shape}, {count} values; "
                         f"at most {max_elements} are read")
    body = len(data) - stream.tell()
    if body != count * dtype.itemsize:
        raise InputError(f"cannot read {source}: header declares shape {shape} of {dtype} "
                         f"({count * dtype.itemsize} bytes) but the file holds {body}")
    values = np.frombuffer(data, dtype, count, offset=stream.tell())
    return values.reshape(shape, order="F" if fortran else "C")
