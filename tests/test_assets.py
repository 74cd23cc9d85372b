"""User assets (`mesh:PATH`) keep their objects, names, materials and units.

Every asset is made inside the test: textures drawn in numpy, GLBs written by trimesh
with a TextureVisuals/PBRMaterial, OBJ+MTL written by hand.

Colour checks use a plane lit by a constant environment of radiance 1 (an all-ones
--envmap): a diffuse surface of albedo a that sees the whole sky and nothing else sends
L = a * 1 towards every direction, so the rendered linear colour of a pixel inside one
texel region is the texel's linear albedo.

Two tolerances are checked. A rigorous one: the path tracer's per-sample estimate at the
first hit is bounded: its BSDF-sampled term (pdf p_b = cos / pi) is a L w_bsdf <= a L_max,
and its emitter-sampled term with the power heuristic is
(a / pi) cos L p_e / (p_e^2 + p_b^2) <= (a / pi) cos L / (2 p_b) = a L / 2 (AM-GM), whatever
the emitter's sampling pdf p_e; so with L <= 1 every sample lies in [0, 1.5 a]. The mean of n such samples is within
t = 1.5 a sqrt(ln(2 / delta) / (2 n)) of a except with probability delta (Hoeffding);
delta = 1e-6 here, n = spp times the pixels averaged. Hoeffding ignores how small the
variance really is (measured errors are ~50x below it), so a tighter one too: the K pixel
values of one region are independent estimates of a with a standard deviation that falls
as 1/sqrt(spp); their mean lies within 6 sample standard errors s / sqrt(K) of a
(Student's t with K - 1 >= 19 degrees of freedom: probability < 1e-5 of failing), plus
1e-4 for float32.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh
from nerfgauge.generate.mitsuba_scene import scene_dict, write_meshes
from nerfgauge.generate.render import render_view
from nerfgauge.scenes import make_scene
from nerfgauge.core.images import srgb_to_linear
from nerfgauge.scenes.trimesh_reader import gltf_json
from nerfgauge.scenes.envmap import read_envmap
from PIL import Image

from nerfgauge.cli import main
from nerfgauge.core.camera import Intrinsics, look_at, pixel_rays
from nerfgauge.core.errors import InputError
from nerfgauge.core.images import write_exr

DELTA = 1e-6

# 16 x 16 sRGB texture, four 8 x 8 quadrants: top-left red, top-right green,
# bottom-left blue, bottom-right grey (row 0 is the image's top).
QUADRANTS = {"top_left": (200, 30, 30), "top_right": (30, 190, 40), "bottom_left": (20, 40, 210),
             "bottom_right": (170, 170, 170)}


def quadrant_texture() -> np.ndarray:
    """[16, 16, 3] uint8."""
    image = np.zeros((16, 16, 3), np.uint8)
    image[:8, :8], image[:8, 8:] = QUADRANTS["top_left"], QUADRANTS["top_right"]
    image[8:, :8], image[8:, 8:] = QUADRANTS["bottom_left"], QUADRANTS["bottom_right"]
    return image


def plane(half=1.0, z=0.0) -> trimesh.Trimesh:
    """The square [-half, half]^2 at height z facing +Z, uv = ((x/half + 1)/2, (y/half + 1)/2)."""
    vertices = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    return trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], process=False)


PLANE_UV = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)


def textured_plane_glb(path, texture_uint8, **material):
    mesh = plane()
    pbr = trimesh.visual.material.PBRMaterial(name="quadrants", baseColorTexture=Image.fromarray(texture_uint8),
                                              **material)
    mesh.visual = trimesh.visual.TextureVisuals(uv=PLANE_UV, material=pbr)
    scene = trimesh.Scene()
    scene.add_geometry(mesh, node_name="sign", geom_name="sign_mesh")
    scene.export(path)
    return path


def ones_envmap(path):
    """A 8 x 4 equirectangular EXR of radiance 1 everywhere."""
    ones = np.ones((4, 8), np.float32)
    write_exr(path, {"R": ones, "G": ones, "B": ones})
    return path


def render_from_above(mi, scene, folder, height=3.0, res=32, spp=64, fov=40.0):
    """One view from (0, 0, height) looking down -Z (image up = +Y). Returns (ViewImages,
    hit points of the pixel-centre rays with the plane z = 0 [H, W, 3])."""
    paths = write_meshes(scene, folder / "meshes")
    loaded = mi.load_dict(scene_dict(mi, scene, paths, max_depth=8))
    c2w = np.eye(4)
    c2w[2, 3] = height
    intrinsics = Intrinsics.from_fov(res, res, fov)
    images = render_view(mi, loaded, c2w, intrinsics, spp, seed=1)
    origins, directions = pixel_rays(c2w, intrinsics)
    t = -origins[..., 2] / directions[..., 2]
    return images, origins + t[..., None] * directions


def quadrant_masks(points, margin=1.5 / 16):
    """Pixels whose plane point lies inside a texture quadrant by at least `margin` in uv
    (bilinear filtering reaches half a texel, 1/32, and a pixel's footprint ~1/60 beyond
    its centre). {quadrant: [H, W] bool}."""
    u, v = (points[..., 0] + 1) / 2, (points[..., 1] + 1) / 2
    inside = lambda x, lo, hi: (x > lo + margin) & (x < hi - margin)  # noqa: E731
    return {"top_left": inside(u, 0, 0.5) & inside(v, 0.5, 1), "top_right": inside(u, 0.5, 1) & inside(v, 0.5, 1),
            "bottom_left": inside(u, 0, 0.5) & inside(v, 0, 0.5), "bottom_right": inside(u, 0.5, 1) & inside(v, 0, 0.5)}


def assert_quadrants_match(images, points, expected_linear: dict, spp: int):
    for name, mask in quadrant_masks(points).items():
        assert mask.sum() >= 20, name
        assert (images.rgba[mask][:, 3] > 0.999).all()
        measured = images.rgba[mask][:, :3].mean(axis=0)
        albedo = np.asarray(expected_linear[name])
        hoeffding = 1.5 * albedo * math.sqrt(math.log(2 / DELTA) / (2 * spp * mask.sum())) + 1e-4
        np.testing.assert_array_less(np.abs(measured - albedo), hoeffding, err_msg=name)
        standard_error = images.rgba[mask][:, :3].std(axis=0, ddof=1) / math.sqrt(mask.sum())
        np.testing.assert_array_less(np.abs(measured - albedo), 6 * standard_error + 1e-4, err_msg=name)


def test_glb_base_colour_texture_is_rendered_texel_for_texel(tmp_path, mi):
    """The GLB's sRGB texture, decoded to linear, is what a uniformly lit plane shows,
    with the image's top-left quadrant at the plane's (-x, +y) corner (uv v up)."""
    glb = textured_plane_glb(tmp_path / "sign.glb", quadrant_texture())
    scene = make_scene(f"mesh:{glb}", 0, envmap=ones_envmap(tmp_path / "ones.exr"))
    assert [s.name for s in scene.shapes] == ["sign"]
    images, points = render_from_above(mi, scene, tmp_path)
    expected = {name: srgb_to_linear(np.asarray(rgb) / 255) for name, rgb in QUADRANTS.items()}
    assert_quadrants_match(images, points, expected, spp=64)
    # 16 texels across the 2-unit plane: the finest texture detail a field must resolve.
    assert scene.needs.finest_texture_period == pytest.approx(2 / 16)


def test_glb_base_colour_factor_multiplies_the_texture(tmp_path, mi):
    factor = (0.5, 1.0, 0.25, 1.0)
    glb = textured_plane_glb(tmp_path / "sign.glb", quadrant_texture(), baseColorFactor=factor)
    scene = make_scene(f"mesh:{glb}", 0, envmap=ones_envmap(tmp_path / "ones.exr"))
    images, points = render_from_above(mi, scene, tmp_path)
    # The factor as the file states it (trimesh's exporter writes it 8-bit: 0.25 -> 64/255).
    stated = gltf_json(".glb", glb.read_bytes())["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"]
    np.testing.assert_allclose(stated[:3], factor[:3], atol=0.5 / 255)
    expected = {name: srgb_to_linear(np.asarray(rgb) / 255) * np.asarray(stated[:3]) for name, rgb in QUADRANTS.items()}
    assert_quadrants_match(images, points, expected, spp=64)


def write_obj_plane(folder, mtl_body: str, name="sign", extra_groups=""):
    """A plane OBJ (uv as PLANE_UV, normals +Z) using material `paint` from sign.mtl."""
    (folder / "sign.mtl").write_text(mtl_body)
    obj = folder / f"{name}.obj"
    obj.write_text("mtllib sign.mtl\nv -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\n"
                   "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\n"
                   f"o {name}\nusemtl paint\nf 1/1/1 2/2/1 3/3/1 4/4/1\n" + extra_groups)
    return obj


def test_obj_mtl_texture_beside_the_file_is_rendered(tmp_path, mi):
    Image.fromarray(quadrant_texture()).save(tmp_path / "paint.png")
    obj = write_obj_plane(tmp_path, "newmtl paint\nKd 1 1 1\nmap_Kd paint.png\n")
    scene = make_scene(f"mesh:{obj}", 0, envmap=ones_envmap(tmp_path / "ones.exr"))
    assert str(tmp_path / "paint.png") in scene.params["inputs"]  # the texture is an input too
    assert scene.shapes[0].mesh().normals is not None  # the file's normals
    images, points = render_from_above(mi, scene, tmp_path)
    expected = {name: srgb_to_linear(np.asarray(rgb) / 255) for name, rgb in QUADRANTS.items()}
    assert_quadrants_match(images, points, expected, spp=64)


def test_obj_kd_without_texture_and_vertex_colours(tmp_path, mi):
    """Kd is linear albedo; OBJ vertex colours (v x y z r g b) multiply Kd."""
    obj = write_obj_plane(tmp_path, "newmtl paint\nKd 0.5 0.8 0.2\n")
    scene = make_scene(f"mesh:{obj}", 0, envmap=ones_envmap(tmp_path / "ones.exr"))
    images, points = render_from_above(mi, scene, tmp_path)
    expected = dict.fromkeys(QUADRANTS, (0.5, 0.8, 0.2))
    assert_quadrants_match(images, points, expected, spp=16)

    coloured = tmp_path / "coloured.obj"
    coloured.write_text(obj.read_text().replace("v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\n",
                                                "v -1 -1 0 0.6 0.5 1\nv 1 -1 0 0.6 0.5 1\n"
                                                "v 1 1 0 0.6 0.5 1\nv -1 1 0 0.6 0.5 1\n"))
    scene = make_scene(f"mesh:{coloured}", 0, envmap=ones_envmap(tmp_path / "ones.exr"))
    images, points = render_from_above(mi, scene, tmp_path / "c")
    expected = dict.fromkeys(QUADRANTS, (0.3, 0.4, 0.2))
    assert_quadrants_match(images, points, expected, spp=16)


def test_glb_vertex_colours_are_rendered(tmp_path, mi):
    mesh = plane()
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=np.tile([51, 128, 204, 255], (4, 1)))
    glb = tmp_path / "painted.glb"
    trimesh.Scene(mesh).export(glb)
    scene = make_scene(f"mesh:{glb}", 0, envmap=ones_envmap(tmp_path / "ones.exr"))
    images, points = render_from_above(mi, scene, tmp_path)
    expected = dict.fromkeys(QUADRANTS, np.array([51, 128, 204]) / 255)  # COLOR_0 is linear
    assert_quadrants_match(images, points, expected, spp=16)


def test_roughness_and_metallic_use_the_principled_bsdf(tmp_path, mi):
    glb = textured_plane_glb(tmp_path / "metal.glb", quadrant_texture(), roughnessFactor=0.3, metallicFactor=1.0)
    scene = make_scene(f"mesh:{glb}", 0)
    material = scene.shapes[0].material
    assert (material.roughness, material.metallic) == pytest.approx((0.3, 1.0))
    assert scene.needs.view_dependent
    paths = write_meshes(scene, tmp_path / "meshes")
    entry = scene_dict(mi, scene, paths, max_depth=4)["sign"]
    assert entry["bsdf"]["bsdf"]["type"] == "principled"
    images, _ = render_from_above(mi, scene, tmp_path, res=16, spp=4)
    assert np.isfinite(images.rgba).all() and images.hit[4:12, 4:12].all()


def test_metallic_roughness_texture_scales_by_the_factors(tmp_path, mi):
    """glTF packs roughness in G and metallic in B (linear); the factors multiply them.
    A texture saying 'not metal' must win over metallicFactor 1 (no chrome by default)."""
    packed = np.zeros((4, 4, 3), np.uint8)
    packed[..., 1], packed[..., 2] = 204, 0  # roughness 0.8, metallic 0
    packed[0, 0, 2] = 255  # one metal texel
    mesh = plane()
    pbr = trimesh.visual.material.PBRMaterial(name="painted", baseColorFactor=(1.0, 1.0, 1.0, 1.0),
                                              metallicRoughnessTexture=Image.fromarray(packed),
                                              roughnessFactor=0.5, metallicFactor=1.0)
    mesh.visual = trimesh.visual.TextureVisuals(uv=PLANE_UV, material=pbr)
    trimesh.Scene(mesh).export(tmp_path / "painted.glb")
    material = make_scene(f"mesh:{tmp_path / 'painted.glb'}", 0).shapes[0].material
    np.testing.assert_allclose(material.roughness_texture.pixels[..., 0], 0.8 * 0.5, atol=1e-6)
    expected_metal = np.zeros((4, 4))
    expected_metal[0, 0] = 1.0
    np.testing.assert_allclose(material.metallic_texture.pixels[..., 0], expected_metal, atol=1e-6)
    scene = make_scene(f"mesh:{tmp_path / 'painted.glb'}", 0)
    entry = scene_dict(mi, scene, write_meshes(scene, tmp_path / "meshes"), max_depth=4)
    bsdf = entry[scene.shapes[0].name]["bsdf"]["bsdf"]
    assert bsdf["type"] == "principled" and bsdf["metallic"]["type"] == "bitmap"
    images, _ = render_from_above(mi, scene, tmp_path, res=16, spp=4)
    assert np.isfinite(images.rgba).all() and images.hit[4:12, 4:12].all()


def two_object_glb(path):
    """A 1-unit box 'crate' at the origin and a ball 'ball' (radius 0.5) whose node sits
    at (2, 0, 1): the scene graph's transforms place them."""
    box = trimesh.creation.box(extents=(1, 1, 1))
    ball = trimesh.creation.icosphere(2, radius=0.5)
    scene = trimesh.Scene()
    scene.add_geometry(box, node_name="crate", geom_name="crate_mesh")
    scene.add_geometry(ball, node_name="ball", geom_name="ball_mesh",
                       transform=trimesh.transformations.translation_matrix([2, 0, 1]))
    scene.export(path)
    return path


