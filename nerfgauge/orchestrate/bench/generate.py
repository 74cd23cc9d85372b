"""`nerfgauge bench generate`: the generator's whole time against Mitsuba's own render time
for the same views (the overhead ratio), seconds per view. Mitsuba's time renders the same
views and keeps nothing."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from nerfgauge.generate.mitsuba_scene import scene_dict, write_meshes
from nerfgauge.generate.pipeline import GenerateConfig, generate, plan
from nerfgauge.generate.views import SPLIT_SEED_OFFSET, view_seed
from nerfgauge.generate.render import render_rgba
from nerfgauge.generate.variant import use_variant


def mitsuba_render_seconds(config: GenerateConfig) -> dict:
    """Seconds spent in mi.render alone for every view of `config` (scene loaded once,
    one warm-up render first so kernel compilation is not counted)."""
    the_plan = plan(config)
    mi = use_variant(the_plan.variant)
    with tempfile.TemporaryDirectory() as folder:
        paths = write_meshes(the_plan.scene, Path(folder))
        scene = mi.load_dict(scene_dict(mi, the_plan.scene, paths, config.max_depth), optimize=False)  # as workers.py
        views = [(split, i) for split in SPLIT_SEED_OFFSET for i in range(len(the_plan.poses[split]))]
        first = views[0]
        render_rgba(mi, scene, the_plan.poses[first[0]][first[1]], the_plan.intrinsics, config.spp, 0)
        start = time.perf_counter()
        for split, index in views:
            render_rgba(mi, scene, the_plan.poses[split][index], the_plan.intrinsics, config.spp,
                        view_seed(config.seed, split, index))
        seconds = time.perf_counter() - start
    return {"views": len(views), "seconds": seconds, "variant": the_plan.variant}


def bench_generate(scene: str, views: int, width: int, height: int, spp: int) -> dict:
    config = GenerateConfig(scene=scene, views=views, val_views=0, test_views=0, width=width, height=height, spp=spp)
    mitsuba = mitsuba_render_seconds(config)
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        generate(config, Path(folder) / "dataset", progress=False)
        total = time.perf_counter() - start
    return {"scene": scene, "views": views, "resolution": [width, height], "spp": spp, "variant": mitsuba["variant"],
            "generator_seconds": total, "mitsuba_seconds": mitsuba["seconds"],
            "seconds_per_view": total / views, "mitsuba_seconds_per_view": mitsuba["seconds"] / views,
            "overhead_ratio": total / mitsuba["seconds"]}
