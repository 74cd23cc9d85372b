"""COLMAP export, initial points and `nerfgauge sfm` (issue 32), checked with pycolmap as
the independent reader: it must read every model we write, project ground-truth surface
points where our cameras do (1e-3 px) and put the camera centres where ours are."""

from __future__ import annotations

import builtins
import json
import shutil

import numpy as np
import pytest

from cli_errors import one_line_exit_2
from nerfgauge.cli import main
from nerfgauge.core import colmap
from nerfgauge.core.camera import Intrinsics, look_at, pixel_rays
from nerfgauge.core.dataset import Dataset, verify_manifest
from nerfgauge.core.triangle_distance import point_triangle_distance
from nerfgauge.generate import points as points_module

pycolmap = pytest.importorskip("pycolmap")


@pytest.fixture(scope="module")
def colmap_dataset(tmp_path_factory, make_dataset):
    """primitives, 6 train views at 48 px, 2000 surface points."""
    from nerfgauge.generate.pipeline import GenerateConfig, generate

    out = tmp_path_factory.mktemp("colmap") / "prim"
    generate(GenerateConfig(scene="primitives", views=6, val_views=1, test_views=1, width=48, height=40, spp=4),
             out, progress=False, points="surface:2000")
    return out


def tree_bytes(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != ".nerfgauge.lock"}


# --- the format ------------------------------------------------------------------------


def test_quaternion_round_trip_and_sign():
    rng = np.random.default_rng(1)
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        rotation = colmap.quaternion_to_rotation(q)
        back = colmap.rotation_to_quaternion(rotation)
        assert back[0] >= 0
        np.testing.assert_allclose(back, q if q[0] >= 0 else -q, atol=1e-12)
    for angle in (np.pi, np.pi - 1e-9):  # near 180 degrees: the trace branch would lose precision
        rotation = colmap.quaternion_to_rotation([np.cos(angle / 2), 0, np.sin(angle / 2), 0])
        np.testing.assert_allclose(colmap.quaternion_to_rotation(colmap.rotation_to_quaternion(rotation)), rotation,
                                   atol=1e-12)


def test_pose_conversion_inverts_and_matches_opencv_axes():
    c2w = look_at([3.0, -2.0, 1.5], [0.1, 0.2, -0.3])
    qvec, tvec = colmap.world_to_camera(c2w)
    np.testing.assert_allclose(colmap.camera_to_world(qvec, tvec), c2w, atol=1e-12)
    target_in_camera = colmap.quaternion_to_rotation(qvec) @ np.array([0.1, 0.2, -0.3]) + tvec
    assert target_in_camera[2] > 0 and abs(target_in_camera[0]) < 1e-12 and abs(target_in_camera[1]) < 1e-12


