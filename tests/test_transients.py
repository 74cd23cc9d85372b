"""Transient objects (issue 35, item 5): present in some training views only, their masks
the exact hit mask of the transients, everything else the dataset without them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nerfgauge.core.camera import pixel_rays
from nerfgauge.core.dataset import Dataset
from nerfgauge.core.errors import InputError
from nerfgauge.core.images import read_png
from nerfgauge.generate import transients
from nerfgauge.generate.pipeline import GenerateConfig, plan
from nerfgauge.generate.render import cast_rays

SMALL = dict(scene="primitives", views=6, val_views=1, test_views=2, width=32, height=32, spp=4, seed=3)
WITH = dict(transients=3, transient_fraction=0.5)


@pytest.fixture(scope="module")
def pair(tmp_path_factory, make_dataset):
    """The same dataset with and without transients."""
    root = tmp_path_factory.mktemp("transients")
    return make_dataset(root / "with", **SMALL, **WITH), make_dataset(root / "without", **SMALL)


def test_placement_is_seeded_apart_and_in_bounds():
    the_plan = plan(GenerateConfig(**SMALL, **WITH))
    objects = the_plan.transients
    assert len(objects) == 3 and objects == plan(GenerateConfig(**SMALL, **WITH)).transients
    aabb = the_plan.scene.aabb
    static = transients.surface_samples(the_plan.scene, 5000, np.random.default_rng(0))
    for k, obj in enumerate(objects):
        centre, radius = np.array(obj.centre), obj.bounding_radius
        assert (centre - radius >= aabb[0] - 1e-12).all() and (centre + radius <= aabb[1] + 1e-12).all()
        # clear of the static surfaces (other samples than placement's: spacing allows a little slack)
        assert np.linalg.norm(static - centre, axis=1).min() > radius
        assert len(obj.views) == round(0.5 * SMALL["views"]) and len(set(obj.views)) == len(obj.views)
        for other in objects[k + 1:]:
            assert np.linalg.norm(centre - np.array(other.centre)) > radius + other.bounding_radius
    # the cameras do not move: the transients draw from their own generator
    base = plan(GenerateConfig(**SMALL))
    for split in ("train", "val", "test"):
        assert np.array_equal(base.poses[split], the_plan.poses[split])
    assert base.transients == () and "transients" not in base.config.to_json()
    for bad in ({"transients": -1}, {"transients": 65}, {"transients": 2, "transient_fraction": 0.0},
                {"transients": 2, "transient_fraction": 1.5}):
        with pytest.raises(InputError, match="--transient"):
            plan(GenerateConfig(**SMALL | bad))


def test_held_out_views_and_meshes_are_byte_identical(pair):
    """Val and test views never hold a transient, and each view's render seed depends on
    (seed, split, index) only: their files are the dataset without transients' own bytes.
    So are training views no transient was put in, and meshes/."""
    with_root, without_root = pair
    record = json.loads((with_root / "scene.json").read_text())["transients"]
    shown = {stem for obj in record["objects"] for stem in obj["views"]}
    manifest = json.loads((without_root / "manifest.json").read_text())
    files = manifest["files"] if isinstance(manifest.get("files"), (dict, list)) else manifest
    compared = 0
    for rel in files:
        if rel.startswith(("val/", "test/", "meshes/")) or (rel.startswith("train/") and not
                                                             any(rel.startswith(s + "_") or rel.startswith(s + ".")
                                                                 for s in shown)):
            assert (with_root / rel).read_bytes() == (without_root / rel).read_bytes(), rel
            compared += 1
    assert compared > 0
    assert not list(with_root.glob("val/*_transient.png")) and not list(with_root.glob("test/*_transient.png"))
    assert sorted(p.name for p in (with_root / "meshes").iterdir()) == sorted(p.name for p in (without_root / "meshes").iterdir())


def test_masks_are_the_transients_hit_masks(pair, mi):
    """Oracle: the present transients alone, intersected with the pixel-centre rays; a pixel
    is a transient's when such a ray hits one nearer than the static scene's surface (the
    dataset without transients' exact distance) or the static scene has nothing there."""
    with_root, without_root = pair
    ds, static = Dataset(with_root), Dataset(without_root)
    the_plan = plan(GenerateConfig(**SMALL, **WITH))
    cameras = ds.cameras("train")
    n_static = len(ds.instance_names()) - WITH["transients"]
    total = 0
    for index, stem in enumerate(cameras.stems):
        mask = read_png(with_root / f"{stem}_transient.png") > 0.5
        present = [t for t in the_plan.transients if index in t.views]
        expected = np.zeros(mask.shape, bool)
        if present:
            alone = mi.load_dict({"type": "scene", **{t.name: transients.shape_dict(mi, t) for t in present}})
            origins, directions = pixel_rays(cameras.c2w[index], cameras.intrinsics)
            distance, _, hit = cast_rays(mi, alone, origins.reshape(-1, 3), directions.reshape(-1, 3))
            distance, hit = distance.reshape(mask.shape), hit.reshape(mask.shape)
            behind = static.depth("train", index).astype(np.float64)
            expected = hit & ((behind == 0) | (distance < behind))
        assert np.array_equal(mask, expected), (stem, np.argwhere(mask != expected))
        # the view's own truth shows them: its hit mask holds every transient pixel,
        # and its instance ids there are the transients' (after the static shapes')
        assert ds.mask("train", index)[mask].all()
        assert (ds.instance("train", index)[mask] > n_static).all()
        assert (ds.instance("train", index)[~mask] <= n_static).all()
        total += int(mask.sum())
    assert total > 0  # some transient is seen at all
    record = ds.scene["transients"]
    assert record["count"] == 3 and record["fraction"] == 0.5
    assert ds.instance_names()[n_static + 1] == "transient_0"
    config = json.loads((with_root / "config.json").read_text())["config"]
    assert config["transients"] == 3 and config["transient_fraction"] == 0.5
