"""Instance ids and albedo per view (generate), read back through Dataset, and the
evaluator's per-object PSNR and empty-view count."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from nerfgauge.core.dataset import Dataset, verify_manifest
from nerfgauge.scenes import make_scene


@pytest.fixture(scope="module")
def inside_dataset(tmp_path_factory, make_dataset):
    """The `inside` hard scene, 32 px: cameras among nine shapes and a floor."""
    return make_dataset(tmp_path_factory.mktemp("aov") / "inside", scene="inside", views=3, val_views=0,
                        test_views=3, spp=2)


@pytest.mark.parametrize("which", ["tiny_dataset", "inside_dataset"])
def test_instance_ids_agree_with_the_depth_hit_mask_pixel_for_pixel(request, which):
    ds = Dataset(request.getfixturevalue(which))
    names = ds.instance_names()
    seen = set()
    for split in ds.splits:
        for index in range(len(ds.frames(split))):
            ids = ds.instance(split, index)
            hit = ds.depth(split, index) > 0
            np.testing.assert_array_equal(ids > 0, hit)
            np.testing.assert_array_equal(ids > 0, ds.mask(split, index))
            assert set(np.unique(ids[ids > 0]).tolist()) <= set(names)
            seen |= set(np.unique(ids[ids > 0]).tolist())
    assert len(seen) >= 2  # the views show several shapes, told apart


def test_the_legend_names_every_shape_sorted(tiny_dataset, inside_dataset):
    for root, scene in ((tiny_dataset, "primitives"), (inside_dataset, "inside")):
        names = list(Dataset(root).instance_names().values())
        assert names == sorted(shape.name for shape in make_scene(scene, 0).shapes)


def test_instance_pixels_lie_on_their_own_mesh(tiny_dataset):
    """Each instance's pixels, unprojected with the ground-truth depth, lie on that
    shape's mesh (ids name the right shape, not just some shape)."""
    import trimesh

    from nerfgauge.core.camera import pixel_rays

    ds = Dataset(tiny_dataset)
    names = ds.instance_names()
    ids, depth = ds.instance("test", 0), ds.depth("test", 0)
    origins, directions = pixel_rays(ds.c2w("test")[0], ds.intrinsics("test"))
    points = origins + directions * depth[..., None]
    for number in np.unique(ids[ids > 0]):
        mesh = trimesh.load(tiny_dataset / "meshes" / f"{names[int(number)]}.ply", force="mesh")
        others = [trimesh.load(path, force="mesh") for path in (tiny_dataset / "meshes").glob("*.ply")
                  if path.stem != names[int(number)]]
        own = np.abs(trimesh.proximity.signed_distance(mesh, points[ids == number]))
        nearest_other = np.min([np.abs(trimesh.proximity.signed_distance(m, points[ids == number])) for m in others],
                               axis=0)
        assert np.all(own <= nearest_other + 1e-4)


def test_albedo_inside_a_diffuse_shape_is_its_colour(tiny_dataset):
    """Away from edges (all 8 neighbours the same instance) the box-filtered albedo is the
    BSDF's reflectance; it is 0 where no sample hits. (Its samples are not the colour's,
    so edge pixels' coverage differs from alpha.)"""
    ds = Dataset(tiny_dataset)
    colours = {shape.name: shape.material.color for shape in make_scene("primitives", 0).shapes
               if hasattr(shape.material, "color")}
    names = ds.instance_names()
    checked = 0
    for index in range(len(ds.frames("test"))):
        ids, albedo = ds.instance("test", index), ds.albedo("test", index)
        padded = np.pad(ids, 1, constant_values=-1)
        interior = np.all([padded[1 + dy:1 + dy + ids.shape[0], 1 + dx:1 + dx + ids.shape[1]] == ids
                           for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)
        for number, name in names.items():
            pixels = interior & (ids == number)
            if name in colours and pixels.any():
                np.testing.assert_allclose(albedo[pixels], np.broadcast_to(colours[name], albedo[pixels].shape),
                                           atol=1e-5)
                checked += 1
        # Pixels deep in the background (no neighbour's centre ray hits) get no albedo.
        assert np.all(albedo[interior & (ids == 0)] == 0)
    assert checked >= 2


def test_the_manifest_lists_the_new_files_and_they_verify(tiny_dataset):
    ds = Dataset(tiny_dataset)
    for stem in ds.frames("test"):
        for suffix in ("_instance.png", "_albedo.exr", "_noise.json"):
            assert stem + suffix in ds.manifest_files
    assert verify_manifest(tiny_dataset) == []


def test_evaluate_scores_each_object_on_its_own_pixels(tiny_dataset, tmp_path):
    """Ground truth as the prediction, with one object's pixels painted black: that
    object's PSNR drops, the others stay perfect."""
    from PIL import Image

    from nerfgauge.eval.evaluate import evaluate

    ds = Dataset(tiny_dataset)
    pred = tmp_path / "pred"
    (pred / "test").mkdir(parents=True)
    names = ds.instance_names()
    target = None
    for index, stem in enumerate(ds.frames("test")):
        image = np.array(Image.open(tiny_dataset / f"{stem}.png"))
        ids = ds.instance("test", index)
        if target is None:
            target = int(np.unique(ids[ids > 0])[0])
        image[ids == target, :3] = 0
        Image.fromarray(image).save(pred / f"{stem}.png")
    document = evaluate(tiny_dataset, pred)
    means = document["psnr_objects"]
    assert means[names[target]] < 20
    assert all(value == 100.0 for name, value in means.items() if name != names[target])
    assert document["empty_views"] == {"count": 0, "of": 2, "frames": [], "warning": None}
    assert document["noise"]["psnr_ceiling"] is not None and document["noise"]["at_noise_floor"] is False


def test_evaluate_warns_when_more_than_a_quarter_of_the_views_are_empty(tmp_path, make_dataset):
    from nerfgauge.eval.evaluate import evaluate, format_means

    root = make_dataset(tmp_path / "empty", scene="empty", views=2, val_views=0, test_views=2, width=16, height=16,
                        spp=2)
    pred = tmp_path / "pred"
    (pred / "test").mkdir(parents=True)
    for stem in Dataset(root).frames("test"):
        shutil.copy(root / f"{stem}.png", pred / f"{stem}.png")
    document = evaluate(root, pred)
    assert document["empty_views"]["count"] == 2 and "2 of 2 views hold no geometry" in document["empty_views"]["warning"]
    assert "warning: 2 of 2 views" in format_means(document)
    assert document["psnr_objects"] == {}
    # A perfect score of background against background is at the noise floor, and says so.
    assert document["noise"]["at_noise_floor"] is True and "add spp" in format_means(document)
