"""Mitsuba variant choice, in one place.

auto: `cuda_ad_rgb` when a CUDA driver answers, `llvm_ad_rgb` when a working libLLVM is
found, else `scalar_rgb` with one note. The environment variable NERFGAUGE_MITSUBA_VARIANT
(auto|cuda|llvm|scalar) replaces what auto picks, for every command and test at once:
`NERFGAUGE_MITSUBA_VARIANT=scalar` runs on a machine with libLLVM as if it had none (CI
proves the scalar path that way); an explicit `--variant` still wins over it. Dr.Jit reads `DRJIT_LIBLLVM_PATH` when its LLVM
backend starts, so the path is set before mitsuba is first imported. The system's older
LLVMs (14, 15) crash Dr.Jit, so only libLLVM 17 or newer is picked automatically; a
`DRJIT_LIBLLVM_PATH` set by the user is trusted as it is.
"""

from __future__ import annotations

import ctypes
import functools
import glob
import os
import re
import sys

from nerfgauge.core.errors import InputError

VARIANTS = {"cuda": "cuda_ad_rgb", "llvm": "llvm_ad_rgb", "scalar": "scalar_rgb"}
CHOICES = ("auto",) + tuple(VARIANTS)
ENVIRONMENT = "NERFGAUGE_MITSUBA_VARIANT"
MIN_LLVM_MAJOR = 17
LIBLLVM_PATTERNS = (
    "/usr/lib/*-linux-gnu/libLLVM-[0-9]*.so*",
    "/usr/lib/*-linux-gnu/libLLVM.so.[0-9]*",
    "/usr/lib/llvm-[0-9]*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM.dylib",
)


def find_libllvm() -> str | None:
    """Path of the newest libLLVM with major version >= MIN_LLVM_MAJOR, or None."""
    best = None
    for pattern in LIBLLVM_PATTERNS:
        for path in glob.glob(pattern):
            match = re.search(r"(?:llvm-|LLVM-|LLVM\.so\.)(\d+)", path)
            major = int(match.group(1)) if match else 0
            if major >= MIN_LLVM_MAJOR and (best is None or major > best[0]):
                best = (major, path)
    return best[1] if best else None


def cuda_available() -> bool:
    """True when the CUDA driver loads and reports at least one device."""
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return False
    count = ctypes.c_int(0)
    return cuda.cuInit(0) == 0 and cuda.cuDeviceGetCount(ctypes.byref(count)) == 0 and count.value > 0


def prepare_llvm_path() -> str | None:
    """Set DRJIT_LIBLLVM_PATH (unless the user did) before mitsuba is imported."""
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return os.environ["DRJIT_LIBLLVM_PATH"]
    path = find_libllvm()
    if path is not None and "mitsuba" not in sys.modules:
        os.environ["DRJIT_LIBLLVM_PATH"] = path
    return path


@functools.lru_cache(maxsize=None)
def _note_once(message: str) -> None:
    print(f"nerfgauge: note: {message}", file=sys.stderr)


def environment_choice() -> str:
    """What NERFGAUGE_MITSUBA_VARIANT asks `auto` to be: auto (unset or empty), cuda, llvm or scalar."""
    value = os.environ.get(ENVIRONMENT, "").strip()
    if not value:
        return "auto"
    if value not in CHOICES:
        raise InputError(f"{ENVIRONMENT}={value!r} is not a variant; choose one of {', '.join(CHOICES)}")
    return value


def resolve_variant(requested: str = "auto") -> str:
    """The Mitsuba variant name for `requested` (auto|cuda|llvm|scalar), without importing it.

    auto means NERFGAUGE_MITSUBA_VARIANT when that is set, else the fastest variant found."""
    if requested not in CHOICES:
        raise InputError(f"unknown variant {requested!r}; choose one of {', '.join(CHOICES)}")
    source = f"variant {requested}"
    if requested == "auto":
        requested = environment_choice()
        source = f"{ENVIRONMENT}={requested}"
    if requested != "auto":
        if requested == "llvm" and prepare_llvm_path() is None:
            raise InputError(f"{source} needs libLLVM >= 17 (Debian: apt-get install libllvm19) "
                             "or DRJIT_LIBLLVM_PATH")
        if requested == "cuda" and not cuda_available():
            raise InputError(f"{source} needs a CUDA driver and a GPU; none was found")
        return VARIANTS[requested]
    if cuda_available():
        return VARIANTS["cuda"]
    if prepare_llvm_path() is not None:
        return VARIANTS["llvm"]
    _note_once("no libLLVM >= 17 found (Debian: apt-get install libllvm19); rendering with "
               "scalar_rgb, slower than llvm_ad_rgb (the demo's dataset: about 2x the CPU time)")
    return VARIANTS["scalar"]


def use_variant(name: str):
    """Import mitsuba with a resolved variant (e.g. "llvm_ad_rgb"). Returns the module."""
    if name not in VARIANTS.values():
        raise InputError(f"unknown Mitsuba variant {name!r}; expected one of {', '.join(VARIANTS.values())}")
    if name != VARIANTS["scalar"]:
        prepare_llvm_path()
    import mitsuba as mi  # mitsuba: only when the variant is set

    if name not in mi.variants():
        raise InputError(f"this Mitsuba build lacks variant {name}; it has {', '.join(mi.variants())}")
    mi.set_variant(name)
    return mi
