"""Procedural scene descriptions (renderer-free): `make_scene(name, seed)`."""

from scenes.description import Needs, Scene
from scenes.registry import list_scenes, make_scene

__all__ = ["Needs", "Scene", "list_scenes", "make_scene"]
