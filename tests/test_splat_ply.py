"""The Gaussians' PLY (splat.ply): the 3DGS reference code's layout, written and read back,
read by an independent reader (plyfile, what the 3DGS code itself uses), and PLYs made by
other tools (other endianness, ASCII, fewer SH coefficients, extra properties, other
property order) read and rendered; damaged files refused in one line."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from nerfgauge.splat.gaussians import Gaussians
from nerfgauge.splat.ply import GaussianArrays, ply_bytes, property_names, read_ply, sh_degree_of, write_ply
from splat_scenes import camera

from nerfgauge.core.errors import InputError


def arrays(n: int = 50, seed: int = 0, degree: int = 3) -> GaussianArrays:
    rng = np.random.default_rng(seed)
    sh = np.zeros((n, 16, 3), np.float32)
    sh[:, :(degree + 1) ** 2] = rng.normal(0, 0.3, (n, (degree + 1) ** 2, 3))
    return GaussianArrays(rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32),
                          np.log(rng.uniform(0.02, 0.1, (n, 3))).astype(np.float32),
                          rng.normal(size=(n, 4)).astype(np.float32), rng.normal(size=n).astype(np.float32), sh)


def same(a: GaussianArrays, b: GaussianArrays) -> None:
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_round_trip_is_exact(tmp_path):
    original = arrays()
    write_ply(tmp_path / "g.ply", original)
    same(read_ply(tmp_path / "g.ply"), original)
    assert ply_bytes(original) == (tmp_path / "g.ply").read_bytes()  # deterministic


def test_plyfile_reads_the_3dgs_layout(tmp_path):
    """Property names and order as the 3DGS code's save_ply; f_rest channel-major."""
    plyfile = pytest.importorskip("plyfile", reason="plyfile (the 3DGS code's reader) is not installed")
    original = arrays()
    write_ply(tmp_path / "g.ply", original)
    vertex = plyfile.PlyData.read(str(tmp_path / "g.ply"))["vertex"]
    assert [p.name for p in vertex.properties] == property_names()
    assert all(str(p.val_dtype) in ("float32", "f4") for p in vertex.properties)
    np.testing.assert_array_equal(np.stack([vertex["x"], vertex["y"], vertex["z"]], 1), original.means)
    np.testing.assert_array_equal(vertex["opacity"], original.opacity_logits)
    np.testing.assert_array_equal(np.stack([vertex[f"rot_{i}"] for i in range(4)], 1), original.quats)
    rest = np.stack([vertex[f"f_rest_{i}"] for i in range(45)], 1).reshape(-1, 3, 15)  # as the 3DGS code loads it
    np.testing.assert_array_equal(rest.transpose(0, 2, 1), original.sh[:, 1:])
    np.testing.assert_array_equal(np.stack([vertex[f"f_dc_{i}"] for i in range(3)], 1), original.sh[:, 0])


def foreign_ply(path, gaussians: GaussianArrays, *, fmt="binary_big_endian", degree=1, dtype=">f8",
                extra=True) -> None:
    """A PLY as another tool might write it: other endianness or ASCII, doubles, the
    properties shuffled, fewer SH coefficients, an extra property and a second element."""
    n = len(gaussians)
    per_channel = (degree + 1) ** 2 - 1
    columns = {"x": gaussians.means[:, 0], "y": gaussians.means[:, 1], "z": gaussians.means[:, 2],
               "opacity": gaussians.opacity_logits}
    columns |= {f"f_dc_{i}": gaussians.sh[:, 0, i] for i in range(3)}
    columns |= {f"scale_{i}": gaussians.log_scales[:, i] for i in range(3)}
    columns |= {f"rot_{i}": gaussians.quats[:, i] for i in range(4)}
    rest = gaussians.sh[:, 1:1 + per_channel].transpose(0, 2, 1).reshape(n, -1)
    columns |= {f"f_rest_{i}": rest[:, i] for i in range(3 * per_channel)}
    if extra:
        columns["confidence"] = np.ones(n)
    names = sorted(columns, reverse=True)
    header = ["ply", f"format {fmt} 1.0", "comment made elsewhere", f"element vertex {n}"]
    header += [f"property double {name}" for name in names]
    header += ["element camera 1", "property float focal", "end_header"]
    table = np.stack([np.asarray(columns[name], np.float64) for name in names], 1)
    if fmt == "ascii":
        body = "\n".join(" ".join(repr(float(v)) for v in row) for row in table) + "\n1.0\n"
        data = body.encode()
    else:
        data = table.astype(dtype).tobytes() + np.asarray([1.0], dtype[0] + "f4").tobytes()
    path.write_bytes(("\n".join(header) + "\n").encode() + data)


@pytest.mark.parametrize("fmt,dtype", [("binary_big_endian", ">f8"), ("binary_little_endian", "<f8"), ("ascii", None)])
def test_a_ply_from_another_tool_is_read_and_renders(tmp_path, fmt, dtype):
    original = arrays(degree=1)
    foreign_ply(tmp_path / "other.ply", original, fmt=fmt, dtype=dtype)
    read = read_ply(tmp_path / "other.ply")
    np.testing.assert_allclose(read.sh, original.sh, rtol=1e-6, atol=1e-7)  # degrees 2-3 read as zero
    np.testing.assert_allclose(read.means, original.means, rtol=1e-6)
    assert sh_degree_of(read) == 1
    cam = camera(dtype=torch.float32)
    out = Gaussians.from_arrays(read).render(cam, torch.ones(3), sh_degree_of(read))
    ours = Gaussians.from_arrays(original).render(cam, torch.ones(3), 1)
    assert float(out.opacity.max()) > 0.5
    torch.testing.assert_close(out.rgb, ours.rgb, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("damage,expected", [
    (lambda b: b[:-10], "truncated"),
    (lambda b: b"plx" + b[3:], "not a PLY"),
    (lambda b: b.replace(b"property float opacity\n", b"property float opacityx\n"), "no opacity"),
    (lambda b: b.replace(b"property float f_rest_44\n", b""), "f_rest_"),
    (lambda b: b.replace(b"end_header", b"end_headex"), "no end_header"),
    (lambda b: b.replace(b"binary_little_endian", b"binary_middle_endian"), "unknown PLY format"),
    (lambda b: b.replace(b"element vertex 50", b"element vertex 99999999999"), "more than"),
])
def test_damaged_files_are_one_line_input_errors(tmp_path, damage, expected):
    path = tmp_path / "bad.ply"
    path.write_bytes(damage(ply_bytes(arrays())))
    with pytest.raises(InputError, match=expected) as error:
        read_ply(path)
    assert "\n" not in str(error.value) and str(path) in str(error.value)


def test_nan_in_a_ply_is_refused(tmp_path):
    bad = arrays()
    bad.means[3, 1] = np.nan
    write_ply(tmp_path / "nan.ply", bad)
    with pytest.raises(InputError, match="NaN or inf in the Gaussians' means"):
        read_ply(tmp_path / "nan.ply")