def test_objects_keep_their_names_and_transforms(tmp_path):
    glb = two_object_glb(tmp_path / "pair.glb")
    scene = make_scene(f"mesh:{glb}", 0, units="keep")
    shapes = {s.name: s for s in scene.shapes}
    assert set(shapes) == {"crate", "ball"}
    np.testing.assert_allclose(shapes["crate"].mesh().bounds(), [[-0.5] * 3, [0.5] * 3], atol=1e-12)
    np.testing.assert_allclose(shapes["ball"].mesh().vertices.mean(axis=0), [2, 0, 1], atol=1e-9)
    # Normalised: all objects together span [-1, 1] along the largest extent (x: -0.5 .. 2.5).
    normalised = make_scene(f"mesh:{glb}", 0)
    scale, shift = normalised.params["to_scene"]["scale"], np.array(normalised.params["to_scene"]["translation"])
    assert scale == pytest.approx(2 / 3)
    for shape in normalised.shapes:
        np.testing.assert_allclose(shape.mesh().vertices, shapes[shape.name].mesh().vertices * scale + shift,
                                   atol=1e-12)


def test_obj_groups_become_named_objects(tmp_path):
    """o/g groups are objects; a group using two materials is split as group_material."""
    obj = tmp_path / "parts.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\n"
                   "o first\nf 1 2 3\ng second\nf 1 3 4\no third\nusemtl a\nf 1 2 5\nusemtl b\nf 2 6 5\n")
    names = [s.name for s in make_scene(f"mesh:{obj}", 0).shapes]
    assert names == ["first", "second", "third_a", "third_b"]


