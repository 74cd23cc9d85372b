"""The ground truth's LPIPS features, computed once and reused by every method and seed.

LPIPS passes both images of a pair through AlexNet or VGG16; the ground truth's pass is the
same for every method and seed scored against it, and at 800 x 800 one VGG16 pass costs
seconds. `features_source(model)` gives eval.lpips.LpipsBatch (and lpips_scores) the
ground truth's unit-normalised features from a cache on disk, computing and storing them
on a miss. The head then gets the very tensors a fresh pass gives (values, shape and
strides), so an LPIPS value is the same bit for bit with the cache, without it, cold or
warm (tests/test_lpips_cache.py).

What an entry holds: the features of one batch of ground-truth frames, as LpipsBatch
groups them (a batch of about BATCH_PIXELS pixels: which frames depends on their count
and size only, so every method scoring a split meets the same batches). A batch and not a
frame because torch's CPU convolutions are not batch-invariant: a frame's features alone
differ from its features inside a batch by up to 5e-5 (measured, AlexNet at 128 px), and
passing the ground truth one frame at a time costs 4 to 15 times the batched pass on small
frames.

The key (sha256) covers what the features depend on: FEATURE_LAYOUT, the network, the
sha256 of its weights (names, shapes, bytes), the torch version (its kernels), the input
tensor's shape and strides, and the input's bytes: the ground truth after compositing,
the protocol's mapping (background, uint8 round trip) and LPIPS' [-1, 1] scaling, exactly
as the network sees it.

An entry is data, never trusted: `<key>.lpips` is a fixed header (MAGIC, a 4-byte length,
bounded JSON naming the key, layout, shapes, memory order and the body's crc32) and the
float32 body, read with numpy (no pickle), through O_NOFOLLOW, refused unless the file's
size is the one the expected shapes imply and its key, shapes, order and digest are
right and every value lies in [0, 1] (unit-normalised ReLU outputs; NaN fails). A refused
entry (corrupt, truncated, foreign, a symbolic link, a FIFO) is recomputed and replaced,
with a note on stderr; a cache is never a reason for a score to fail.

Nothing is written through a link (core.owned's rule for folders of ours): a link (or
any other non-file) at an entry's name is removed as itself, its target untouched
(core.owned.remove_file), before the fresh entry is written through core.files
.atomic_path (a temporary per process, then a rename, so two processes storing one entry
at once both leave a whole file; it refuses a link on the way or as the target: a link
planted again in between costs that entry's store, with a note). The folder is ours
(core.folders.adopt_shared_folder: our marker, never inside a dataset, never a link
itself); eviction deletes regular files of our names only.

Where and how much (environment, so that evaluate, run, suite and their Dask workers all
see it; a bad value is one InputError line, exit 2):
    NERFGAUGE_LPIPS_CACHE     unset or empty: $XDG_CACHE_HOME/nerfgauge/lpips-features
                              (~/.cache/nerfgauge/...); "off": no cache; else a folder.
    NERFGAUGE_LPIPS_CACHE_GB  the cap in GiB, CAP_GB's range (default DEFAULT_CAP_GB);
                              past it the least recently used entries go (a hit
                              refreshes its mtime).
"""

from __future__ import annotations

import argparse
import errno
import hashlib
import json
import math
import os
import re
import stat
import struct
import sys
import threading
import time
import weakref
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from nerfgauge.core import arguments, bounded, complete, folders, owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import atomic_path
from nerfgauge.eval.lpips import ALEX_POOL_BEFORE, VGG_POOL_BEFORE, VGG_TAPS, cache_dir

FOLDER_ENV = "NERFGAUGE_LPIPS_CACHE"
CAP_ENV = "NERFGAUGE_LPIPS_CACHE_GB"
OFF = "off"
FOLDER_NAME = "lpips-features"
# Holds the issue's case, 20 frames of 800 x 800 under NerfBaselines' protocol (VGG 312 MB
# and Alex 26 MB a frame: 6.8 GB), with room to spare.
DEFAULT_CAP_GB = 8.0
CAP_GB = arguments.bounded(float, 0, 1e6, above=True)  # GiB; 1e6 GiB (a pebibyte) is beyond any disk here
FEATURE_LAYOUT = 1  # what an entry's body means (unit features, float32, in memory order); bump on change
MAGIC = b"nerfgauge lpips features\n"
MAX_HEADER_BYTES = 1 << 16
BODY_ALIGNMENT = 64  # bytes: the body starts at a multiple of it, so read tensors are aligned as fresh ones
SUFFIX = ".lpips"
ENTRY_NAME = re.compile(r"[0-9a-f]{64}\.lpips")
STALE_TEMPORARY_SECONDS = 24 * 3600  # a killed writer's temporary (`.<entry>.tmp<pid>`) older than this goes
_TEMPORARY_NAME = re.compile(r"\.[0-9a-f]{64}\.lpips\.tmp\d+")
_write_lock = threading.Lock()  # atomic_path's temporary is per process: one writer per process at a time
_weights_digests: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


