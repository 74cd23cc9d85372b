"""Gaussians as the 3DGS reference code stores them (its GaussianModel.save_ply), and back.

One binary little-endian PLY element `vertex`, one row per Gaussian, float32 properties:

    x y z                  mean
    nx ny nz               zeros (the reference writes them; nothing reads them)
    f_dc_0 .. f_dc_2       degree-0 SH coefficient per channel (splat.sh: colour = 0.5 + C0 f_dc + ...)
    f_rest_0 .. f_rest_44  the other 15 coefficients per channel, channel-major:
                           f_rest_{c * 15 + k} is coefficient k + 1 of channel c
                           (features_rest [N, 15, 3] transposed to [N, 3, 15], then flattened)
    opacity                logit of the opacity (sigmoid gives it back)
    scale_0 .. scale_2     log of the standard deviations along the Gaussian's axes
    rot_0 .. rot_3         rotation quaternion (w, x, y, z), not necessarily normalised

Reading accepts what other tools write in that layout: binary little- or big-endian or
ASCII, any numeric property types, properties in any order and extra ones ignored, fewer
SH coefficients (f_rest_ counts 0, 9, 24 or 45: degree 0 to 3, missing ones read as zero),
and other elements after `vertex`. Anything else (no vertex element, a missing property, a
size that disagrees with the header, NaN) is an InputError naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nerfgauge.core import bounded
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_bytes_atomic

REST_PER_CHANNEL = 15  # degree 3: (3 + 1)^2 - 1
MAX_GAUSSIANS = 20_000_000  # 20 M rows of 62 floats: 5 GB; beyond any scene trained here
MAX_HEADER_BYTES = 1 << 16
TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
         "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
         "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}


@dataclass
class GaussianArrays:
    """Gaussians as stored (float32 numpy): means [N, 3], log_scales [N, 3], quats [N, 4]
    (w, x, y, z), opacity_logits [N], sh [N, 16, 3] (coefficient 0 the DC term)."""

    means: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray

    def __len__(self) -> int:
        return len(self.means)


def property_names() -> list[str]:
    """The 3DGS reference's vertex properties, in its order."""
    return (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
            + [f"f_rest_{i}" for i in range(3 * REST_PER_CHANNEL)] + ["opacity"]
            + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])


def ply_bytes(gaussians: GaussianArrays) -> bytes:
    """The PLY file of `gaussians` (module docstring). Deterministic: same values, same bytes."""
    n = len(gaussians)
    rest = np.asarray(gaussians.sh[:, 1:, :], np.float32).transpose(0, 2, 1).reshape(n, -1)  # [N, 3 * 15]
    columns = [gaussians.means, np.zeros((n, 3)), gaussians.sh[:, 0, :], rest, gaussians.opacity_logits[:, None],
               gaussians.log_scales, gaussians.quats]
    rows = np.ascontiguousarray(np.concatenate([np.asarray(c, np.float32) for c in columns], axis=1), dtype="<f4")
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {name}" for name in property_names()] + ["end_header"]
    return ("\n".join(header) + "\n").encode("ascii") + rows.tobytes()


def write_ply(path, gaussians: GaussianArrays) -> None:
    write_bytes_atomic(path, ply_bytes(gaussians))


