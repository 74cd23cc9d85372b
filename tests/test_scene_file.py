"""Scene files (docs/scene-files.md): several assets at given poses, usable as a scene name."""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest
import trimesh
from nerfgauge.generate.mitsuba_scene import scene_dict, write_meshes
from nerfgauge.generate.render import render_view
from nerfgauge.scenes import make_scene
from nerfgauge.scenes.description import PointLight

from nerfgauge.cli import main
from nerfgauge.core.camera import Intrinsics, pixel_rays
from nerfgauge.core.errors import InputError

HALF_SIZE = 0.6  # the raised tile: the unit tile scaled by 1.2
HALF_DIAGONAL = HALF_SIZE * math.sqrt(2)  # ... and turned 45 degrees


def unit_tile(path):
    """A 1 x 1 square in z = 0 centred on the origin, facing +Z."""
    vertices = [[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]]
    trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], process=False).export(path)
    return path


TWO_TILES = """version = 1

[[asset]]
path = "tile.ply"
name = "floor"
translation = [-1.0, 0.0, 0.0]

[[asset]]
path = "tile.ply"
name = "raised"
translation = [1.0, 0.0, 2.0]
rotation = [0.0, 0.0, 45.0]
scale = 1.2
material = { base_color = [0.8, 0.2, 0.1] }

[[light]]
type = "constant"
radiance = [1.0, 1.0, 1.0]
"""


def two_tiles(folder, text=TWO_TILES, name="scene.toml"):
    unit_tile(folder / "tile.ply")
    (folder / name).write_text(text)
    return folder / name


def test_two_assets_sit_where_the_file_says(tmp_path, mi):
    """From (0, 0, 10) looking down: pixels whose ray meets the raised tile (a 1.2 square
    turned 45 degrees about +Z at (1, 0, 2): the diamond |dx| + |dy| <= 0.849) lie 8 / |d_z|
    away; those meeting the floor tile ([-1.5, -0.5] x [-0.5, 0.5] at z = 0) 10 / |d_z|;
    rays 2 % of a tile clear of both edges miss. The rotation is tested too: points of the
    unturned square's corners outside the diamond are misses."""
    scene = make_scene(str(two_tiles(tmp_path)), 0, units="keep")
    assert [s.name for s in scene.shapes] == ["floor", "raised"]
    paths = write_meshes(scene, tmp_path / "meshes")
    loaded = mi.load_dict(scene_dict(mi, scene, paths, max_depth=2))
    c2w = np.eye(4)
    c2w[2, 3] = 10.0
    intrinsics = Intrinsics.from_fov(48, 48, 30.0)
    images = render_view(mi, loaded, c2w, intrinsics, 1, seed=0)
    origins, directions = pixel_rays(c2w, intrinsics)
    down = -directions[..., 2]
    at_raised = origins + (8.0 / down)[..., None] * directions
    at_floor = origins + (10.0 / down)[..., None] * directions
    diamond = np.abs(at_raised[..., 0] - 1) + np.abs(at_raised[..., 1])
    margin = 0.02
    on_raised = diamond < HALF_DIAGONAL - margin
    on_floor = (np.abs(at_floor[..., 0] + 1) < 0.5 - margin) & (np.abs(at_floor[..., 1]) < 0.5 - margin)
    clear = (diamond > HALF_DIAGONAL + margin) & ~((np.abs(at_floor[..., 0] + 1) < 0.5 + margin)
                                                    & (np.abs(at_floor[..., 1]) < 0.5 + margin))
    corner_of_unturned = clear & (np.abs(at_raised[..., 0] - 1) < HALF_SIZE) & (np.abs(at_raised[..., 1]) < HALF_SIZE)
    assert on_raised.sum() >= 4 and on_floor.sum() >= 20 and corner_of_unturned.sum() >= 1
    np.testing.assert_allclose(images.distance[on_raised], (8.0 / down)[on_raised], rtol=1e-5)
    np.testing.assert_allclose(images.distance[on_floor], (10.0 / down)[on_floor], rtol=1e-5)
    assert not images.hit[clear].any()


def test_normalised_scene_file_maps_everything_by_the_recorded_transform(tmp_path):
    text = TWO_TILES.replace('type = "constant"\nradiance = [1.0, 1.0, 1.0]',
                             'type = "point"\nposition = [0.0, 0.0, 4.0]\nintensity = [10.0, 10.0, 10.0]')
    text += '\n[camera]\nlayout = "hemisphere"\nradius = 6.0\n'
    path = two_tiles(tmp_path, text)
    kept, normalised = make_scene(str(path), 0, units="keep"), make_scene(str(path), 0)
    scale, shift = normalised.params["to_scene"]["scale"], np.array(normalised.params["to_scene"]["translation"])
    # x spans -1.5 .. 1 + 0.849 and z 0 .. 2: the largest extent (x) becomes 2.
    assert scale == pytest.approx(2 / (1.5 + 1 + HALF_DIAGONAL))
    for a, b in zip(kept.shapes, normalised.shapes):
        np.testing.assert_allclose(b.mesh().vertices, a.mesh().vertices * scale + shift, atol=1e-12)
    light = normalised.lights[0]
    assert isinstance(light, PointLight)
    np.testing.assert_allclose(light.position, np.array([0, 0, 4.0]) * scale + shift)
    np.testing.assert_allclose(light.intensity, np.full(3, 10 * scale**2))  # same irradiance at scaled distances
    assert normalised.cameras.radius == pytest.approx(6 * scale) and kept.cameras.radius == 6.0


