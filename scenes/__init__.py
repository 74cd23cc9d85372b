"""Procedural scene descriptions (renderer-free): `make_scene(name, seed)`."""

from nerfgauge.scenes.description import Needs, Scene
from nerfgauge.scenes.hard import HARD_RECIPES
from nerfgauge.scenes.registry import list_scenes, make_scene

HARD_SCENES = tuple(HARD_RECIPES)  # the hard cases, for `nerfgauge bench hard`

__all__ = ["HARD_SCENES", "Needs", "Scene", "list_scenes", "make_scene"]