def test_dataset_carries_object_names_and_units(tmp_path, make_dataset):
    """meshes/ holds one PLY per object under its name; --units keep leaves meshes/ and
    scene.json in the file's coordinates."""
    glb = two_object_glb(tmp_path / "pair.glb")
    root = make_dataset(tmp_path / "ds", scene=f"mesh:{glb}", views=1, val_views=0, test_views=0, width=16,
                        height=16, spp=2, units="keep")
    assert sorted(p.name for p in (root / "meshes").glob("*.ply")) == ["ball.ply", "crate.ply"]
    ball = trimesh.load(root / "meshes" / "ball.ply", process=False)
    np.testing.assert_allclose(ball.vertices.mean(axis=0), [2, 0, 1], atol=1e-6)
    doc = json.loads((root / "scene.json").read_text())
    assert doc["scene"]["params"]["units"] == "keep"
    assert sorted(s["name"] for s in doc["scene"]["shapes"]) == ["ball", "crate"]


def test_instance_ids_follow_the_objects(tmp_path, make_dataset):
    """Each object of the file is one shape, so it has its own instance id, named in the
    legend; every pixel of an id back-projects (exact depth) onto that object's mesh."""
    from nerfgauge.core.camera import pixel_rays
    from nerfgauge.core.dataset import Dataset

    glb = two_object_glb(tmp_path / "pair.glb")
    root = make_dataset(tmp_path / "ds", scene=f"mesh:{glb}", views=1, val_views=0, test_views=3, width=24,
                        height=24, spp=2, units="keep", layout="sphere")
    ds = Dataset(root)
    names = ds.instance_names()
    assert sorted(names.values()) == ["ball", "crate"]
    meshes = {name: trimesh.load(root / "meshes" / f"{name}.ply", process=False) for name in names.values()}
    seen = set()
    for index, c2w in enumerate(ds.c2w("test")):
        ids, depth = ds.instance("test", index), ds.depth("test", index)
        origins, directions = pixel_rays(c2w, ds.intrinsics("test"))
        for number in np.unique(ids[ids > 0]):
            name = names[int(number)]
            pick = ids == number
            points = origins[pick] + depth[pick][:, None] * directions[pick]
            _, distance, _ = trimesh.proximity.closest_point(meshes[name], points)
            # exact depth in float32 on unit-sized objects: float rounding, far below a pixel
            assert distance.max() < 1e-4, (name, distance.max())
            seen.add(name)
    assert seen == {"ball", "crate"}


