"""Procedural scene descriptions (renderer-free): `make_scene(name, seed)`."""

from nerfgauge.scenes.description import Needs, Scene
from nerfgauge.scenes.checks import CHECK_RECIPES
from nerfgauge.scenes.hard import HARD_RECIPES
from nerfgauge.scenes.registry import list_scenes, make_scene

HARD_SCENES = tuple(HARD_RECIPES)  # the hard cases, for `nerfgauge bench hard`
# captures for checking rules nobody tuned on them (issue 34): in no suite and not in bench hard
CHECK_SCENES = tuple(CHECK_RECIPES)

__all__ = ["CHECK_SCENES", "HARD_SCENES", "Needs", "Scene", "list_scenes", "make_scene"]