@dataclass(frozen=True)
class Settings:
    folder: Optional[Path]  # None: no cache
    cap_bytes: int


def settings(environ=None) -> Settings:
    """The cache's folder and cap from the environment (module docstring); InputError on a
    bad value."""
    environ = os.environ if environ is None else environ
    given = environ.get(CAP_ENV, "").strip()
    try:
        cap_gb = CAP_GB(given) if given else DEFAULT_CAP_GB
    except argparse.ArgumentTypeError as error:
        raise InputError(f"{CAP_ENV}={given!r}: the LPIPS cache's size cap in GiB: {error} "
                         f"(default {DEFAULT_CAP_GB:g})") from None
    folder = environ.get(FOLDER_ENV, "")
    if folder.strip().lower() == OFF:
        return Settings(None, int(cap_gb * 2**30))
    arguments.encodable_path(folder, FOLDER_ENV)
    return Settings(Path(folder).expanduser() if folder.strip() else cache_dir() / FOLDER_NAME, int(cap_gb * 2**30))


def _note(message: str) -> None:
    print(f"nerfgauge: note: {message}", file=sys.stderr)


# --- keys ---------------------------------------------------------------------------------------


def weights_digest(model) -> str:
    """sha256 of the model's weights: every parameter's and buffer's name, dtype, shape and bytes."""
    digest = _weights_digests.get(model)
    if digest is None:
        hasher = hashlib.sha256()
        named = [*model.named_parameters(), *model.named_buffers()]  # buffers: the scaling layer's constants
        for name, tensor in sorted(named, key=lambda item: item[0]):
            array = tensor.detach().cpu().contiguous().numpy()
            hasher.update(f"{name} {array.dtype.str} {list(array.shape)}\n".encode())
            hasher.update(memoryview(array).cast("B"))
        digest = _weights_digests[model] = hasher.hexdigest()
    return digest


def entry_key(model, images) -> str:
    """The key of the features of `images` ([N, 3, H, W] float32 on [-1, 1], the tensor the
    network is given) under `model`: sha256 of everything they depend on (module docstring)."""
    import torch  # torch: only when LPIPS is scored

    context = {"layout": FEATURE_LAYOUT, "net": model.net, "weights": weights_digest(model),
               "torch": torch.__version__, "shape": list(images.shape), "stride": list(images.stride()),
               "dtype": str(images.dtype)}
    hasher = hashlib.sha256(MAGIC + json.dumps(context, sort_keys=True).encode() + b"\0")
    hasher.update(memoryview(images.detach().contiguous().numpy()).cast("B"))
    return hasher.hexdigest()