def test_units_keep_depth_is_the_analytic_distance_in_file_units(tmp_path, mi):
    """A 100-unit square at z = 5 seen from z = 35: every pixel-centre ray that meets the
    square inside (by 1 unit) hits it at t = 30 / |d_z|, to float32 precision."""
    big = plane(half=50.0, z=5.0)
    big.export(tmp_path / "big.ply")
    scene = make_scene(f"mesh:{tmp_path / 'big.ply'}", 0, units="keep")
    paths = write_meshes(scene, tmp_path / "meshes")
    loaded = mi.load_dict(scene_dict(mi, scene, paths, max_depth=2))
    c2w = np.eye(4)
    c2w[2, 3] = 35.0
    intrinsics = Intrinsics.from_fov(24, 24, 90.0)
    images = render_view(mi, loaded, c2w, intrinsics, 1, seed=0)
    origins, directions = pixel_rays(c2w, intrinsics)
    t = 30.0 / -directions[..., 2]
    point = origins + t[..., None] * directions
    inside = (np.abs(point[..., :2]) < 49).all(-1)
    assert inside.sum() > 100 and images.hit[inside].all()
    np.testing.assert_allclose(images.distance[inside], t[inside], rtol=1e-5)


# --- bad input ----------------------------------------------------------------------------

