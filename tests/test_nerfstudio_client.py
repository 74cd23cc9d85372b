"""nerfstudio itself as the client (issue 32): its COLMAP dataparser loads a generated
dataset from `images/` + `sparse/0` (the text model, and the binary one alone) and keeps
our train cameras: intrinsics, poses (OpenGL camera-to-world, like transforms_train.json,
once the transform and scale it reports are undone), file names and the initial points.

nerfstudio is not a dependency (its requirements pull torchvision, which replaces the pinned
torch): tox installs it with --no-deps plus the few pure-Python and wheel-only packages its
COLMAP dataparser imports (tox.ini); where it is not importable these are skipped, saying so.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(importlib.util.find_spec("nerfstudio") is None,
                                 reason="nerfstudio is not installed (tox.ini [testenv] commands_pre: "
                                        "pip install --no-deps nerfstudio and the light packages it imports)")]


@pytest.fixture(scope="module")
def nerfstudio_colmap():
    """Their COLMAP dataparser module, imported only here (not at collection: it imports torch,
    tensorboard and viser); installed without a package its import chain needs, a skip naming it."""
    try:
        return importlib.import_module("nerfstudio.data.dataparsers.colmap_dataparser")
    except ImportError as error:
        pytest.skip(f"nerfstudio's COLMAP dataparser is not importable ({error}); "
                    "tox.ini [testenv] commands_pre lists the packages it needs")


POINTS = 600
# Their pipeline is float32: poses and points pass through float32 matrices (and, with their
# defaults, a float32 orientation and scale), so a few float32 ulps of the ~5-unit scene.
ATOL = 1e-5


@pytest.fixture(scope="module")
def ds(tmp_path_factory):
    from nerfgauge.generate.pipeline import GenerateConfig, generate

    out = tmp_path_factory.mktemp("ns") / "primitives"
    generate(GenerateConfig(scene="primitives", views=5, val_views=1, test_views=1, width=48, height=40, spp=4),
             out, progress=False, points=f"surface:{POINTS}")
    return out


@pytest.fixture(scope="module")
def binary_only(ds, tmp_path_factory):
    """sparse/0's binary model alone: with cameras.txt beside it nerfstudio reads the text one."""
    folder = tmp_path_factory.mktemp("ns-bin") / "0"
    folder.mkdir()
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        shutil.copyfile(ds / "sparse" / "0" / name, folder / name)
    return folder


def parse(nerfstudio_colmap, ds: Path, colmap_path: Path, settings: str):
    keep = dict(orientation_method="none", center_method="none", auto_scale_poses=False,
                assume_colmap_world_coordinate_convention=False)
    config = nerfstudio_colmap.ColmapDataParserConfig(data=ds, colmap_path=colmap_path, images_path=Path("images"),
                                                      scale_factor=1.0, downscale_factor=1, eval_mode="all",
                                                      **(keep if settings == "as-is" else {}))
    return config.setup().get_dataparser_outputs(split="train")


def homogeneous(transform) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :4] = np.asarray(transform, dtype=np.float64)
    return matrix


@pytest.fixture(params=["text", "binary"])
def colmap_path(request, binary_only):
    return Path("sparse/0") if request.param == "text" else binary_only


@pytest.mark.parametrize("settings", ["as-is", "nerfstudio-defaults"])
def test_their_colmap_dataparser_keeps_our_cameras(nerfstudio_colmap, ds, colmap_path, settings):
    out = parse(nerfstudio_colmap, ds, colmap_path, settings)
    ours = json.loads((ds / "transforms_train.json").read_text())
    nerfstudio_json = json.loads((ds / "transforms.json").read_text())
    frames = ours["frames"]

    # file names: images/r_00i.png, our train frames in order, the same bytes as train/r_00i.png
    names = [Path(frame["file_path"]).name + ".png" for frame in frames]
    assert [Path(p) for p in out.image_filenames] == [ds / "images" / name for name in names]
    for frame, name in zip(frames, names):
        assert (ds / "images" / name).read_bytes() == (ds / (frame["file_path"] + ".png")).read_bytes()

    # intrinsics: float32 in their Cameras, ours float64
    cams = out.cameras
    n = len(frames)
    for theirs, key in ((cams.fx, "fl_x"), (cams.fy, "fl_y"), (cams.cx, "cx"), (cams.cy, "cy")):
        np.testing.assert_allclose(theirs.numpy().ravel(), np.full(n, ours[key]), rtol=1e-6, err_msg=key)
        assert ours[key] == nerfstudio_json[key]
    assert cams.width.numpy().ravel().tolist() == [ours["w"]] * n
    assert cams.height.numpy().ravel().tolist() == [ours["h"]] * n
    assert not cams.distortion_params.numpy().any()

    # poses: theirs = T @ ours with the translation times s (T, s what they report); undo both
    transform = homogeneous(out.dataparser_transform.numpy())
    scale = float(out.dataparser_scale)
    if settings == "as-is":
        np.testing.assert_array_equal(transform, np.eye(4))
        assert scale == 1.0
    theirs = np.tile(np.eye(4), (n, 1, 1))
    theirs[:, :3, :4] = cams.camera_to_worlds.numpy().astype(np.float64)
    theirs[:, :3, 3] /= scale
    recovered = np.linalg.inv(transform) @ theirs
    expected = np.array([frame["transform_matrix"] for frame in frames], dtype=np.float64)
    np.testing.assert_allclose(recovered, expected, rtol=0, atol=ATOL)

    # initial points: the count we wrote, at our points3D.ply positions once T and s are undone
    import trimesh

    scene = json.loads((ds / "scene.json").read_text())
    assert scene["points"]["count"] == POINTS
    ply = np.asarray(trimesh.load(ds / nerfstudio_json["ply_file_path"]).vertices, dtype=np.float64)
    xyz = out.metadata["points3D_xyz"].numpy().astype(np.float64)
    assert xyz.shape == ply.shape == (POINTS, 3)
    assert out.metadata["points3D_rgb"].shape == (POINTS, 3)
    back = (np.c_[xyz / scale, np.ones(POINTS)] @ np.linalg.inv(transform).T)[:, :3]
    np.testing.assert_allclose(back, ply, rtol=0, atol=ATOL)