def test_pycolmap_reads_binary_and_text_with_tracks(tmp_path):
    """Every field of a model with 2D points and tracks survives pycolmap's readers."""
    intrinsics = Intrinsics(64, 48, 50.5, 51.25, 31.75, 24.5)
    poses = np.stack([look_at([4 * np.cos(a), 4 * np.sin(a), 1.0], [0, 0, 0]) for a in (0.0, 1.0, 2.0)])
    images = colmap.model_images(poses, ["a.png", "b.png", "c.png"])
    images[0] = colmap.Image(1, images[0].qvec, images[0].tvec, 1, "a.png", np.array([[1.5, 2.5], [3.0, 4.0]]),
                             np.array([1, -1]))
    images[1] = colmap.Image(2, images[1].qvec, images[1].tvec, 1, "b.png", np.array([[7.0, 8.0]]), np.array([1]))
    points = colmap.Points.make([[0.1, 0.2, 0.3], [1.0, -1.0, 0.5]], [[255, 0, 10], [1, 2, 3]], [0.25, 0.0],
                                [np.array([[1, 0], [2, 0]]), np.zeros((0, 2))])
    colmap.write_model(tmp_path / "bin", [colmap.pinhole_camera(intrinsics)], images, points)
    text = tmp_path / "txt"
    text.mkdir()
    for name in colmap.FILES:
        shutil.copy(tmp_path / "bin" / f"{name}.txt", text)
    for folder in (tmp_path / "bin", text):
        model = pycolmap.Reconstruction(folder)
        camera = model.cameras[1]
        assert camera.model_name == "PINHOLE" and (camera.width, camera.height) == (64, 48)
        np.testing.assert_array_equal(camera.params, [50.5, 51.25, 31.75, 24.5])
        for k, pose in enumerate(poses):
            image = model.images[k + 1]
            np.testing.assert_allclose(image.projection_center(), pose[:3, 3], atol=1e-12)
        assert model.images[1].points2D[0].point3D_id == 1 and not model.images[1].points2D[1].has_point3D()
        np.testing.assert_array_equal(model.images[2].points2D[0].xy, [7.0, 8.0])
        point = model.points3D[1]
        np.testing.assert_array_equal(point.xyz, [0.1, 0.2, 0.3])
        np.testing.assert_array_equal(point.color, [255, 0, 10])
        assert point.error == 0.25 and sorted(e.image_id for e in point.track.elements) == [1, 2]
        assert model.points3D[2].track.length() == 0
    ours = colmap.read_images_bin((tmp_path / "bin" / "images.bin").read_bytes())
    assert [i.name for i in ours] == ["a.png", "b.png", "c.png"]
    np.testing.assert_array_equal(ours[0].point3D_ids, [1, -1])


def test_pycolmap_projects_ground_truth_depth_points_onto_our_pixel_centres(colmap_dataset):
    """The exact depth of every hit pixel, back-projected along our pixel-centre ray, is a
    ground-truth surface point; pycolmap's projection of it lands on that pixel's centre."""
    ds = Dataset(colmap_dataset)
    cameras = ds.cameras("train")
    model = pycolmap.Reconstruction(colmap_dataset / "sparse" / "0")
    assert model.num_reg_images() == len(cameras.stems)
    worst = 0.0
    for k, c2w in enumerate(cameras.c2w):
        image = model.images[k + 1]
        assert image.name == cameras.stems[k].rsplit("/", 1)[-1] + ".png"
        assert (colmap_dataset / "images" / image.name).read_bytes() == (colmap_dataset / f"{cameras.stems[k]}.png").read_bytes()
        np.testing.assert_allclose(image.projection_center(), c2w[:3, 3], rtol=0, atol=1e-12)
        origins, directions = pixel_rays(c2w, cameras.intrinsics)
        depth = ds.depth("train", k, kind="distance")
        rows, cols = np.nonzero(depth > 0)
        assert len(rows) > 50
        surface = origins[rows, cols] + depth[rows, cols, None] * directions[rows, cols]
        projected = np.array([image.project_point(p) for p in surface])
        worst = max(worst, float(np.abs(projected - np.stack([cols + 0.5, rows + 0.5], axis=1)).max()))
        ours, _ = colmap.project(surface, c2w, cameras.intrinsics)
        np.testing.assert_allclose(ours, projected, atol=1e-9)
    assert worst < 1e-3, worst


def test_dataset_records_points_and_stays_valid(colmap_dataset):
    ds = Dataset(colmap_dataset)
    assert verify_manifest(colmap_dataset) == []
    for rel in ("sparse/0/cameras.bin", "sparse/0/images.txt", "sparse/0/points3D.ply", "images/r_000.png"):
        assert rel in ds.manifest_files
    transforms = json.loads((colmap_dataset / "transforms.json").read_text())
    assert transforms["ply_file_path"] == "sparse/0/points3D.ply"
    points = ds.scene["points"]
    assert points["kind"] == "surface" and points["count"] == 2000 and points["spec"] == "surface:2000"
    distance = points["distance_to_surface"]
    assert distance["max"] < 1e-5 * distance["diagonal"]
    model = pycolmap.Reconstruction(colmap_dataset / "sparse" / "0")
    assert model.num_points3D() == 2000
    import trimesh

    cloud = trimesh.load(colmap_dataset / "sparse" / "0" / "points3D.ply")
    xyz = np.array([p.xyz for _, p in sorted(model.points3D.items())])
    np.testing.assert_allclose(np.asarray(cloud.vertices), xyz.astype(np.float32), rtol=0, atol=0)