def _header(data: bytes, path) -> tuple[str, list, int]:
    """(format, [(element name, count, [(property, numpy type or None for a list)])], body offset)."""
    if not data.startswith(b"ply\n") and not data.startswith(b"ply\r\n"):
        raise InputError(f"{path} is not a PLY file (it does not start with 'ply')")
    end = data.find(b"end_header", 0, MAX_HEADER_BYTES)
    if end < 0:
        raise InputError(f"{path}: no end_header in the first {MAX_HEADER_BYTES} bytes")
    body = data.index(b"\n", end) + 1 if b"\n" in data[end:end + 64] else len(data)
    try:
        lines = data[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise InputError(f"{path}: the PLY header is not ASCII") from None
    fmt, elements = None, []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
            if fmt not in FORMATS:
                raise InputError(f"{path} line {number}: unknown PLY format {fmt!r}")
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in TYPES:
            elements[-1][2].append((words[2], TYPES[words[1]]))
        elif words[0] == "property" and elements and len(words) == 5 and words[1] == "list":
            elements[-1][2].append((words[4], None))
        else:
            raise InputError(f"{path} line {number}: cannot read PLY header line {line!r}")
    if fmt is None:
        raise InputError(f"{path}: the PLY header has no format line")
    return fmt, elements, body


def _vertex_table(data: bytes, path) -> dict:
    """{property: float64 [N]} of the vertex element."""
    fmt, elements, body = _header(data, path)
    if not elements or elements[0][0] != "vertex":
        raise InputError(f"{path}: the first PLY element must be 'vertex' (the Gaussians), got "
                         f"{elements[0][0] if elements else 'none'}")
    _, count, properties = elements[0]
    if count > MAX_GAUSSIANS:
        raise InputError(f"{path}: {count} Gaussians is more than the {MAX_GAUSSIANS} read")
    if any(kind is None for _, kind in properties):
        raise InputError(f"{path}: list properties in the vertex element are not Gaussians")
    names = [name for name, _ in properties]
    if len(set(names)) != len(names):
        raise InputError(f"{path}: a vertex property is named twice")
    if FORMATS[fmt] is None:
        text = data[body:].decode("ascii", errors="replace").split("\n")
        rows = [line.split() for line in text if line.strip()][:count]
        if len(rows) < count or any(len(row) < len(names) for row in rows):
            raise InputError(f"{path}: the header promises {count} vertices of {len(names)} values; the file has fewer")
        try:
            table = np.asarray([[float(v) for v in row[:len(names)]] for row in rows], np.float64).reshape(count, -1)
        except ValueError:
            raise InputError(f"{path}: a vertex value is not a number") from None
        return {name: table[:, i] for i, name in enumerate(names)}
    dtype = np.dtype([(name, FORMATS[fmt] + kind) for name, kind in properties])
    needed = body + count * dtype.itemsize
    if len(data) < needed:
        raise InputError(f"{path}: the header promises {count} vertices ({needed} bytes), the file has {len(data)} "
                         "bytes (truncated?)")
    rows = np.frombuffer(data, dtype, count=count, offset=body)
    return {name: rows[name].astype(np.float64) for name in names}


def read_ply(path) -> GaussianArrays:
    """Gaussians from a PLY in the 3DGS layout (module docstring). InputError (one line) for a
    file that is not one."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"Gaussians file not found: {path}")
    size = path.stat().st_size
    data = bounded.read_bytes(path, MAX_HEADER_BYTES + MAX_GAUSSIANS * 62 * 8, "Gaussians PLY")
    if len(data) != size:
        raise InputError(f"{path} changed while it was read")
    table = _vertex_table(data, path)
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"scale_{i}" for i in range(3)] \
        + [f"rot_{i}" for i in range(4)]
    missing = [name for name in required if name not in table]
    if missing:
        raise InputError(f"{path} is not a Gaussian splatting PLY: no {', '.join(missing)} vertex properties")
    rest = sorted((int(name[7:]) for name in table if name.startswith("f_rest_") and name[7:].isdigit()))
    if rest != list(range(len(rest))) or len(rest) not in (0, 9, 24, 45):
        raise InputError(f"{path}: f_rest_ properties must be f_rest_0 .. f_rest_N-1 with N = 0, 9, 24 or 45 "
                         f"(degree 0 to 3), got {len(rest)}")
    n = len(table["x"])
    stack = lambda names: np.stack([table[name] for name in names], axis=1) if names else np.zeros((n, 0))  # noqa: E731
    per_channel = len(rest) // 3
    sh = np.zeros((n, 1 + REST_PER_CHANNEL, 3))
    sh[:, 0, :] = stack([f"f_dc_{i}" for i in range(3)])
    sh[:, 1:1 + per_channel, :] = stack([f"f_rest_{i}" for i in rest]).reshape(n, 3, per_channel).transpose(0, 2, 1)
    gaussians = GaussianArrays(stack(["x", "y", "z"]), stack([f"scale_{i}" for i in range(3)]),
                               stack([f"rot_{i}" for i in range(4)]), table["opacity"], sh)
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        value = getattr(gaussians, name)
        if not np.isfinite(value).all():
            raise InputError(f"{path}: NaN or inf in the Gaussians' {name.replace('_', ' ')}")
        setattr(gaussians, name, value.astype(np.float32))
    if n and (np.linalg.norm(gaussians.quats, axis=1) == 0).any():
        raise InputError(f"{path}: a Gaussian has a zero rotation quaternion")
    return gaussians


def sh_degree_of(gaussians: GaussianArrays) -> int:
    """The highest degree whose coefficients are not all zero (what a PLY was trained to)."""
    for degree in (3, 2, 1):
        if np.any(gaussians.sh[:, degree * degree:(degree + 1) ** 2, :]):
            return degree
    return 0

