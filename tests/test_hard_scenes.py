"""The hard scenes: each is hard in the way it claims (checked from geometry, not from a
render that could drift), the layouts they ask for put cameras where they should, and
every one survives the whole pipeline with finite numbers and defined metrics."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from nerfgauge.generate import layouts
from nerfgauge.generate.pipeline import GenerateConfig, plan
from nerfgauge.scenes import HARD_SCENES, list_scenes, make_scene
from nerfgauge.scenes.description import Cylinder, Sphere

from nerfgauge.core.camera import Intrinsics
from nerfgauge.core.errors import InputError

DEFAULT = GenerateConfig()  # 128x128, 40-degree field of view


def footprint_at(distance: float, config: GenerateConfig = DEFAULT) -> float:
    """Scene units one pixel spans at `distance` (pinhole: distance / focal length in pixels)."""
    return distance / Intrinsics.from_fov(config.width, config.height, config.fov).fx


def centre_distance(scene_name: str) -> float:
    scene = make_scene(scene_name, 0)
    return layouts.default_radius(scene.aabb, DEFAULT.fov, DEFAULT.width, DEFAULT.height)


def test_every_hard_scene_is_listed_and_fixed_across_seeds():
    listed = {name for name, _ in list_scenes()}
    assert set(HARD_SCENES) <= listed
    assert {"thin", "checker-fine", "mirror", "depth-range", "hdr", "glass", "empty", "tiny", "inside"} <= set(HARD_SCENES)
    for name in HARD_SCENES:
        a, b = make_scene(name, 0), make_scene(name, 7)
        assert a.shapes == b.shapes and a.aabb_min == b.aabb_min and a.aabb_max == b.aabb_max


def test_needs_follow_the_materials():
    for name in ("mirror", "glass", "hdr"):
        assert make_scene(name, 0).needs.view_dependent, name
    for name in ("thin", "checker-fine", "depth-range", "empty", "tiny", "inside"):
        assert not make_scene(name, 0).needs.view_dependent, name


def test_thin_parts_are_thinner_than_a_pixel_at_the_centre_distance():
    scene = make_scene("thin", 0)
    pixel = footprint_at(centre_distance("thin"))
    wires = [s for s in scene.shapes if s.name.startswith("wire")]
    plates = [s for s in scene.shapes if s.name.startswith("plate")]
    assert wires and plates
    for wire in wires:
        diameter = 2 * (wire.radius if isinstance(wire, Cylinder) else wire.minor)
        assert diameter < pixel, (wire.name, diameter, pixel)
    for plate in plates:
        assert min(plate.size) < pixel, (plate.name, plate.size, pixel)


def test_checker_fine_sits_at_the_nyquist_limit():
    """A checker's period is two cells; Nyquist needs 2 pixels per period. At the nearest
    possible content (camera radius minus the AABB's bounding radius) the finest period
    must span at most 3 pixels, and at the centre at least 1.5: near the limit both ways."""
    scene = make_scene("checker-fine", 0)
    radius = centre_distance("checker-fine")
    bound = float(np.linalg.norm(scene.aabb[1] - scene.aabb[0])) / 2
    period = 2 * scene.needs.finest_texture_period
    assert period / footprint_at(radius - bound) <= 3.0
    assert period / footprint_at(radius) >= 1.5


def test_tiny_covers_a_few_pixels():
    (speck,) = make_scene("tiny", 0).shapes
    farthest = centre_distance("tiny") + np.linalg.norm(speck.center)
    nearest = centre_distance("tiny") - np.linalg.norm(speck.center)
    across_far = 2 * speck.radius / footprint_at(farthest)
    across_near = 2 * speck.radius / footprint_at(nearest)
    assert 1.0 <= across_far and across_near <= 4.0, (across_far, across_near)


def test_empty_has_no_shapes_but_a_box():
    scene = make_scene("empty", 0)
    assert scene.shapes == () and (scene.aabb[1] > scene.aabb[0]).all()


def test_depth_range_near_and_far_from_every_camera():
    """Sphere distances from every camera of the plan: nearest 0.2 +- the camera spread,
    farthest object at least 50 away, ratio at least 100."""
    the_plan = plan(GenerateConfig(scene="depth-range", views=20, val_views=2, test_views=4))
    assert the_plan.layout.layout == "forward"
    spheres = {s.name: s for s in the_plan.scene.shapes if isinstance(s, Sphere)}
    eyes = np.concatenate([p[:, :3, 3] for p in the_plan.poses.values()])
    spread = the_plan.scene.cameras.spread

    def surface_distance(sphere):
        return np.linalg.norm(eyes - np.asarray(sphere.center), axis=1) - sphere.radius

    near, far = surface_distance(spheres["pebble"]), surface_distance(spheres["boulder"])
    assert np.all(np.abs(near - 0.2) <= spread + 1e-9)
    assert np.all(far >= 50.0 - spread)
    assert far.min() / near.max() >= 100


def test_forward_layout_is_parallel_on_a_disc_across_the_view():
    spec = layouts.LayoutSpec("forward", (30, 3, 5), radius=4.0, eye=(1.0, -2.0, 0.5), target=(1.0, 3.0, 0.5),
                              spread=0.3)
    poses = np.concatenate(list(layouts.camera_poses(spec, np.array([[-1.0] * 3, [1.0] * 3]),
                                                     np.random.default_rng(0)).values()))
    assert len(poses) == 38
    np.testing.assert_allclose(poses[:, :3, :3], np.broadcast_to(poses[0, :3, :3], (38, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(-poses[0, :3, 2], [0.0, 1.0, 0.0], atol=1e-12)  # looks along -Z = +Y here
    offsets = poses[:, :3, 3] - np.array([1.0, -2.0, 0.5])
    assert np.all(np.linalg.norm(offsets, axis=1) <= 0.3 + 1e-12)
    np.testing.assert_allclose(offsets @ poses[0, :3, 2], 0.0, atol=1e-12)  # on the plane across the view
    assert len(np.unique(poses[:, :3, 3].round(9), axis=0)) == 38


def test_inside_layout_puts_cameras_inside_the_box_within_the_elevation_band():
    the_plan = plan(GenerateConfig(scene="inside", views=30, val_views=3, test_views=5))
    assert the_plan.layout.layout == "inside"
    aabb = the_plan.scene.aabb
    poses = np.concatenate(list(the_plan.poses.values()))
    eyes = poses[:, :3, 3]
    assert np.all((eyes > aabb[0]) & (eyes < aabb[1]))
    view = -poses[:, :3, 2]
    elevation = np.degrees(np.arcsin(np.clip(view[:, 2], -1, 1)))
    lo, hi = the_plan.scene.cameras.elevation
    assert np.all((elevation >= lo - 1e-9) & (elevation <= hi + 1e-9))
    np.testing.assert_allclose(np.linalg.det(poses[:, :3, :3]), 1.0, atol=1e-12)


def test_orbiting_layouts_still_refuse_cameras_inside_the_box():
    with pytest.raises(InputError, match="inside the scene's AABB"):
        plan(GenerateConfig(scene="inside", layout="hemisphere", radius=0.5))


def test_command_line_layout_overrides_the_scene_suggestion():
    assert plan(GenerateConfig(scene="depth-range", layout="hemisphere", radius=60.0)).layout.layout == "hemisphere"
    assert plan(GenerateConfig(scene="primitives")).layout.layout == "hemisphere"


def test_hdr_keeps_its_emitters_visible_and_other_scenes_hide_the_sky(mi):
    from nerfgauge.generate.mitsuba_scene import scene_dict

    hdr = scene_dict(mi, make_scene("hdr", 0), {"light_0": "unused.ply", "floor": "f.ply", "matte_box": "b.ply"}, 8)
    assert hdr["integrator"]["hide_emitters"] is False
    emission = max(max(s.emission) for s in make_scene("hdr", 0).shapes if s.emission is not None)
    assert emission > 10
    primitives = make_scene("primitives", 0)
    paths = {s.name: f"{s.name}.ply" for s in primitives.shapes}
    assert scene_dict(mi, primitives, paths, 8)["integrator"]["hide_emitters"] is True


@pytest.mark.slow
@pytest.mark.parametrize("scene", HARD_SCENES)
def test_hard_scene_survives_generate_train_render_evaluate(tmp_path, scene):
    """A tiny pipeline per hard scene: it must finish, every number it writes must be
    finite, and every metric must be defined or have no pixel to score."""
    from nerfgauge.orchestrate.bench.hard import all_finite, audit

    from nerfgauge.run import RunConfig, run_pipeline

    out = tmp_path / scene
    # 1024 rays a step, not the default 4096: the 16 px views hold 1536 pixels in all
    run_pipeline(RunConfig(scene=scene, out=str(out), width=16, height=16, views=6, val_views=1, test_views=2, spp=4,
                           steps=15, train_options={"batch_rays": 1024}), progress=False)
    found = audit(out) | {"exit": 0}
    assert all_finite(found), found
    metrics = json.loads((out / "eval" / "compact" / "metrics.json").read_text(),
                         parse_constant=lambda c: pytest.fail(f"metrics.json holds {c}"))
    assert metrics["mean"]["psnr"] is not None and math.isfinite(metrics["mean"]["psnr"])
    # a metric that was not measured (LPIPS without its weights) is not one with no pixels
    assert found["not_measured"] == sorted(metrics.get("notes") or {})
    assert not set(found["no_pixels"]) & set(found["not_measured"])
    if scene == "empty":
        assert found["no_pixels"], "an empty scene has no hit pixel to score depth on"
        assert metrics["count"]["depth_absrel"] == 0


def test_bench_hard_refuses_bad_settings_before_running(tmp_path):
    from nerfgauge.orchestrate.bench.hard import HardConfig, bench_hard

    for config, message in [(HardConfig(("thin", "no-such-scene")), "unknown scene 'no-such-scene'"),
                            (HardConfig(("thin",), steps=0), "--steps must be an integer from 1 to"),
                            (HardConfig(("thin",), test_views=-1), "--test-views must be an integer from 1 to"),
                            (HardConfig(()), "--scenes is empty")]:
        with pytest.raises(InputError, match=message):
            bench_hard(config, tmp_path / "out")
        assert not (tmp_path / "out").exists()


def _found(**overrides):
    found = {"exit": 0, "dataset_non_finite": 0, "dataset_exr_files": 10, "log_entries": 3, "log_non_finite": 0,
             "render_depth_non_finite": 0, "render_depth_files": 2, "mean": {"psnr": 30.0}, "undefined": [],
             "no_pixels": []}
    return found | overrides


@pytest.mark.parametrize("overrides", [{"exit": 3}, {"dataset_non_finite": 1}, {"log_non_finite": 2},
                                       {"render_depth_non_finite": 5}, {"log_entries": 0},
                                       {"undefined": ["ssim"]}, {"metrics_error": "holds NaN"}])
def test_any_single_failure_makes_a_run_not_finite(overrides):
    from nerfgauge.orchestrate.bench.hard import all_finite

    assert all_finite(_found())
    assert not all_finite(_found(**overrides))


def test_audit_finds_nan_in_a_dataset_exr_and_a_log(tmp_path):
    from nerfgauge.orchestrate.bench.hard import audit

    from nerfgauge.core.images import write_exr

    (tmp_path / "dataset" / "test").mkdir(parents=True)
    (tmp_path / "run" / "renders" / "test").mkdir(parents=True)
    depth = np.ones((4, 4), np.float32)
    depth[1, 2] = np.nan
    depth[3, 3] = np.inf
    write_exr(tmp_path / "dataset" / "test" / "r_000_distance.exr", {"Z": depth}, {})
    write_exr(tmp_path / "run" / "renders" / "test" / "r_000_depth.exr", {"Z": np.ones((4, 4), np.float32)}, {})
    (tmp_path / "run" / "log.jsonl").write_text('{"loss": 0.1, "val_psnr": 20.0}\n{"loss": NaN, "val_psnr": 21.0}\n')
    found = audit(tmp_path)
    assert found["dataset_non_finite"] == 2 and found["dataset_exr_files"] == 1
    assert found["log_non_finite"] == 1 and found["log_entries"] == 2
    assert found["render_depth_non_finite"] == 0 and found["render_depth_files"] == 1
    assert "metrics_error" in found  # no metrics.json: reported, not a crash


def test_bench_hard_table_marks_failures_and_unscored_metrics():
    from nerfgauge.orchestrate.bench.hard import table_markdown

    rows = [_found(scene="empty", finite=True, mean={"psnr": 100.0, "opacity_iou": 1.0},
                   no_pixels=["depth_absrel", "psnr_foreground"], steps_per_second=60.0, resolution=53),
            _found(scene="inside", exit=3, finite=False, mean={})]
    table = table_markdown(rows, "nerfgauge bench hard").splitlines()
    assert table[0] == "`nerfgauge bench hard`"
    empty, inside = table[-2].split(" | "), table[-1].split(" | ")
    assert empty[2] == "yes" and empty[3] == "100.00" and empty[-1].startswith("depth_absrel, psnr_foreground")
    assert inside[1] == "3" and inside[2] == "**no**" and inside[3] == "–"