def test_surface_points_lie_on_the_meshes_and_some_view_sees_them(colmap_dataset):
    """Independently of the recorded figure: exact distance to the meshes' triangles via
    trimesh, and each point's depth matches some train view's exact depth."""
    import trimesh

    ds = Dataset(colmap_dataset)
    model = pycolmap.Reconstruction(colmap_dataset / "sparse" / "0")
    xyz = np.array([p.xyz for _, p in sorted(model.points3D.items())])[:300]
    meshes = [trimesh.load(p, process=False) for p in sorted((colmap_dataset / "meshes").glob("*.ply"))]
    mesh = trimesh.util.concatenate(meshes)
    _, distance, _ = trimesh.proximity.closest_point(mesh, xyz)
    assert distance.max() < 1e-5 * np.linalg.norm(mesh.bounds[1] - mesh.bounds[0])
    cameras = ds.cameras("train")
    seen = np.zeros(len(xyz), bool)
    for k, c2w in enumerate(cameras.c2w):
        uv, _ = colmap.project(xyz, c2w, cameras.intrinsics)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < 48) & (uv[:, 1] >= 0) & (uv[:, 1] < 40)
        depth = ds.depth("train", k, kind="distance")
        recorded = np.where(inside, depth[np.clip(uv[:, 1], 0, 39).astype(int), np.clip(uv[:, 0], 0, 47).astype(int)], 0)
        distance = np.linalg.norm(xyz - c2w[:3, 3], axis=1)
        widest = np.sqrt(2) / (2 * cameras.intrinsics.fx) * np.tan(np.radians(80)) + 1e-5  # the rule's grazing cap
        seen |= inside & (np.abs(recorded - distance) <= distance * widest)
    assert seen.all()


def test_point_triangle_distance_against_brute_force():
    rng = np.random.default_rng(3)
    a, b, c = (rng.normal(size=(500, 3)) for _ in range(3))
    p = rng.normal(size=(500, 3)) * 2
    exact = point_triangle_distance(p, a, b, c)
    u, v = np.meshgrid(np.linspace(0, 1, 301), np.linspace(0, 1, 301))
    keep = u + v <= 1
    u, v = u[keep], v[keep]
    for k in range(0, 500, 50):
        samples = a[k] + u[:, None] * (b[k] - a[k]) + v[:, None] * (c[k] - a[k])
        brute = np.linalg.norm(samples - p[k], axis=1).min()
        assert exact[k] <= brute + 1e-12 and brute - exact[k] < 0.01 * max(1.0, np.linalg.norm(b[k] - a[k]))


# --- generate and export agree, bytes and all -------------------------------------------


def test_export_into_a_dataset_equals_generating_with_the_points(colmap_dataset, tmp_path, capsys):
    copy = tmp_path / "copy"
    shutil.copytree(colmap_dataset, copy, symlinks=True)
    assert main(["export", "colmap", str(copy), "--points", "random:300"]) == 0
    ds = Dataset(copy)
    assert ds.scene["points"]["kind"] == "random" and ds.scene["points"]["count"] == 300
    assert verify_manifest(copy) == []
    assert pycolmap.Reconstruction(copy / "sparse" / "0").num_points3D() == 300
    bounds = np.array(ds.scene["bounds"])
    xyz = np.array([p.xyz for p in pycolmap.Reconstruction(copy / "sparse" / "0").points3D.values()])
    assert (xyz >= bounds[0]).all() and (xyz <= bounds[1]).all()
    assert main(["export", "colmap", str(copy), "--points", "none"]) == 0
    assert not (copy / "sparse" / "0" / "points3D.ply").exists()
    assert "ply_file_path" not in json.loads((copy / "transforms.json").read_text())
    assert main(["export", "colmap", str(copy), "--points", "surface:2000"]) == 0
    assert tree_bytes(copy) == tree_bytes(colmap_dataset)
    assert not list(copy.rglob(".*.tmp*"))