CLI_TINY = ["--res", "16", "--views", "1", "--val-views", "0", "--test-views", "0", "--spp", "1", "--quiet"]


def run_cli(capsys, *argv):
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err.strip().splitlines()


def test_missing_texture_falls_back_to_base_colour_with_one_warning(tmp_path, capsys, mi):
    obj = write_obj_plane(tmp_path, "newmtl paint\nKd 0.5 0.8 0.2\nmap_Kd gone.png\n")
    scene = make_scene(f"mesh:{obj}", 0, envmap=ones_envmap(tmp_path / "ones.exr"))
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning:") and "gone.png" in err[0]
    assert scene.shapes[0].material.texture is None
    images, points = render_from_above(mi, scene, tmp_path, spp=16)
    assert_quadrants_match(images, points, dict.fromkeys(QUADRANTS, (0.5, 0.8, 0.2)), spp=16)


@pytest.mark.parametrize("mtl, texture, expected", [
    ("newmtl paint\nKd 1 1 1\nmap_Kd paint.png\n", b"not a png at all", "cannot read texture"),
    ("newmtl paint\nKd 1 1 1\nd 0.5\n", None, "transparent"),
    ("newmtl paint\nKd 1 1 1\nmap_Ke glow.png\n", None, "emission texture"),
])
def test_bad_obj_material_is_one_line_and_exit_2(tmp_path, capsys, mtl, texture, expected):
    if texture is not None:
        (tmp_path / "paint.png").write_bytes(texture)
    obj = write_obj_plane(tmp_path, mtl)
    code, err = run_cli(capsys, "generate", f"mesh:{obj}", "--out", tmp_path / "out", *CLI_TINY)
    assert code == 2 and len(err) == 1 and expected in err[0], err
    assert not (tmp_path / "out").exists()