def expected_shapes(model, shape) -> list[tuple]:
    """The shapes of model.unit_features for an input of `shape` ([N, 3, H, W]): from its
    convolutions' own kernel, stride and padding and the max-pools eval.lpips puts between
    them (tests/test_lpips_cache.py holds them to a real pass). Not a pass on torch's meta
    device: that imports torch._dynamo, 5 s."""
    n, _, height, width = shape
    sides, shapes = [height, width], []
    for i, conv in enumerate(model.convs):
        if model.net == "alex" and i in ALEX_POOL_BEFORE:
            sides = [(side - 3) // 2 + 1 for side in sides]  # 3x3, stride 2
        if model.net == "vgg" and i in VGG_POOL_BEFORE:
            sides = [side // 2 for side in sides]  # 2x2, stride 2
        sides = [(side + 2 * pad - k) // stride + 1
                 for side, k, stride, pad in zip(sides, conv.kernel_size, conv.stride, conv.padding)]
        if model.net == "alex" or i in VGG_TAPS:
            shapes.append((n, conv.out_channels, *sides))
    return shapes


# --- one entry on disk ----------------------------------------------------------------------------


def _memory_order(tensor) -> list[int]:
    """Its dimensions from the slowest-varying to the fastest in memory (ties by index)."""
    return sorted(range(tensor.dim()), key=lambda d: (-tensor.stride(d), d))


def _canonical(tensor, order):
    """`tensor` as a view of one dense buffer in `order`: what a read entry gives back."""
    dense = tensor.permute(order).contiguous()
    return dense.view(-1).view(dense.shape).permute([order.index(d) for d in range(len(order))])


def _from_buffer(buffer, shape, order):
    import torch  # torch: only when LPIPS is scored

    stored = [shape[d] for d in order]
    return torch.from_numpy(buffer).view(stored).permute([order.index(d) for d in range(len(order))])


def write_entry(path: Path, key: str, features: list) -> int:
    """Store `features` (canonical tensors) at `path` atomically; returns its size."""
    orders = [_memory_order(f) for f in features]
    bodies = [np.ascontiguousarray(f.permute(o).numpy()) for f, o in zip(features, orders)]
    checksum = 0
    for body in bodies:
        checksum = zlib.crc32(memoryview(body).cast("B"), checksum)
    header = json.dumps({"key": key, "layout": FEATURE_LAYOUT, "dtype": "<f4",
                         "shapes": [list(f.shape) for f in features], "orders": orders,
                         "body_crc32": checksum}).encode()
    header += b" " * (-(len(MAGIC) + 4 + len(header)) % BODY_ALIGNMENT)  # JSON allows trailing blanks
    size = len(MAGIC) + 4 + len(header) + sum(body.nbytes for body in bodies)
    with _write_lock, atomic_path(path, verify=lambda tmp, shown: complete.check_size(tmp, size, shown)) as tmp:
        with open(tmp, "wb") as handle:
            handle.write(MAGIC + struct.pack("<I", len(header)) + header)
            for body in bodies:
                handle.write(memoryview(body).cast("B"))
    return size


class BadEntry(Exception):
    """An entry that is not the one asked for: foreign, corrupt, truncated."""


def _read_regular(path: Path, limit: int):
    """The file's bytes (a bytearray) or None when absent; never through a link
    (O_NOFOLLOW), never a FIFO or device, never more than `limit` bytes. Refreshes its
    mtime: the cache's eviction order."""
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        return None
    except OSError as error:
        if error.errno == errno.ELOOP:
            raise BadEntry("it is a symbolic link") from None
        raise
    with os.fdopen(descriptor, "rb") as handle:
        status = os.fstat(descriptor)
        if not stat.S_ISREG(status.st_mode):
            raise BadEntry("not a regular file")
        if status.st_size > limit:
            raise BadEntry(f"{status.st_size} bytes, more than the {limit} its shapes allow")
        data = np.empty(status.st_size, np.uint8)  # not bytearray(n): zero-filling 300 MB first costs as much as reading it
        if handle.readinto(memoryview(data)) != status.st_size:
            raise BadEntry("shorter than its size")
        try:
            os.utime(descriptor)  # least recently used: a hit is a use
        except PermissionError:  # a cache shared read-only: used, never reordered
            pass
    return data


def read_entry(path: Path, key: str, shapes: list) -> Optional[list]:
    """The features stored at `path` for `key` with these shapes (canonical tensors), None
    when there is no entry; BadEntry (saying why) when the file is not that entry."""
    import torch  # torch: only when LPIPS is scored

    body_bytes = 4 * sum(math.prod(shape) for shape in shapes)
    data = _read_regular(path, len(MAGIC) + 4 + MAX_HEADER_BYTES + body_bytes)
    if data is None:
        return None
    if len(data) < len(MAGIC) + 4 or data[:len(MAGIC)].tobytes() != MAGIC:
        raise BadEntry("not an LPIPS feature file")
    (length,) = struct.unpack_from("<I", data, len(MAGIC))
    start = len(MAGIC) + 4 + length
    if length > MAX_HEADER_BYTES or len(data) != start + body_bytes:
        raise BadEntry(f"{len(data)} bytes, not the {len(MAGIC) + 4 + length + body_bytes} of its shapes")
    try:
        header = bounded.loads_json(data[len(MAGIC) + 4:start].tobytes(), path, limit=MAX_HEADER_BYTES)
    except (InputError, ValueError) as error:
        raise BadEntry(f"unreadable header ({str(error).splitlines()[0]})") from None
    if not isinstance(header, dict) or header.get("key") != key or header.get("layout") != FEATURE_LAYOUT \
            or header.get("dtype") != "<f4":
        raise BadEntry("another key, layout or dtype")
    if header.get("shapes") != [list(shape) for shape in shapes]:
        raise BadEntry(f"shapes {header.get('shapes')}, expected {[list(s) for s in shapes]}")
    orders = header.get("orders")
    if not isinstance(orders, list) or len(orders) != len(shapes) or \
            any(not isinstance(o, list) or sorted(o) != list(range(len(s))) for o, s in zip(orders, shapes)):
        raise BadEntry("no memory order of its dimensions")
    body = memoryview(data)[start:]
    if zlib.crc32(body) != header.get("body_crc32"):  # catches accidents (a writer of the folder could forge any)
        raise BadEntry("its values fail their crc32")
    values = data[start:].view(np.dtype("<f4"))  # the body starts 64-byte aligned (write_entry pads the header)
    low, high = (float(v) for v in torch.from_numpy(values).aminmax())  # one pass over the contiguous body
    if not (low >= 0.0 and high <= 1.0):  # NaN fails both
        raise BadEntry(f"values outside [0, 1] ({low}, {high})")
    features, offset = [], 0
    for shape, order in zip(shapes, orders):
        count = math.prod(shape)
        features.append(_from_buffer(values[offset:offset + count], shape, order))
        offset += count
    return features


# --- the folder -------------------------------------------------------------------------------


def evict(folder: Path, cap_bytes: int, keep: Optional[Path] = None) -> int:
    """Delete the least recently used entries (oldest mtime first, never `keep`) until the
    entries take at most `cap_bytes`, and killed writers' temporaries older than
    STALE_TEMPORARY_SECONDS; nothing else in the folder is touched. Returns bytes freed."""
    entries, now = [], time.time()
    with os.scandir(folder) as listing:
        for item in listing:
            try:
                status = item.stat(follow_symlinks=False)
            except FileNotFoundError:  # another process evicted it meanwhile
                continue
            if not stat.S_ISREG(status.st_mode):
                continue
            if ENTRY_NAME.fullmatch(item.name):
                entries.append((status.st_mtime_ns, item.name, status.st_size))
            elif _TEMPORARY_NAME.fullmatch(item.name) and now - status.st_mtime > STALE_TEMPORARY_SECONDS:
                owned.remove_file(folder / item.name)
    total, freed = sum(size for _, _, size in entries), 0
    for _, name, size in sorted(entries):
        if total <= cap_bytes:
            break
        if keep is not None and name == keep.name:
            continue
        if owned.remove_file(folder / name):  # missing_ok: two evicting processes may race
            freed += size
        total -= size
    return freed


def _clear_the_name(path: Path) -> None:
    """Remove a symbolic link, FIFO, socket or device at an entry's name, as itself (a
    link's target is never touched: core.owned.remove_file), so that the entry written next
    takes its place instead of being refused or written through it. A folder there stays
    (the write refuses it: InputError)."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return
    if not stat.S_ISREG(mode) and not stat.S_ISDIR(mode):
        owned.remove_file(path)


class FeatureCache:
    """model's ground-truth features through the cache in `folder` (None: no cache, the
    same computation). Call it with the [N, 3, H, W] input tensor; it returns the unit
    features LpipsBatch gives the head."""

    def __init__(self, model, folder: Optional[Path], cap_bytes: int):
        self.model, self.folder, self.cap_bytes = model, folder, cap_bytes
        self.hits = self.misses = 0
        self._shapes = {}

    def __call__(self, images) -> list:
        if self.folder is None:
            return self._compute(images)
        key = entry_key(self.model, images)
        path = self.folder / f"{key}{SUFFIX}"
        if tuple(images.shape) not in self._shapes:
            self._shapes[tuple(images.shape)] = expected_shapes(self.model, images.shape)
        shapes = self._shapes[tuple(images.shape)]
        try:
            features = read_entry(path, key, shapes)
        except BadEntry as why:
            _note(f"LPIPS cache entry {path} refused ({why}); recomputed")
            features = None
        except OSError as error:
            _note(f"LPIPS cache entry {path} unreadable ({error.strerror or error}); recomputed")
            features = None
        if features is not None:
            self.hits += 1
            return features
        self.misses += 1
        features = self._compute(images)
        self._store(path, key, features)
        return features

    def _compute(self, images) -> list:
        computed = self.model.unit_features(images)
        return [_canonical(feature, _memory_order(feature)) for feature in computed]

    def _store(self, path: Path, key: str, features: list) -> None:
        if 4 * sum(f.numel() for f in features) > self.cap_bytes:
            return  # larger than the whole cache: storing it would only evict everything
        try:
            _clear_the_name(path)
            write_entry(path, key, features)
            evict(self.folder, self.cap_bytes, keep=path)
        except InputError as error:  # a folder at the entry's name, a link planted again meanwhile
            _note(f"LPIPS cache entry {path} not stored ({error})")
        except OSError as error:  # a full disk or a read-only cache: the scores go on without it
            _note(f"LPIPS cache {self.folder} not written ({error.strerror or error}); "
                  f"features are computed afresh (set {FOLDER_ENV}={OFF} to stop trying)")
            self.folder = None


def features_source(model, environ=None) -> FeatureCache:
    """The ground-truth feature source for LpipsBatch(model, ground_truth=...): the cache
    the environment names (module docstring), its folder made ours on first use. A folder
    that cannot be ours is one InputError line; one that cannot be written (read-only, full)
    scores without the cache after a note."""
    chosen = settings(environ)
    folder = chosen.folder
    if folder is not None:
        try:
            folder = folders.adopt_shared_folder(folder, "cache")
        except InputError as error:
            raise InputError(f"LPIPS cache: {error} (relocate it with {FOLDER_ENV}=DIR or set {FOLDER_ENV}={OFF})") \
                from None
        except OSError as error:
            _note(f"LPIPS cache {folder} unavailable ({error.strerror or error}); features are computed afresh")
            folder = None
    return FeatureCache(model, folder, chosen.cap_bytes)