def test_json_scene_file_is_the_same_scene(tmp_path):
    toml_path = two_tiles(tmp_path)
    import tomllib

    (tmp_path / "scene.json").write_text(json.dumps(tomllib.loads(toml_path.read_text())))
    a, b = make_scene(str(toml_path), 0), make_scene(str(tmp_path / "scene.json"), 0)
    assert [s.name for s in a.shapes] == [s.name for s in b.shapes]
    for x, y in zip(a.shapes, b.shapes):
        np.testing.assert_array_equal(x.mesh().vertices, y.mesh().vertices)
        assert x.material == y.material


def test_generate_records_every_input_with_its_sha256(tmp_path, capsys):
    path = two_tiles(tmp_path)
    out = tmp_path / "ds"
    assert main(["generate", str(path), "--out", str(out), "--res", "16", "--views", "1", "--val-views", "0",
                 "--test-views", "0", "--spp", "1", "--quiet"]) == 0
    doc = json.loads((out / "scene.json").read_text())
    digest = lambda p: hashlib.sha256(p.read_bytes()).hexdigest()  # noqa: E731
    assert doc["inputs"] == {str(path): digest(path), str(tmp_path / "tile.ply"): digest(tmp_path / "tile.ply")}
    assert [a["name"] for a in doc["scene"]["params"]["assets"]] == ["floor", "raised"]
    assert sorted(p.name for p in (out / "meshes").glob("*.ply")) == ["floor.ply", "raised.ply"]


BAD_FILES = {
    "unknown top key": ("version = 1\ncolour = 3\n[[asset]]\npath = 'tile.ply'\n", "unknown key 'colour'"),
    "unknown asset key": ("version = 1\n[[asset]]\npath = 'tile.ply'\nposition = [0, 0, 0]\n", "unknown key 'position'"),
    "missing asset": ("version = 1\n[[asset]]\npath = 'nowhere.glb'\n", "not found"),
    "no version": ("[[asset]]\npath = 'tile.ply'\n", "missing 'version'"),
    "future version": ("version = 2\n[[asset]]\npath = 'tile.ply'\n", "version 2"),
    "non-uniform scale": ("version = 1\n[[asset]]\npath = 'tile.ply'\nscale = [1, 2, 1]\n", "non-uniform"),
    "sheared matrix": ("version = 1\n[[asset]]\npath = 'tile.ply'\n"
                       "matrix = [[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n", "not a rigid pose"),
    "mirroring matrix": ("version = 1\n[[asset]]\npath = 'tile.ply'\n"
                         "matrix = [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n", "not a rigid pose"),
    "zero scale": ("version = 1\n[[asset]]\npath = 'tile.ply'\nscale = 0\n", "positive"),
    "bad light": ("version = 1\n[[asset]]\npath = 'tile.ply'\n[[light]]\ntype = 'laser'\n", "type must be one of"),
    "two environments": ("version = 1\n[[asset]]\npath = 'tile.ply'\n[[light]]\ntype = 'constant'\n"
                         "radiance = [1, 1, 1]\n[[light]]\ntype = 'constant'\nradiance = [1, 1, 1]\n", "more than one"),
    "not toml": ("version = = 1\n", "not valid TOML"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_scene_file_is_one_line_and_exit_2(tmp_path, capsys, case):
    text, expected = BAD_FILES[case]
    path = two_tiles(tmp_path, text)
    out = tmp_path / "ds"
    code = main(["generate", str(path), "--out", str(out), "--res", "8", "--spp", "1", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and expected in err[0] and str(path) in err[0], err
    assert not out.exists()


def test_a_pose_matrix_with_uniform_scale_is_accepted(tmp_path):
    turn = np.array([[0, -2, 0, 1], [2, 0, 0, 0], [0, 0, 2, 3], [0, 0, 0, 1]], float)  # 90 degrees, scale 2
    path = two_tiles(tmp_path, f"version = 1\n[[asset]]\npath = 'tile.ply'\nmatrix = {turn.tolist()}\n")
    (shape,) = make_scene(str(path), 0, units="keep").shapes
    np.testing.assert_allclose(shape.mesh().bounds(), [[0, -1, 3], [2, 1, 3]], atol=1e-12)
    with pytest.raises(InputError, match="unknown scene"):
        make_scene(str(tmp_path / "scene.yaml"), 0)


def test_scene_file_envmap_is_recorded_and_the_command_line_one_replaces_it(tmp_path):
    from nerfgauge.core.images import write_exr
    from nerfgauge.scenes.envmap import EnvironmentMap

    ones = np.ones((4, 8), np.float32)
    write_exr(tmp_path / "sky.exr", {"R": ones, "G": ones, "B": ones})
    write_exr(tmp_path / "other.exr", {"R": ones * 2, "G": ones, "B": ones})
    text = TWO_TILES.split("[[light]]")[0] + '[envmap]\npath = "sky.exr"\nrotation = 45.0\n'
    path = two_tiles(tmp_path, text)
    scene = make_scene(str(path), 0)
    digest = hashlib.sha256((tmp_path / "sky.exr").read_bytes()).hexdigest()
    assert scene.params["envmap"] == {"path": str(tmp_path / "sky.exr"), "sha256": digest, "rotation": 45.0}
    assert scene.params["inputs"][str(tmp_path / "sky.exr")] == digest
    (light,) = scene.lights
    assert isinstance(light, EnvironmentMap) and light.rotation == 45.0
    replaced = make_scene(str(path), 0, envmap=tmp_path / "other.exr")
    (light,) = replaced.lights
    assert light.path == str(tmp_path / "other.exr") and light.rotation == 0.0