def test_their_input_dataset_reads_our_images(nerfstudio_colmap, ds):
    """Their InputDataset (what their datamanagers train on) opens the images the parser named."""
    from nerfstudio.data.datasets.base_dataset import InputDataset

    from nerfgauge.core.images import read_png

    out = parse(nerfstudio_colmap, ds, Path("sparse/0"), "as-is")
    data = InputDataset(out)
    frames = json.loads((ds / "transforms_train.json").read_text())["frames"]
    assert len(data) == len(frames)
    for index, frame in enumerate(frames):
        theirs = data.get_numpy_image(index)
        ours = np.round(read_png(ds / (frame["file_path"] + ".png")) * 255).astype(np.uint8)
        np.testing.assert_array_equal(theirs, ours)


def test_their_dataparsers_read_a_degraded_dataset_with_the_perturbed_train_poses(nerfstudio_colmap, tmp_path):
    """Degraded train views (generate.degrade): the extra frame keys (exact_transform_matrix,
    photometric) are passed over; their nerfstudio-format dataparser (transforms.json) and
    their COLMAP dataparser (sparse/0) both give the perturbed train poses the transforms hold."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    from nerfgauge.generate.pipeline import GenerateConfig, generate

    ds = tmp_path / "degraded"
    generate(GenerateConfig(scene="primitives", views=5, val_views=1, test_views=1, width=32, height=24, spp=4,
                            pose_noise_rotation=2.0, pose_noise_translation=0.05, exposure_ev=0.5, white_balance=0.1),
             ds, progress=False, points="surface:200")
    frames = json.loads((ds / "transforms_train.json").read_text())["frames"]
    noisy = np.array([frame["transform_matrix"] for frame in frames], dtype=np.float64)
    exact = np.array([frame["exact_transform_matrix"] for frame in frames], dtype=np.float64)
    assert np.abs(noisy - exact).max() > 1e-4

    theirs_json = NerfstudioDataParserConfig(data=ds, orientation_method="none", center_method="none",
                                             auto_scale_poses=False, scale_factor=1.0, eval_mode="filename")
    out = theirs_json.setup().get_dataparser_outputs(split="train")
    assert [Path(p).name for p in out.image_filenames] == [Path(f["file_path"]).name + ".png" for f in frames]
    poses = np.tile(np.eye(4), (len(frames), 1, 1))
    poses[:, :3, :4] = out.cameras.camera_to_worlds.numpy().astype(np.float64)
    recovered = np.linalg.inv(homogeneous(out.dataparser_transform.numpy())) @ poses
    np.testing.assert_allclose(recovered, noisy, rtol=0, atol=ATOL)

    out = parse(nerfstudio_colmap, ds, Path("sparse/0"), "as-is")
    poses[:, :3, :4] = out.cameras.camera_to_worlds.numpy().astype(np.float64)
    np.testing.assert_allclose(poses, noisy, rtol=0, atol=ATOL)


@pytest.mark.parametrize("split", ["train", "val", "test"])
def test_ns_train_data_path_reads_every_split(ds, split):
    """As `ns-train nerfacto --data PATH` does: their default dataparser (nerfstudio-data) on
    the folder with nothing else named reads transforms.json, each split's frames by our split
    lists, with our intrinsics and, undone their scale and transform, our poses."""
    try:
        parser_module = importlib.import_module("nerfstudio.data.dataparsers.nerfstudio_dataparser")
    except ImportError as error:
        pytest.skip(f"nerfstudio's nerfstudio-data dataparser is not importable ({error})")
    from nerfgauge.core.dataset import Dataset

    out = parser_module.NerfstudioDataParserConfig(data=ds).setup().get_dataparser_outputs(split=split)
    ours = Dataset(ds)
    assert [p.relative_to(ds).with_suffix("").as_posix() for p in out.image_filenames] == list(ours.frames(split))
    intr = ours.intrinsics(split)
    cams = out.cameras
    np.testing.assert_allclose([cams.fx[0].item(), cams.fy[0].item(), cams.cx[0].item(), cams.cy[0].item()],
                               [intr.fx, intr.fy, intr.cx, intr.cy], rtol=1e-6)
    # their camera_to_worlds = scale * (T @ c2w) with T, scale in dataparser_transform/scale
    transform = homogeneous(out.dataparser_transform.numpy())
    for k, c2w in enumerate(ours.c2w(split)):
        theirs = homogeneous(cams.camera_to_worlds[k].numpy())
        theirs[:3, 3] /= out.dataparser_scale
        expected = transform @ c2w
        np.testing.assert_allclose(theirs[:3, :3], expected[:3, :3], atol=ATOL)
        np.testing.assert_allclose(theirs[:3, 3], expected[:3, 3], atol=ATOL * 10)
