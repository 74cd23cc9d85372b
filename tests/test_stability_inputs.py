"""Stability on degenerate inputs: every case gives a defined value or a one-line
InputError, never a crash, NaN or inf.

What test_metrics / test_evaluate / test_camera / test_generate_pipeline already cover is
not repeated here (SSIM of different constants at 20x20, 5x3 and 1x1, SSIM on every size
below the window, empty-mask depth and IoU on plain arrays, NaN colour / inf opacity / NaN
depth on a hit pixel in evaluate, straight-down look_at, one collinear-triangle mesh).
Added: the same cases end to end through `evaluate` on hand-built datasets (no hit pixels,
1x1 and 3x5 frames, an empty split), non-finite depth on hit and on miss pixels, float64
overflow in depth metrics and means, degenerate user meshes down to the generated dataset,
and look_at / layouts / rendering with the view along the up axis.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from nerfgauge.eval.evaluate import evaluate
from nerfgauge.eval.metrics import (
    PSNR_CAP_DB,
    depth_metrics,
    opacity_iou,
    ssim,
    summarize,
)
from nerfgauge.generate import layouts
from nerfgauge.scenes import make_scene
from nerfgauge.scenes.registry import load_user_mesh

from nerfgauge.cli import main
from nerfgauge.core import dataset
from nerfgauge.core.camera import Intrinsics, look_at, pixel_rays
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_json
from nerfgauge.core.images import read_exr_single, read_png, write_exr, write_png

C1, C2 = 0.01 ** 2, 0.03 ** 2  # SSIM constants for data range 1 (K1 = 0.01, K2 = 0.03)


def strict_json(path):
    """Parse JSON refusing NaN, Infinity and -Infinity."""
    def refuse(constant):
        raise ValueError(f"{constant} in {path}")

    return json.loads(path.read_text(), parse_constant=refuse)


def hand_dataset(root, frames, split="test", recipe="hand"):
    """A complete dataset written with the project's own helpers, no renderer.

    frames: list of (rgba uint8 [H, W, 4], ray distance float32 [H, W], 0 = miss). The
    mask is distance > 0; z-depth is written equal to distance (only its presence matters
    here). Every frame gets the same straight-down camera; `split` holds them all and the
    other splits are empty.
    """
    height, width = frames[0][0].shape[:2] if frames else (4, 4)
    intrinsics = Intrinsics.from_fov(width, height, 40.0)
    stems = {s: [dataset.frame_stem(s, i, len(frames)) for i in range(len(frames))] if s == split else []
             for s in dataset.SPLITS}
    pose = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0))
    poses = {s: [pose] * len(stems[s]) for s in dataset.SPLITS}
    written = []
    (root / split).mkdir(parents=True)
    for stem, (rgba, distance) in zip(stems[split], frames):
        write_png(root / (stem + ".png"), rgba)
        write_png(root / (stem + "_mask.png"), ((distance > 0) * 255).astype(np.uint8))
        write_exr(root / (stem + "_distance.exr"), {"Z": distance}, {"nerfgauge_depth": "ray_distance"})
        write_exr(root / (stem + "_zdepth.exr"), {"Z": distance}, {"nerfgauge_depth": "z_depth"})
        written += [stem + suffix for suffix in (".png", "_mask.png", "_distance.exr", "_zdepth.exr")]
    for s in dataset.SPLITS:
        write_json(root / f"transforms_{s}.json", dataset.synthetic_transforms(intrinsics, stems[s], poses[s]))
        written.append(f"transforms_{s}.json")
    write_json(root / "scene.json", {"schema": 1, "recipe": recipe})
    dataset.write_manifest(root, written + ["scene.json"])
    return root


def constant_rgba(height, width, rgb255, alpha=255):
    image = np.empty((height, width, 4), np.uint8)
    image[..., :3], image[..., 3] = rgb255, alpha
    return image


# --- metrics: what the unit tests leave out ------------------------------------------------


@pytest.mark.parametrize("shape", [(1, 1, 3), (3, 5, 3), (5, 3, 3), (2, 1, 3), (7, 7, 3), (11, 11, 3), (12, 40, 3)])
@pytest.mark.parametrize("value", [0.0, 0.37, 1.0])
def test_ssim_of_identical_constant_images_is_one(shape, value):
    # Identical inputs give identical local means and (co)variances, so numerator and
    # denominator are the same products: 1 up to one rounding.
    for dtype in (np.float64, np.float32):
        image = np.full(shape, value, dtype)
        assert ssim(image, image.copy()) == pytest.approx(1.0, abs=1e-15)


@pytest.mark.parametrize("shape", [(1, 1, 3), (3, 5, 3), (16, 16, 3)])
def test_ssim_with_one_constant_image_is_finite_and_below_one(shape):
    # Zero variance in one image only: the structure term is C2 / (s_x^2 + C2) * ... > 0.
    rng = np.random.default_rng(11)
    constant, varied = np.full(shape, 0.5), rng.random(shape)
    forward, backward = ssim(constant, varied), ssim(varied, constant)
    assert math.isfinite(forward) and -1.0 <= forward < 1.0
    assert forward == pytest.approx(backward, abs=1e-15)  # the formula is symmetric


def test_depth_and_opacity_reject_empty_planes():
    for shape in [(0, 0), (0, 3), (3, 0)]:
        with pytest.raises(InputError, match="H, W >= 1"):
            depth_metrics(np.zeros(shape), np.zeros(shape), np.zeros(shape, bool))
        with pytest.raises(InputError, match="H, W >= 1"):
            opacity_iou(np.zeros(shape), np.zeros(shape, bool))


def test_one_pixel_depth_and_opacity():
    hit, miss = np.array([[True]]), np.array([[False]])
    assert depth_metrics(np.array([[3.0]]), np.array([[2.0]]), hit) == {
        "absrel": 0.5, "rmse": 1.0, "mae": 1.0, "delta1": 0.0, "bias": 0.5}  # 1.5 >= 1.25; exact in binary
    assert depth_metrics(np.array([[np.inf]]), np.array([[0.0]]), miss)["rmse"] is None
    assert opacity_iou(np.array([[0.0]]), miss) == 1.0  # both silhouettes empty: they agree
    assert opacity_iou(np.array([[1.0]]), miss) == 0.0  # something predicted where nothing is


@pytest.mark.parametrize("pred", [1e160, -1e160, 1e308])
def test_depth_overflow_is_an_input_error_not_inf(pred):
    # (p - g)^2 exceeds float64's 1.8e308 once |p - g| > 1.34e154: RMSE would be inf.
    with pytest.raises(InputError, match=r"overflow.*rmse.*predicted depth.*e\+"):
        depth_metrics(np.array([[pred, 2.0]]), np.array([[1.0, 2.0]]), np.ones((1, 2), bool))


def test_huge_but_representable_depth_errors_stay_exact():
    # |p - g| = 1e100: squares 1e200, no overflow. Errors 1e100 and 0 on two pixels.
    out = depth_metrics(np.array([[1e100, 2.0]]), np.array([[1.0, 2.0]]), np.ones((1, 2), bool))
    assert out["mae"] == pytest.approx(0.5e100, rel=1e-15)
    assert out["rmse"] == pytest.approx(1e100 / math.sqrt(2), rel=1e-15)
    assert out["delta1"] == 0.5


def test_summarize_near_the_float64_limit_is_finite():
    # The plain sum 1.7e308 + 1.7e308 overflows; the mean of the values does not.
    mean, std = summarize([1.7e308, 1.7e308, 1.1e308])
    assert mean == pytest.approx((1.7 + 1.7 + 1.1) / 3 * 1e308, rel=1e-15)
    assert std == pytest.approx(math.sqrt(((1.7 - 1.5) ** 2 * 2 + 0.4 ** 2) / 3) * 1e308, rel=1e-12)
    assert summarize([-1.7e308, 1.7e308]) == (0.0, 1.7e308)
    assert summarize([1.0, 2.0, 3.0, 4.0]) == (2.5, math.sqrt(1.25))  # ordinary values: unchanged path


# --- evaluate on hand-built datasets ---------------------------------------------------------


def test_evaluate_ground_truth_with_no_hit_pixels(tmp_path, capsys):
    """Empty views (nothing in front of the camera): depth metrics and foreground PSNR are
    null with count 0, the (empty) silhouettes agree (IoU 1), colour is perfect,
    metrics.json holds no NaN or inf."""
    empty = (constant_rgba(6, 8, (0, 0, 0), alpha=0), np.zeros((6, 8), np.float32))
    root = hand_dataset(tmp_path / "ds", [empty, empty])
    out = tmp_path / "m.json"
    assert main(["evaluate", str(root), "--pred", str(root), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    doc = strict_json(out)
    assert doc["mean"]["psnr"] == PSNR_CAP_DB and doc["mean"]["ssim"] == 1.0
    for metric in ("depth_absrel", "depth_rmse", "depth_mae", "depth_delta1", "psnr_foreground"):
        assert doc["mean"][metric] is None and doc["std"][metric] is None and doc["count"][metric] == 0, metric
        assert all(frame[metric] is None for frame in doc["frames"])
    assert doc["mean"]["opacity_iou"] == 1.0 and doc["count"]["opacity_iou"] == 2
    assert doc["count"]["psnr"] == 2
    assert "0/2" in printed and "100.0000" in printed
    # The depth error map of an all-miss view is black (no pixel to colour).
    assert not np.any(read_png(tmp_path / "error_maps" / "r_000_depth.png"))


def test_evaluate_predictions_with_content_against_empty_ground_truth(tmp_path):
    """A method that paints an opaque object where the ground truth is empty: IoU 0 (not
    null: one silhouette is non-empty), depth still null (no ground-truth hit to score)."""
    empty = (constant_rgba(6, 8, (0, 0, 0), alpha=0), np.zeros((6, 8), np.float32))
    root = hand_dataset(tmp_path / "ds", [empty])
    pred = tmp_path / "pred"
    pred.mkdir()
    painted = constant_rgba(6, 8, (255, 255, 255), alpha=0)
    painted[2:4, 3:6] = (0, 0, 0, 255)  # 6 black opaque pixels on white
    write_png(pred / "r_000.png", painted)
    np.save(pred / "r_000_depth.npy", np.full((6, 8), 4.0))
    doc = evaluate(root, pred)
    frame = doc["frames"][0]
    assert frame["opacity_iou"] == 0.0 and frame["depth_rmse"] is None
    assert frame["psnr"] == pytest.approx(10 * math.log10(48 / 6), abs=1e-12)  # MSE = 6 * 3 / (48 * 3)
    strict_json(pred / "metrics.json")


@pytest.mark.parametrize("height,width", [(1, 1), (3, 5), (1, 7)])
def test_evaluate_frames_smaller_than_the_ssim_window(tmp_path, height, width):
    """Constant opaque frames below the 11x11 window: PSNR and SSIM by hand.

    Ground truth c and prediction d are constant per channel (8-bit values k / 255 as
    float32, like read_png). Zero local variances make the structure term C2 / C2 = 1:
        SSIM = mean_channels (2 c d + C1) / (c^2 + d^2 + C1),  PSNR = -10 log10(mean (d - c)^2)
    """
    gt255, pred255 = np.array([200, 30, 90]), np.array([180, 30, 140])
    distance = np.full((height, width), 2.0, np.float32)
    root = hand_dataset(tmp_path / "ds", [(constant_rgba(height, width, gt255), distance)])
    pred = tmp_path / "pred"
    pred.mkdir()
    write_png(pred / "r_000.png", constant_rgba(height, width, pred255)[..., :3].copy())  # RGB, no alpha
    np.save(pred / "r_000_depth.npy", np.full((height, width), 2.25))
    doc = evaluate(root, pred)
    c = (gt255 / 255.0).astype(np.float32).astype(np.float64)
    d = (pred255 / 255.0).astype(np.float32).astype(np.float64)
    frame = doc["frames"][0]
    assert frame["psnr"] == pytest.approx(-10 * math.log10(np.mean((d - c) ** 2)), abs=1e-9)
    # The computed variances of a constant are rounding noise ~1e-17, ~1e-14 relative to C2.
    assert frame["ssim"] == pytest.approx(np.mean((2 * c * d + C1) / (c ** 2 + d ** 2 + C1)), abs=1e-12)
    # Every pixel off by 0.25 on a true 2 (exact in binary); ratio 1.125 < 1.25.
    assert frame["depth_rmse"] == 0.25 and frame["depth_absrel"] == 0.125 and frame["depth_delta1"] == 1.0
    assert frame["opacity_iou"] is None  # an RGB prediction has no opacity
    strict_json(pred / "metrics.json")


def test_evaluate_an_empty_split_is_refused(tmp_path):
    """Issue 47: a split without frames was scored as a success (nulls, exit 0); now refused,
    nothing written (tests/test_bounded_reads.py::TestEmptySplit covers every format)."""
    root = hand_dataset(tmp_path / "ds", [])
    pred = tmp_path / "pred"
    pred.mkdir()
    with pytest.raises(InputError, match="split test of .* has no frames"):
        evaluate(root, pred)
    assert list(pred.iterdir()) == []


@pytest.fixture
def half_hit(tmp_path):
    """A 6x8 view whose left half hits geometry at distance 2 (grey) and whose right half
    is empty, with a flat folder of ground-truth-equal predictions beside it."""
    rgba = constant_rgba(6, 8, (128, 128, 128))
    rgba[:, 4:] = 0
    distance = np.zeros((6, 8), np.float32)
    distance[:, :4] = 2.0
    root = hand_dataset(tmp_path / "ds", [(rgba, distance)])
    pred = tmp_path / "pred"
    pred.mkdir()
    write_png(pred / "r_000.png", rgba)
    return root, pred, distance


def test_non_finite_depth_on_miss_pixels_is_ignored(half_hit, tmp_path):
    """Depth where the ground truth is empty is never scored, so a method's inf (no hit) or
    NaN (0/0 from zero opacity) there is accepted: same metrics as clean depth."""
    root, pred, distance = half_hit
    np.save(pred / "r_000_depth.npy", distance.astype(np.float64))
    clean = evaluate(root, pred, out=tmp_path / "clean.json")["frames"][0]
    depth = distance.astype(np.float64)
    depth[:, 4:6], depth[:, 6:] = np.inf, np.nan
    np.save(pred / "r_000_depth.npy", depth)
    noisy = evaluate(root, pred, out=tmp_path / "noisy.json")["frames"][0]
    assert noisy == clean and clean["depth_rmse"] == 0.0 and clean["opacity_iou"] == 1.0
    strict_json(tmp_path / "noisy.json")


@pytest.mark.parametrize("bad, needle", [(np.inf, "0 NaN and 1 inf"), (-np.inf, "0 NaN and 1 inf"),
                                         (np.nan, "1 NaN and 0 inf")])
def test_non_finite_depth_on_a_hit_pixel_fails_the_evaluation(half_hit, capsys, bad, needle):
    root, pred, distance = half_hit
    depth = distance.astype(np.float64)
    depth[3, 1] = bad
    np.save(pred / "r_000_depth.npy", depth)
    assert main(["evaluate", str(root), "--pred", str(pred)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "test/r_000" in err and needle in err and "r_000_depth.npy" in err, err
    assert not (pred / "metrics.json").exists() and not (pred / "error_maps").exists()


@pytest.mark.parametrize("channel, bad, needle", [(3, np.inf, "0 NaN and 1 inf"), (0, -np.inf, "1 inf"),
                                                  (1, np.nan, "1 NaN")])
def test_non_finite_exr_colour_fails_even_on_a_background_pixel(half_hit, capsys, channel, bad, needle):
    """NaN or inf anywhere in a colour EXR (here a pixel with alpha 0, which compositing
    would hide for colour channels) is a broken render: refused, not averaged away."""
    root, pred, _ = half_hit
    rgba = np.zeros((6, 8, 4), np.float32)
    rgba[:, :4] = (0.2, 0.2, 0.2, 1.0)
    rgba[2, 6, channel] = bad
    (pred / "r_000.png").unlink()
    write_exr(pred / "r_000.exr", {"RGBA": rgba})
    assert main(["evaluate", str(root), "--pred", str(pred)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "test/r_000" in err and needle in err, err
    assert not (pred / "metrics.json").exists()


def test_overflowing_depth_prediction_is_a_one_line_error(half_hit, capsys):
    root, pred, distance = half_hit
    depth = distance.astype(np.float64)
    depth[0, 0] = 1e200
    np.save(pred / "r_000_depth.npy", depth)
    assert main(["evaluate", str(root), "--pred", str(pred)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "overflow" in err and "test/r_000" in err, err


def test_corrupt_ground_truth_depth_names_the_dataset_file(half_hit, capsys):
    # The mask says hit but the stored depth is 0 there: the dataset's fault, named as such.
    root, pred, distance = half_hit
    np.save(pred / "r_000_depth.npy", distance.astype(np.float64))
    broken = distance.copy()
    broken[0, 0] = 0.0
    write_exr(root / "test/r_000_distance.exr", {"Z": broken}, {"nerfgauge_depth": "ray_distance"})
    dataset.write_manifest(root, dataset.read_manifest(root))  # vouch for the edit: test the depth check
    assert main(["evaluate", str(root), "--pred", str(pred)]) == 2
    err = capsys.readouterr().err
    assert "test/r_000_distance.exr" in err and "ground-truth depth must be > 0" in err, err


# --- user meshes (mesh:PATH) -----------------------------------------------------------------


def write_obj(path, vertices, faces):
    """faces: 0-based triangles."""
    lines = [f"v {x} {y} {z}" for x, y, z in vertices] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("vertices, faces", [
    ([(0, 0, 0), (1, 0, 0), (2, 0, 0), (0, 1, 0)], [(0, 1, 2), (0, 0, 3), (3, 3, 3)]),  # collinear, repeated
    ([(1, 2, 3)] * 3, [(0, 1, 2)]),  # three copies of one point: zero extent
    ([(0, 0, 0), (1, 1, 1), (2, 2, 2), (3, 3, 3)], [(0, 1, 2), (1, 2, 3), (0, 2, 3)]),  # a line in 3D
])
def test_mesh_of_only_zero_area_triangles_is_a_one_line_error(tmp_path, vertices, faces):
    path = write_obj(tmp_path / "degenerate.obj", vertices, faces)
    with pytest.raises(InputError, match="only degenerate") as info:
        load_user_mesh(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_non_finite_vertex_used_by_a_face_is_an_error(tmp_path, bad):
    # trimesh's default processing would silently drop the face instead.
    path = write_obj(tmp_path / "nan.obj", [(0, 0, 0), (1, 0, 0), (0, 1, 0), (bad, 0, 1)], [(0, 1, 2), (0, 1, 3)])
    with pytest.raises(InputError, match="1 vertices with NaN or inf") as info:
        load_user_mesh(path)
    assert "\n" not in str(info.value)


def test_coordinates_beyond_float64_arithmetic_are_an_error(tmp_path):
    path = write_obj(tmp_path / "huge.obj", [(-1e308, 0, 0), (1e308, 0, 0), (0, 1e308, 0)], [(0, 1, 2)])
    with pytest.raises(InputError, match="too large"):
        load_user_mesh(path)


def test_degenerate_faces_and_stray_vertices_do_not_count_towards_the_bounds(tmp_path):
    """One good triangle (unit right triangle), a zero-area sliver reaching x = 100, a face
    repeating a vertex, a duplicate vertex and an unreferenced vertex (even a NaN one).
    Only the good triangles are kept and they alone fill [-1, 1]."""
    vertices = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (100, 0, 0), (50, 0, 0), (1, 0, 0), (7, 7, 7), ("nan", 0, 0)]
    faces = [(0, 1, 2), (0, 3, 4), (1, 1, 2), (5, 2, 0)]  # (5, 2, 0) uses the duplicate of vertex 1
    mesh = load_user_mesh(write_obj(tmp_path / "mixed.obj", vertices, faces))
    np.testing.assert_array_equal(mesh.bounds(), [[-1, -1, 0], [1, 1, 0]])
    assert len(mesh.faces) == 2 and len(mesh.vertices) == 4  # vertices 0, 1, 2 and the duplicate 5
    np.testing.assert_array_equal(mesh.vertices[mesh.faces[0]], [[-1, -1, 0], [1, -1, 0], [-1, 1, 0]])
    assert np.isfinite(mesh.vertices).all()


def test_tiny_mesh_is_not_mistaken_for_a_degenerate_one(tmp_path):
    # Areas ~1e-400 underflow in file units; measured relative to the extent they are 1.
    mesh = load_user_mesh(write_obj(tmp_path / "tiny.obj", [(0, 0, 0), (1e-200, 0, 0), (0, 1e-200, 0)], [(0, 1, 2)]))
    np.testing.assert_allclose(mesh.bounds(), [[-1, -1, 0], [1, 1, 0]], atol=1e-12)


def test_flat_mesh_gets_a_padded_aabb(tmp_path):
    """A single quad has zero extent along its normal; the scene AABB is padded by 5 % of
    the largest extent (2 after scaling) on every side, so it is 0.2 thick."""
    path = write_obj(tmp_path / "quad.obj", [(0, 0, 2), (3, 0, 2), (3, 1, 2), (0, 1, 2)], [(0, 1, 2), (0, 2, 3)])
    scene = make_scene(f"mesh:{path}", 0)
    np.testing.assert_allclose(scene.aabb, [[-1.1, -1 / 3 - 0.1, -0.1], [1.1, 1 / 3 + 0.1, 0.1]], atol=1e-12)


def test_flat_mesh_with_degenerate_faces_renders_exact_depth(tmp_path, make_dataset):
    """End to end: a flat quad (plus a zero-area sliver reaching x = 30, a repeated-vertex
    face, a duplicate and an unreferenced vertex) through `mesh:PATH`. The dataset keeps
    the three good (coplanar, overlapping) triangles; every hit lies on the plane z = 0
    inside the quad, every ray aimed well inside the quad hits it at the analytic
    distance, and ground truth scored against itself gives finite metrics."""
    vertices = [(0, 0, 2), (3, 0, 2), (3, 1, 2), (0, 1, 2), (30, 0, 2), (9, 9, 9), (3, 0, 2)]
    faces = [(0, 1, 2), (0, 6, 3), (2, 3, 0), (0, 4, 1), (1, 1, 3)]  # the last two have zero area
    quad = write_obj(tmp_path / "quad.obj", vertices, faces)
    root = make_dataset(tmp_path / "ds", scene=f"mesh:{quad}", views=2, val_views=0, test_views=1,
                        width=24, height=20, spp=2)
    # Vertices 0, 1, 2, 3 and the duplicate 6 are used by the good faces; 4 and 5 are not.
    assert read_ply_counts(root / "meshes" / "user_mesh.ply") == (5, 3)
    bounds = np.array(strict_json(root / "scene.json")["bounds"])
    assert bounds[1, 2] - bounds[0, 2] == pytest.approx(0.2, abs=1e-12)
    half_y = 1 / 3
    hits = 0
    for split in ("train", "test"):
        cameras = dataset.open_dataset(root).cameras(split)
        for stem, c2w in zip(cameras.stems, cameras.c2w):
            stored = read_exr_single(root / (stem + "_distance.exr")).astype(np.float64)
            origins, directions = pixel_rays(c2w, cameras.intrinsics)
            t = -origins[..., 2] / directions[..., 2]  # ray meets the plane z = 0
            point = origins + t[..., None] * directions
            inside = (np.abs(point[..., 0]) < 1 - 0.05) & (np.abs(point[..., 1]) < half_y - 0.05) & (t > 0)
            hit = stored > 0
            assert hit[inside].all()
            on_quad = (np.abs(point[..., 0]) <= 1 + 1e-3) & (np.abs(point[..., 1]) <= half_y + 1e-3)
            assert on_quad[hit].all()
            # float32 vertices and intersection: ~1e-6 relative.
            np.testing.assert_allclose(stored[hit], t[hit], rtol=1e-4)
            hits += int(hit.sum())
    assert hits > 50
    assert main(["evaluate", str(root), "--pred", str(root), "--out", str(tmp_path / "m.json")]) == 0
    doc = strict_json(tmp_path / "m.json")
    assert doc["mean"]["depth_rmse"] == 0.0 and doc["mean"]["psnr"] == PSNR_CAP_DB


def read_ply_counts(path):
    """(vertex count, face count) from a PLY header."""
    header = path.read_bytes().split(b"end_header")[0].decode("ascii")
    counts = {line.split()[1]: int(line.split()[2]) for line in header.splitlines() if line.startswith("element")}
    return counts["vertex"], counts["face"]


def test_non_finite_mesh_through_the_cli_is_exit_2(tmp_path, capsys):
    path = write_obj(tmp_path / "nan.obj", [(0, 0, 0), (1, 0, 0), ("nan", 1, 0)], [(0, 1, 2)])
    out = tmp_path / "out"
    assert main(["generate", f"mesh:{path}", "--out", str(out), "--res", "8", "--spp", "1", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "NaN or inf" in err and str(path) in err
    assert not out.exists()


# --- cameras along the up axis ---------------------------------------------------------------


def assert_camera_frame(c2w, eye, target):
    """Finite, orthonormal, right-handed, at `eye`, -Z towards `target` (float64: 1e-12)."""
    assert np.isfinite(c2w).all()
    rotation = c2w[:3, :3]
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(np.cross(rotation[:, 0], rotation[:, 1]), rotation[:, 2], atol=1e-12)
    view = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    np.testing.assert_allclose(-rotation[:, 2], view / np.linalg.norm(view), atol=1e-12)
    np.testing.assert_array_equal(c2w[:3, 3], eye)
    np.testing.assert_array_equal(c2w[3], [0, 0, 0, 1])


TARGET = np.array([0.3, -0.2, 0.5])
POLAR_OFFSETS = {
    "straight above": (0.0, 0.0, 4.0),
    "straight below": (0.0, 0.0, -4.0),
    "1e-9 off above": (1e-9, 0.0, 4.0),
    "1e-9 off below": (0.0, -1e-9, -4.0),
    "1e-9 off diagonal": (7e-10, 7e-10, 4.0),
    "at the fallback threshold": (4e-9, 0.0, 4.0),  # |up x back| = 1e-9
    "1e-7 off": (-1e-7, 3e-8, 2.0),
}


@pytest.mark.parametrize("offset", POLAR_OFFSETS.values(), ids=POLAR_OFFSETS.keys())
def test_look_at_along_the_up_axis(offset):
    eye = TARGET + np.array(offset)
    assert_camera_frame(look_at(eye, TARGET), eye, TARGET)


def test_look_at_along_a_custom_up_and_its_fallback():
    # up = +Y and the view along Y: the +Y fallback is parallel too, so +X stands in.
    for eye in [(0.0, 3.0, 0.0), (0.0, -3.0, 0.0), (1e-10, 3.0, 0.0)]:
        assert_camera_frame(look_at(eye, (0, 0, 0), up=(0, 1, 0)), eye, (0, 0, 0))
    # A non-unit, non-axis up nearly parallel to the view: still orthonormal.
    up = np.array([0.3, 0.4, 0.5])
    eye = TARGET + 2 * up + np.array([0.0, 0.0, 1e-10])
    assert_camera_frame(look_at(eye, TARGET, up=up * 7), eye, TARGET)


@pytest.mark.parametrize("eye, target, up, needle", [
    ((np.nan, 0, 1), (0, 0, 0), (0, 0, 1), "eye"),
    ((0, 0, 1), (0, np.inf, 0), (0, 0, 1), "target"),
    ((0, 0, 1), (0, 0, 0), (0, 0, 0), "up vector is zero"),
    ((1, 2, 3), (1, 2, 3), (0, 0, 1), "coincide"),
])
def test_look_at_bad_input_is_an_input_error(eye, target, up, needle):
    with pytest.raises(InputError, match=needle):
        look_at(eye, target, up)


def test_pixel_rays_refuse_broken_poses():
    intrinsics = Intrinsics.from_fov(4, 3, 50.0)
    broken = np.eye(4)
    broken[0, 3] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        pixel_rays(broken, intrinsics)
    flat = np.eye(4)
    flat[:3, 2] = 0.0
    with pytest.raises(InputError, match="singular"):
        pixel_rays(flat, intrinsics)


@pytest.mark.parametrize("band", [(85.0, 90.0), (-90.0, -85.0)])
@pytest.mark.parametrize("layout", ["hemisphere", "orbit", "spiral"])
@pytest.mark.parametrize("sampling", ["fibonacci", "random"])
def test_layouts_near_the_poles_give_valid_poses(band, layout, sampling):
    """Bands touching a pole (cameras up to straight above or below the centre, looking
    along the up axis) give finite, right-handed frames that look at the centre. A band of
    zero width at a pole is refused instead (test_layouts_refuse_coinciding_cameras)."""
    aabb = np.array([[-1.0, -1.0, -0.5], [1.0, 1.0, 0.5]])
    spec = layouts.LayoutSpec(layout, (3, 1, 2), 4.0, band, sampling)
    poses = layouts.camera_poses(spec, aabb, np.random.default_rng(0))
    centre = aabb.mean(axis=0)
    assert sum(len(p) for p in poses.values()) == 6
    for split_poses in poses.values():
        for c2w in split_poses:
            assert_camera_frame(c2w, c2w[:3, 3].copy(), centre)
            assert np.linalg.norm(c2w[:3, 3] - centre) == pytest.approx(4.0, rel=1e-12)
            elevation = np.degrees(np.arcsin((c2w[2, 3] - centre[2]) / 4.0))
            assert band[0] - 1e-6 <= elevation <= band[1] + 1e-6


@pytest.mark.parametrize("height", [3.0, -3.0])
def test_render_along_the_up_axis_gives_exact_depth(mi, height):
    """A camera straight above (below) a sphere renders it, centred: the centre ray meets the
    sphere at |height| - r, and the hit pixels are symmetric about the image centre."""
    from nerfgauge.generate.mitsuba_scene import scene_dict
    from nerfgauge.generate.render import render_geometry
    from nerfgauge.scenes.description import (
        ConstantEnvironment,
        Diffuse,
        Sphere,
        build_scene,
    )

    radius = 0.5
    scene = build_scene("pole", 0, [Sphere("ball", (0.0, 0.0, 0.0), radius, Diffuse((0.5, 0.5, 0.5)))],
                        [ConstantEnvironment((1.0, 1.0, 1.0))])
    mitsuba_scene = mi.load_dict(scene_dict(mi, scene, {}, max_depth=2))
    c2w = look_at((0.0, 0.0, height), (0.0, 0.0, 0.0))
    intrinsics = Intrinsics.from_fov(15, 15, 40.0)
    distance, z_depth, _, hit = render_geometry(mi, mitsuba_scene, c2w, intrinsics)
    assert np.isfinite(distance).all() and np.isfinite(z_depth).all()
    # Pixel (7, 7) is the image centre: its ray is the optical axis. float32: ~1e-6 relative.
    assert distance[7, 7] == pytest.approx(abs(height) - radius, rel=1e-5)
    assert 0 < hit.sum() < hit.size
    np.testing.assert_array_equal(hit, hit[::-1, ::-1])


@pytest.mark.parametrize("layout", ["hemisphere", "orbit", "spiral"])
def test_layouts_refuse_coinciding_cameras(layout):
    """At a pole every azimuth is the same point: a zero-width band there would put
    identical views in train and test."""
    spec = layouts.LayoutSpec(layout, (8, 1, 2), radius=3.0, elevation=(90.0, 90.0))
    with pytest.raises(InputError, match="same pose"):
        layouts.camera_poses(spec, np.array([[-1.0] * 3, [1.0] * 3]), np.random.default_rng(0))


def test_transforms_with_nan_pose_name_the_file(tmp_path, make_dataset):
    root = make_dataset(tmp_path / "ds")
    path = root / "transforms_test.json"
    meta = json.loads(path.read_text())
    meta["frames"][1]["transform_matrix"][0][3] = float("nan")
    path.write_text(json.dumps(meta))
    dataset.write_manifest(root, dataset.read_manifest(root))  # vouch for the edit: test the pose check
    with pytest.raises(InputError, match=r"transforms_test.json.*NaN or inf.*r_001"):
        dataset.open_dataset(root).cameras("test")


def test_run_refuses_zero_test_views(tmp_path):
    from nerfgauge.run import RunConfig, run_pipeline

    with pytest.raises(InputError, match="--test-views must be at least 1"):
        run_pipeline(RunConfig(out=str(tmp_path / "out"), test_views=0, steps=5), progress=False)
    assert not (tmp_path / "out").exists()