def panel_gltf(folder, image_uri="wood.png"):
    """A hand-written .gltf: one quad named 'panel' whose material 'wood' takes its
    base-colour texture from an image file beside it."""
    import base64

    positions = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    data = positions.tobytes() + uv.tobytes() + np.array([0, 1, 2, 0, 2, 3], np.uint16).tobytes()
    document = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "panel"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0}]}],
        "materials": [{"name": "wood", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0},
                                                                "baseColorFactor": [0.5, 0.4, 0.3, 1.0]}}],
        "textures": [{"source": 0}], "images": [{"uri": image_uri}],
        "buffers": [{"uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode(),
                     "byteLength": len(data)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 48}, {"buffer": 0, "byteOffset": 48, "byteLength": 32},
                        {"buffer": 0, "byteOffset": 80, "byteLength": 12}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [-1, -1, 0],
                       "max": [1, 1, 0]},
                      {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
                      {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"}]}
    path = folder / "panel.gltf"
    path.write_text(json.dumps(document))
    return path


def test_gltf_texture_beside_the_file_missing_or_unreadable(tmp_path, capsys):
    gltf = panel_gltf(tmp_path)
    scene = make_scene(f"mesh:{gltf}", 0)  # wood.png is missing: one warning, base colour
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning:") and "wood.png" in err[0]
    assert scene.shapes[0].name == "panel" and scene.shapes[0].material.texture is None
    assert scene.shapes[0].material.base_color == (0.5, 0.4, 0.3)  # as the file states it, not 8-bit

    Image.fromarray(quadrant_texture()).save(tmp_path / "wood.png")
    scene = make_scene(f"mesh:{gltf}", 0)
    assert scene.shapes[0].material.texture.width == 16
    assert str(tmp_path / "wood.png") in scene.params["inputs"]

    (tmp_path / "wood.png").write_bytes(b"not an image")
    code, err = run_cli(capsys, "generate", f"mesh:{gltf}", "--out", tmp_path / "out", *CLI_TINY)
    assert code == 2 and len(err) == 1 and "cannot read texture" in err[0] and "wood.png" in err[0]
    assert not (tmp_path / "out").exists()


def test_transparent_glb_material_is_refused(tmp_path, capsys):
    glb = textured_plane_glb(tmp_path / "glass.glb", quadrant_texture(), alphaMode="BLEND")
    code, err = run_cli(capsys, "generate", f"mesh:{glb}", "--out", tmp_path / "out", *CLI_TINY)
    assert code == 2 and len(err) == 1 and "transparent" in err[0]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name, content", [("sky.exr", b"\x76\x2f\x31\x01garbage"), ("sky.hdr", b"P6 not hdr"),
                                           ("sky.png", b"\x89PNG"), ("absent.exr", None)])
def test_envmap_that_is_not_an_image_is_one_line_and_exit_2(tmp_path, capsys, name, content):
    if content is not None:
        (tmp_path / name).write_bytes(content)
    glb = two_object_glb(tmp_path / "pair.glb")
    code, err = run_cli(capsys, "generate", f"mesh:{glb}", "--out", tmp_path / "out", "--envmap", tmp_path / name,
                        *CLI_TINY)
    assert code == 2 and len(err) == 1 and name in err[0], err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("rotation, lit", [(90.0, True), (-90.0, False)])