def test_generate_resumes_a_missing_export(colmap_dataset, tmp_path):
    """A dataset whose export was cut short (no manifest after finish, or an older dataset
    without one) gets it from a rerun of the same generate command."""
    from nerfgauge.generate.pipeline import GenerateConfig, generate

    copy = tmp_path / "copy"
    shutil.copytree(colmap_dataset, copy, symlinks=True)
    shutil.rmtree(copy / "sparse")
    (copy / "manifest.json").unlink()
    result = generate(GenerateConfig(scene="primitives", views=6, val_views=1, test_views=1, width=48, height=40,
                                     spp=4), copy, progress=False, points="surface:2000")
    assert result["views_rendered"] == 0
    assert tree_bytes(copy) == tree_bytes(colmap_dataset)


# --- bad input: one line, exit 2, nothing written ------------------------------------------


@pytest.mark.parametrize("spec, expected", [
    ("surface:0", "between 1 and"), ("random:100000000", "between 1 and"), ("cubes", "KIND[:COUNT]"),
    ("surface:-3", "between 1 and"), ("none:5", "takes no count"),
])
def test_bad_point_specs(colmap_dataset, tmp_path, capsys, spec, expected):
    before = tree_bytes(colmap_dataset)
    one_line_exit_2(capsys, ["export", "colmap", colmap_dataset, "--points", spec], expected)
    one_line_exit_2(capsys, ["generate", "primitives", "--out", tmp_path / "new", "--points", spec], expected)
    assert not (tmp_path / "new").exists()
    assert tree_bytes(colmap_dataset) == before


