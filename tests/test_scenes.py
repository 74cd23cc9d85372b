"""Scenes are plain, seeded descriptions; their meshes are closed and outward-facing."""

import math

import numpy as np
import pytest
from nerfgauge.scenes import list_scenes, make_scene, meshes
from nerfgauge.scenes.description import Textured

from nerfgauge.core.errors import InputError


@pytest.mark.parametrize("name", ["primitives", "glossy", "random"])
def test_recipes_are_deterministic_and_describe_themselves(name):
    a, b = make_scene(name, 7), make_scene(name, 7)
    assert a.to_json() == b.to_json()
    lo, hi = a.aabb
    for shape in a.shapes:  # all content inside the AABB
        bounds = shape.mesh().bounds()
        assert (bounds[0] >= lo - 1e-9).all() and (bounds[1] <= hi + 1e-9).all()


def test_random_scene_follows_its_seed():
    layouts = {tuple(s.name for s in make_scene("random", seed).shapes) for seed in range(6)}
    assert len(layouts) > 1
    assert all(3 <= len(make_scene("random", seed).shapes) <= 6 for seed in range(6))


def test_needs_come_from_the_materials():
    assert make_scene("primitives", 0).needs.view_dependent is False
    assert make_scene("glossy", 0).needs.view_dependent is True
    checker = next(s.material for s in make_scene("primitives", 0).shapes if isinstance(s.material, Textured))
    # A checker tile is 2x2 cells: the finest detail is half the period.
    assert make_scene("primitives", 0).needs.finest_texture_period == pytest.approx(checker.period / 2)


def test_the_scene_package_never_imports_a_renderer():
    import subprocess
    import sys

    code = ("import sys, nerfgauge.scenes as scenes; scenes.make_scene('random', 1); "
            "print('mitsuba' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout.strip() == "False"


def test_unknown_scene_and_bad_seed():
    with pytest.raises(InputError, match="unknown scene 'nope'"):
        make_scene("nope", 0)
    with pytest.raises(InputError, match="seed"):
        make_scene("primitives", -1)


def test_listing_has_every_scene():
    names = [name for name, _ in list_scenes()]
    assert {"primitives", "glossy", "random", "mesh:PATH"} <= set(names)


@pytest.mark.parametrize("mesh,volume", [
    (meshes.box((1.0, 2.0, 3.0)), 6.0),
    (meshes.capped_cylinder(0.5, 1.0, segments=96), math.pi * 0.25 * 1.0),
    (meshes.torus(1.0, 0.3), 2 * math.pi**2 * 1.0 * 0.09),
    (meshes.icosphere((0, 0, 0), 1.0), 4 / 3 * math.pi),
])
def test_meshes_enclose_the_right_volume_with_outward_normals(mesh, volume):
    # A positive signed volume means outward winding; polygonal approximations fall short
    # of the true volume by O(1/segments^2): 1% covers 96 segments and subdivision 4.
    assert mesh.to_trimesh().volume == pytest.approx(volume, rel=1e-2)
    # Shading normals agree with the winding on every face (both point outward).
    tri = mesh.vertices[mesh.faces]
    face_normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vertex_normal = mesh.normals[mesh.faces].mean(axis=1)
    assert (np.einsum("ij,ij->i", face_normal, vertex_normal) > 0).all()


def test_pose_rotates_then_translates():
    matrix = meshes.pose((1, 2, 3), (0, 0, 90))
    np.testing.assert_allclose(matrix[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(matrix[:3, 3], [1, 2, 3])