def test_envmap_orientation_and_rotation(tmp_path, mi, rotation, lit):
    """A map whose left half (columns u < 0.5) has radiance 1 and right half 0 lights the
    world's +X half-space (u = atan2(x, y) / 2pi, docs/scene-files.md); turned +90 degrees
    about +Z that is the +Y half-space. A Kd 0.5 plane facing +Y then sees radiance 1 over
    its whole hemisphere (L = 0.5) and, turned -90 degrees, none (L = 0). Bilinear lookup
    blurs the boundary within one texel (2pi/64) of grazing, whose cosine-weighted share of
    the hemisphere is sin^2(2pi/64) < 0.01."""
    half = np.zeros((32, 64), np.float32)
    half[:, :32] = 1
    write_exr(tmp_path / "half.exr", {"R": half, "G": half, "B": half})
    (tmp_path / "sign.mtl").write_text("newmtl paint\nKd 0.5 0.5 0.5\n")
    obj = tmp_path / "wall.obj"
    obj.write_text("mtllib sign.mtl\nv -1 0 -1\nv -1 0 1\nv 1 0 1\nv 1 0 -1\nvn 0 1 0\n"
                   "usemtl paint\nf 1//1 2//1 3//1 4//1\n")
    scene = make_scene(f"mesh:{obj}", 0, envmap=tmp_path / "half.exr", envmap_rotation=rotation)
    paths = write_meshes(scene, tmp_path / "meshes")
    loaded = mi.load_dict(scene_dict(mi, scene, paths, max_depth=8))
    c2w = look_at((0, 3, 0), (0, 0, 0))
    intrinsics = Intrinsics.from_fov(16, 16, 30.0)
    spp = 16
    images = render_view(mi, loaded, c2w, intrinsics, spp, seed=2)
    origins, directions = pixel_rays(c2w, intrinsics)
    point = origins + (-origins[..., 1] / directions[..., 1])[..., None] * directions
    inside = (np.abs(point[..., 0]) < 0.9) & (np.abs(point[..., 2]) < 0.9)
    assert inside.sum() > 50
    albedo = 0.5
    bound = 1.5 * albedo * math.sqrt(math.log(2 / DELTA) / (2 * spp * inside.sum())) + albedo * math.sin(2 * math.pi / 64) ** 2
    expected = albedo if lit else 0.0
    np.testing.assert_array_less(np.abs(images.rgba[inside][:, :3].mean(axis=0) - expected), bound)


def test_envmap_is_recorded_with_hash_and_rotation(tmp_path):
    sky = ones_envmap(tmp_path / "ones.exr")
    scene = make_scene(f"mesh:{two_object_glb(tmp_path / 'pair.glb')}", 0, envmap=sky, envmap_rotation=30)
    import hashlib

    digest = hashlib.sha256(sky.read_bytes()).hexdigest()
    assert scene.params["envmap"] == {"path": str(sky), "sha256": digest, "rotation": 30.0}
    assert scene.params["inputs"][str(sky)] == digest
    assert json.dumps(scene.to_json())  # JSON-able: the pixels are not in it


def test_radiance_hdr_reader_decodes_flat_and_run_length_scanlines(tmp_path):
    """RGBE: value = mantissa * 2^(exponent - 136). A flat file and a new-style RLE file
    (width 8: each channel one run) decode to the same pixels."""
    header = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 2 +X 8\n"
    pixel = bytes([128, 64, 32, 129])  # (128, 64, 32) * 2^(129 - 136) = (1, 0.5, 0.25)
    (tmp_path / "flat.hdr").write_bytes(header + pixel * 16)
    rle_row = bytes([2, 2, 0, 8]) + b"".join(bytes([128 + 8, value]) for value in pixel)
    (tmp_path / "rle.hdr").write_bytes(header + rle_row * 2)
    for name in ("flat.hdr", "rle.hdr"):
        light = read_envmap(tmp_path / name)
        assert light.pixels.shape == (2, 8, 3)
        np.testing.assert_allclose(light.pixels, np.broadcast_to([1.0, 0.5, 0.25], (2, 8, 3)))
    with pytest.raises(InputError, match="truncated"):
        read_envmap(_write(tmp_path / "short.hdr", header + pixel * 3))


def _write(path, data):
    path.write_bytes(data)
    return path


def test_obj_material_missing_from_its_mtl_is_grey_with_one_warning(tmp_path, capsys):
    obj = write_obj_plane(tmp_path, "newmtl other\nKd 1 0 0\n")
    scene = make_scene(f"mesh:{obj}", 0)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning:") and "'paint'" in err[0]
    assert scene.shapes[0].material.color == (0.6, 0.6, 0.6)