def test_pycolmap_missing_is_one_line(colmap_dataset, tmp_path, capsys, monkeypatch):
    real_import = builtins.__import__

    def no_pycolmap(name, *args, **kwargs):
        if name == "pycolmap":
            raise ImportError("No module named 'pycolmap'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_pycolmap)
    before = tree_bytes(colmap_dataset)
    one_line_exit_2(capsys, ["export", "colmap", colmap_dataset, "--points", "sfm"], "needs pycolmap")
    one_line_exit_2(capsys, ["sfm", colmap_dataset, "--out", tmp_path / "sfm"], "needs pycolmap")
    one_line_exit_2(capsys, ["generate", "primitives", "--out", tmp_path / "new", "--points", "sfm"], "needs pycolmap")
    assert not (tmp_path / "sfm").exists() and not (tmp_path / "new").exists()
    assert tree_bytes(colmap_dataset) == before


def test_no_train_views_and_thin_lens_train_views_are_refused(tmp_path, capsys, make_dataset):
    no_train = tmp_path / "no-train"
    make_dataset(no_train, views=4, width=24, height=24)
    transforms = json.loads((no_train / "transforms_train.json").read_text())
    transforms["frames"] = []
    (no_train / "transforms_train.json").write_text(json.dumps(transforms))
    from nerfgauge.core.dataset import write_manifest

    write_manifest(no_train, [p.relative_to(no_train).as_posix() for p in no_train.rglob("*")
                              if p.is_file() and not p.name.startswith(".") and p.name != "manifest.json"])
    before = tree_bytes(no_train)
    one_line_exit_2(capsys, ["export", "colmap", no_train], "no train views")
    one_line_exit_2(capsys, ["sfm", no_train, "--out", tmp_path / "sfm"], "no train views")
    assert tree_bytes(no_train) == before and not (tmp_path / "sfm").exists()

    lens = make_dataset(tmp_path / "lens", views=4, width=24, height=24, aperture=0.05, focus_distance=4.0,
                        lens_splits="all")
    assert not (lens / "sparse").exists()  # generate skips what COLMAP cannot state
    one_line_exit_2(capsys, ["export", "colmap", lens], "thin lens", "no COLMAP camera model")


def test_export_refuses_folders_nerfgauge_did_not_generate(tmp_path, capsys):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    one_line_exit_2(capsys, ["export", "colmap", tmp_path / "mine"], "not a dataset nerfgauge generated")
    one_line_exit_2(capsys, ["export", "colmap", tmp_path / "absent"], "not found")
    assert sorted(p.name for p in (tmp_path / "mine").iterdir()) == ["notes.txt"]


# --- alignment and scoring ------------------------------------------------------------------


def test_umeyama_recovers_a_known_similarity_and_agrees_with_pycolmap():
    from nerfgauge.methods.sfm import umeyama

    rng = np.random.default_rng(7)
    source = rng.normal(size=(30, 3))
    q = rng.normal(size=4)
    rotation = colmap.quaternion_to_rotation(q / np.linalg.norm(q))
    target = 2.5 * source @ rotation.T + np.array([1.0, -2.0, 0.5])
    scale, r, t = umeyama(source, target)
    assert abs(scale - 2.5) < 1e-12
    np.testing.assert_allclose(r, rotation, atol=1e-12)
    np.testing.assert_allclose(t, [1.0, -2.0, 0.5], atol=1e-12)
    noisy = target + rng.normal(scale=0.05, size=target.shape)
    scale, r, t = umeyama(source, noisy)
    theirs = pycolmap.estimate_sim3d(source, noisy)  # pycolmap's own least-squares Sim(3)
    np.testing.assert_allclose(scale, theirs.scale, rtol=1e-9)
    np.testing.assert_allclose(r, theirs.rotation.matrix(), atol=1e-9)
    np.testing.assert_allclose(t, theirs.translation, atol=1e-9)


def test_scoring_the_exact_model_moved_by_a_similarity_gives_zero_error(colmap_dataset):
    from nerfgauge.methods.sfm import score

    model = pycolmap.Reconstruction(colmap_dataset / "sparse" / "0")
    q = np.array([0.2, -0.1, 0.4, 0.9])
    model.transform(pycolmap.Sim3d(0.3, pycolmap.Rotation3d(q / np.linalg.norm(q)), np.array([5.0, -1.0, 2.0])))
    ds = Dataset(colmap_dataset)
    names = [stem.rsplit("/", 1)[-1] + ".png" for stem in ds.frames("train")]
    result = score(ds, model, names)
    assert result["registered_fraction"] == 1.0
    assert abs(result["alignment"]["scale"] - 1 / 0.3) < 1e-9
    assert result["rotation_error_degrees"]["max"] < 1e-6
    assert result["translation_error"]["max"] < 1e-9 and result["ate_rmse"] < 1e-9
    assert result["rpe"]["rotation_rmse_degrees"] < 1e-6 and result["rpe"]["translation_rmse"] < 1e-9
    # the general search (no known triangle) is an upper bound, looser than the surface kind's
    assert result["points"]["distance_to_surface"]["p90"] < 1e-5 * result["points"]["diagonal"]
    assert result["points"]["distance_to_surface"]["max"] < 1e-3 * result["points"]["diagonal"]


def test_sfm_with_too_few_matches_is_one_line_and_writes_nothing(colmap_dataset, tmp_path, capsys):
    one_line_exit_2(capsys, ["sfm", colmap_dataset, "--out", tmp_path / "sfm"], "too few matches")
    assert not (tmp_path / "sfm").exists()


@pytest.mark.slow
def test_sfm_points_and_the_sfm_command_on_a_textured_dataset(tmp_path, capsys):
    """128 px, 40 views: features triangulated with the exact poses land near the surface;
    `nerfgauge sfm` saves its scores."""
    from nerfgauge.generate.pipeline import GenerateConfig, generate

    out = tmp_path / "prim"
    generate(GenerateConfig(scene="primitives", views=40, val_views=1, test_views=1, width=128, height=128, spp=16),
             out, progress=False, points="sfm")
    ds = Dataset(out)
    points = ds.scene["points"]
    assert points["kind"] == "sfm" and points["count"] >= points_module.MIN_SFM_POINTS
    # sparse and noisy: at 128 px occlusion junctions and silhouettes match too (BENCHMARKS.md), but
    # triangulated with our poses the points are near the scene, not spread through its bounds
    assert points["distance_to_surface"]["p90"] < 0.25 * points["distance_to_surface"]["diagonal"]
    model = pycolmap.Reconstruction(out / "sparse" / "0")
    assert model.num_points3D() == points["count"]
    assert all(p.track.length() >= 2 for p in model.points3D.values())
    assert main(["sfm", str(out), "--out", str(tmp_path / "sfm")]) == 0
    document = json.loads((tmp_path / "sfm" / "sfm.json").read_text())
    assert document["tool"] == "nerfgauge" and document["kind"] == "sfm"
    for key in ("registered_fraction", "rotation_error_degrees", "translation_error", "ate_rmse", "rpe",
                "reprojection_error_px", "points"):
        assert key in document
    assert pycolmap.Reconstruction(tmp_path / "sfm" / "sparse" / "0").num_reg_images() == document["registered"]


def test_an_export_killed_after_removing_the_manifest_is_rolled_back_and_redone(colmap_dataset, tmp_path,
                                                                                   monkeypatch, capsys):
    """The moment a kill hurts most: transforms.json and scene.json replaced, no manifest."""
    from nerfgauge.core import dataset as dataset_module
    from nerfgauge.generate import export

    copy = tmp_path / "copy"
    shutil.copytree(colmap_dataset, copy, symlinks=True)

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(dataset_module, "write_manifest", killed)
    with pytest.raises(KeyboardInterrupt):
        export.export_command(copy, "random:100")
    monkeypatch.undo()
    assert not (copy / "manifest.json").exists() and (copy / export.JOURNAL).is_file()
    assert json.loads((copy / "scene.json").read_text())["points"]["kind"] == "random"
    one_line_exit_2(capsys, ["evaluate", copy, "--pred", tmp_path / "none", "--out", tmp_path / "m.json"], "incomplete")
    assert main(["export", "colmap", str(copy), "--points", "surface:2000"]) == 0
    assert tree_bytes(copy) == tree_bytes(colmap_dataset)


def test_sfm_points_with_too_few_matches_are_one_line_and_change_nothing(colmap_dataset, capsys):
    before = tree_bytes(colmap_dataset)
    one_line_exit_2(capsys, ["export", "colmap", colmap_dataset, "--points", "sfm"], "too few feature matches")
    assert tree_bytes(colmap_dataset) == before


def test_default_count_follows_the_train_pixels():
    assert points_module.default_count(100, 128, 128) == 100_000
    assert points_module.default_count(4, 32, 32) == 256
    assert points_module.parse_spec("surface").to_text() == "surface"
    assert points_module.parse_spec("surface:5000").to_text() == "surface:5000"


def test_export_refuses_a_dataset_whose_files_changed(colmap_dataset, tmp_path, capsys):
    """The export rewrites the manifest: it must not bless a file changed since generation."""
    copy = tmp_path / "copy"
    shutil.copytree(colmap_dataset, copy, symlinks=True)
    depth = copy / "train" / "r_001_distance.exr"
    depth.write_bytes(depth.read_bytes()[:-1] + b"\0")
    before = tree_bytes(copy)
    one_line_exit_2(capsys, ["export", "colmap", copy, "--points", "random:10"], "differ from its manifest.json")
    assert tree_bytes(copy) == before
