"""The COLMAP export of a dataset: `nerfgauge export colmap DS [--points KIND[:COUNT]]`,
and the last step of `nerfgauge generate` (the same code, so the bytes agree).

What it adds to a dataset (docs/conventions.md, "COLMAP"):

  images/r_000.png ...        the train PNGs where COLMAP-based loaders (gsplat, nerfstudio's
                              colmap dataparser, the 3DGS code) look: hard links to
                              train/r_000.png (a byte copy where the file system has none),
                              so every tool sees ordinary files inside the dataset
  sparse/0/cameras.bin, images.bin, points3D.bin and the same as .txt
                              one PINHOLE camera, the train images' exact poses, the initial
                              points (generate/points.py)
  sparse/0/points3D.ply       the points again, as a PLY (x y z nx ny nz red green blue),
                              named by transforms.json "ply_file_path" (nerfstudio) and where
                              the 3DGS code looks for it

and records the points (kind, count, distance to the surface) in scene.json "points" and
the model in scene.json "colmap".

The export is a function of the dataset's verified files and the points spec, so it is
byte-deterministic, and `generate --points X` equals `generate` then `export colmap
--points X` byte for byte. Into an existing dataset, under the folder's write lock: the new
files are written first (atomically each), then manifest.json is removed (the dataset
reads as incomplete, never as valid with a stale manifest), transforms.json and scene.json
are replaced, files of an earlier export no longer produced are removed, and manifest.json
is written last, hashing every file. Before removing the manifest, a rollback journal
(`.nerfgauge-export.json`: the manifest and the JSON files about to be replaced) is written:
a kill in between leaves a dataset without a manifest, which readers refuse in one line,
and the next `export colmap` (or `generate` with the same recipe) restores and redoes it.

The journal is data, not instructions: it may hold only the two files an export replaces
(transforms.json, scene.json), each a JSON object, and a manifest that parses, names only
relative paths inside the dataset (no `..`, no absolute path, no link), lists both files
with the hashes of the journal's own texts, and whose every other entry outside images/
and sparse/0/ matches the file on disk (hashes recomputed). A journal that is not so is
refused in one line and nothing is restored; a valid one is restored, and the manifest
written is the one the export writes for that list (hashed from the files, not copied).

A scene whose geometry no train view resolves (meshes smaller than a pixel's footprint, or
out of every view) gets its model without points and the reason in scene.json "points",
as a scene with no geometry does: the default `--points surface` never fails a dataset
after its views are rendered.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np

from nerfgauge.core import colmap, owned, validate
from nerfgauge.core import dataset as dataset_module
from nerfgauge.core.dataset import Dataset
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import json_bytes, json_from_bytes, link_or_copy_atomic, read_json, write_bytes_atomic
from nerfgauge.core.folders import folder_lock, read_marker
from nerfgauge.generate import points as points_module

MODEL_DIR = "sparse/0"
IMAGES_DIR = "images"
PLY = f"{MODEL_DIR}/points3D.ply"
JOURNAL = ".nerfgauge-export.json"  # hidden: not part of the manifest; exists only during an export
JOURNALED = ("scene.json", "transforms.json")  # the files an export replaces: all its journal may hold
NO_GEOMETRY = "no points: the scene has no geometry to sample"
NO_VISIBLE_SURFACE = "no points: no train view resolves the ground-truth meshes, so there is no surface to sample"
POINTS_NOTE = {
    "surface": "samples of the ground-truth meshes (uniform by area) that some train view sees; colour: mean of the "
               "8-bit sRGB train PNG pixels of the first 4 train views (in order) that see each",
    "random": "uniform in scene.json bounds, uniform random colours",
    "sfm": "pycolmap SIFT features of the train images, matched exhaustively, triangulated with the exact poses",
    "none": "no points",
}


def image_name(stem: str) -> str:
    """"train/r_007" -> "r_007.png": the name under images/ and in images.bin."""
    return stem.rsplit("/", 1)[-1] + ".png"


def check_exportable(ds: Dataset) -> None:
    """InputError unless COLMAP can state the train cameras exactly (pinhole, finite)."""
    cameras = ds.cameras("train")
    if not cameras.stems:
        raise InputError(f"dataset {ds.root} has no train views; the COLMAP model holds the train images")
    lenses = [lens for lens in cameras.lenses if lens is not None and not lens.is_pinhole]
    if lenses:
        raise InputError(f"dataset {ds.root}: the train views were rendered through a thin lens (aperture "
                         f"{lenses[0].aperture_radius:g}), which no COLMAP camera model can express")
    colmap.camera_model(cameras.intrinsics, cameras.distortion)
    names = [image_name(stem) for stem in cameras.stems]
    if len(set(names)) != len(names):
        raise InputError(f"dataset {ds.root}: train frame names collide under images/ ({len(names) - len(set(names))})")


def compute_points(ds: Dataset, spec: points_module.PointsSpec, seed: int, vertices, faces):
    if spec.kind in ("surface", "random") and spec.count is None:
        cameras = ds.cameras("train")
        spec = points_module.PointsSpec(spec.kind, points_module.default_count(
            len(cameras.stems), cameras.intrinsics.width, cameras.intrinsics.height))
    if spec.kind == "surface":
        return points_module.surface_points(ds, spec.count, seed, vertices, faces)
    if spec.kind == "random":
        if ds.bounds is None:
            raise InputError(f"dataset {ds.root} has no scene bounds in scene.json for random points")
        return points_module.random_points(spec.count, seed, np.asarray(ds.bounds, np.float64))
    if spec.kind == "sfm":
        return sfm_points(ds, spec.count, seed)
    return points_module.InitialPoints(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros((0, 3)), np.zeros(0))


def require_pycolmap(what: str):
    try:
        import pycolmap  # pycolmap: an optional extra, only for --points sfm and nerfgauge sfm
    except ImportError:
        raise InputError(f"{what} needs pycolmap, which is not installed; pip install 'nerfgauge[colmap]'") from None
    if not os.environ.get("NERFGAUGE_DEBUG"):
        pycolmap.logging.minloglevel = 3  # COLMAP's progress log would bury the command's one line
    return pycolmap


def stage_images(ds: Dataset, folder: Path) -> list[str]:
    """Write the train PNGs (bytes verified against the manifest) into `folder` under
    their images/ names. Returns the names in train order."""
    cameras = ds.cameras("train")
    names = []
    for stem in cameras.stems:
        name = image_name(stem)
        write_bytes_atomic(folder / name, ds.read_bytes(stem + ".png", stem))
        names.append(name)
    return names


def sfm_options(pycolmap, intrinsics):
    """Extraction and matching options shared by `--points sfm` and `nerfgauge sfm`:
    single-threaded (determinism), CPU SIFT."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(repr(float(v)) for v in (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = 1
    extraction.use_gpu = False
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 1
    matching.use_gpu = False
    return reader, extraction, matching


MATCH_BLOCK = 50  # images per block of exhaustive matching (COLMAP's default, stated)


def extract_and_match(pycolmap, database: Path, image_dir: Path, names, intrinsics) -> None:
    reader, extraction, matching = sfm_options(pycolmap, intrinsics)
    pycolmap.set_random_seed(0)
    pycolmap.extract_features(database, image_dir, image_names=list(names), camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    # every pair of images is matched, a block of MATCH_BLOCK images against another at a time
    # (COLMAP caches the features of a few blocks): memory does not grow with the image count
    pairing = pycolmap.ExhaustivePairingOptions()
    pairing.block_size = MATCH_BLOCK
    pycolmap.match_exhaustive(database, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)


def sfm_points(ds: Dataset, count, seed: int) -> points_module.InitialPoints:
    """Features of the train images triangulated with the exact poses (pycolmap)."""
    pycolmap = require_pycolmap("--points sfm")
    cameras = ds.cameras("train")
    if cameras.distortion is not None:
        raise InputError(f"dataset {ds.root}: --points sfm matches features with a PINHOLE camera, and the train views "
                         f"are distorted ({cameras.distortion.to_text()}); use --points surface or random")
    with tempfile.TemporaryDirectory(prefix="nerfgauge-sfm-") as work:
        work = Path(work)
        owned.make_folder(work / "images")
        names = stage_images(ds, work / "images")
        extract_and_match(pycolmap, work / "database.db", work / "images", names, cameras.intrinsics)
        known = work / "known"
        colmap.write_model(known, [colmap.pinhole_camera(cameras.intrinsics)], colmap.model_images(cameras.c2w, names),
                           colmap.Points.make(np.zeros((0, 3)), np.zeros((0, 3))))
        owned.make_folder(work / "triangulated")
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = 1
        reconstruction = pycolmap.triangulate_points(pycolmap.Reconstruction(known), work / "database.db",
                                                     work / "images", work / "triangulated", options=options)
    by_name = {name: index for index, name in enumerate(names, start=1)}
    image_ids = {image_id: by_name[image.name] for image_id, image in reconstruction.images.items()}
    entries = []
    for point_id, point in reconstruction.points3D.items():
        track = sorted((image_ids[e.image_id], e.point2D_idx) for e in point.track.elements)
        entries.append((-len(track), float(point.error), tuple(point.xyz), point_id, point, track))
    if len(entries) < points_module.MIN_SFM_POINTS:
        raise InputError(f"dataset {ds.root}: too few feature matches for sfm points ({len(entries)} triangulated, "
                         f"need {points_module.MIN_SFM_POINTS}); the scene may be textureless")
    entries.sort(key=lambda e: e[:3])  # longest track first, then smallest error: the best COUNT
    if count is not None:
        entries = entries[:count]
    entries.sort(key=lambda e: e[2])  # written in a content order, not COLMAP's id order
    xyz = np.array([e[2] for e in entries])
    rgb = np.array([np.asarray(e[4].color) for e in entries], np.uint8)
    error = np.array([e[1] for e in entries])
    new_id = {e[3]: k for k, e in enumerate(entries, start=1)}
    points2D = {}
    for image_id, image in reconstruction.images.items():
        xys = np.array([p.xy for p in image.points2D], np.float64).reshape(-1, 2)
        ids = np.array([new_id.get(p.point3D_id, -1) if p.has_point3D() else -1 for p in image.points2D], np.int64)
        points2D[image_ids[image_id]] = (xys, ids)
    tracks = [np.array(e[5], np.int64).reshape(-1, 2) for e in entries]
    return points_module.InitialPoints(xyz, rgb, np.zeros_like(xyz), error, tracks, points2D)


def _link_or_copy(source: Path, target: Path) -> None:
    """`target` becomes a hard link to `source` (atomically), or a copy where links fail."""
    if target.is_symlink() or (target.exists() and not target.is_file()):
        raise InputError(f"refusing to replace {target}: it is not a regular file")
    if target.is_file() and os.path.samefile(source, target):
        return  # already the link (rename(2) between two links of one file would do nothing)
    link_or_copy_atomic(source, target)


def export_colmap(root, spec="surface", *, progress=None) -> dict:
    """Write the COLMAP model, images/ and initial points into the dataset `root`, update
    transforms.json and scene.json and rewrite manifest.json (module docstring). The caller
    holds the folder's write lock. Returns {"points": n, "seconds": s, ...}."""
    start = time.perf_counter()
    spec = points_module.parse_spec(spec)
    root = Path(root)
    ds = Dataset(root)
    check_exportable(ds)
    if spec.kind == "sfm":
        require_pycolmap("--points sfm")
    # The new manifest must not bless a file changed since it was written; the export's own
    # files (an earlier export, or one rolled back) are rewritten from verified ones anyway.
    changed = [rel for rel in dataset_module.verify_manifest(root)
               if not rel.startswith((f"{MODEL_DIR}/", f"{IMAGES_DIR}/"))]
    if changed:
        raise InputError(f"dataset {root}: {len(changed)} file(s) differ from its manifest.json (first: {changed[0]}); "
                         "regenerate it before exporting")
    seed = int(ds.scene.get("seed", 0)) if isinstance(ds.scene.get("seed", 0), int) else 0
    cameras = ds.cameras("train")
    note = POINTS_NOTE[spec.kind]
    if points_module.has_meshes(ds):
        vertices, faces = points_module.read_meshes(ds)
    else:  # a scene with no geometry (hard scene `empty`): nothing to sample or measure against
        vertices = faces = None
        if spec.kind == "surface":
            spec, note = points_module.parse_spec("none"), NO_GEOMETRY
    initial = compute_points(ds, spec, seed, vertices, faces)
    if spec.kind == "surface" and not len(initial.xyz):  # geometry, but no train view resolves it (`tiny` at 24 px)
        spec, note = points_module.parse_spec("none"), NO_VISIBLE_SURFACE
        initial = compute_points(ds, spec, seed, vertices, faces)
    if vertices is None:
        distance_record = {"mean": None, "p90": None, "max": None,
                           "method": "none: the scene has no ground-truth meshes"}
    elif not len(initial.xyz):
        distance_record = {"mean": None, "p90": None, "max": None, "method": "none: no points"}
    else:
        diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
        distance = points_module.distance_to_surface(initial.xyz, vertices, faces,
                                                     np.random.default_rng([seed, points_module.SEED_TAG, 1]),
                                                     initial.faces)
        distance_record = {**points_module.distance_summary(distance, diagonal), "diagonal": diagonal,
                           "method": points_module.DISTANCE_METHOD[
                               "surface" if initial.faces is not None else "search"]}
    names = [image_name(stem) for stem in cameras.stems]
    images = colmap.model_images(cameras.c2w, names)
    if initial.points2D is not None:
        images = [colmap.Image(i.image_id, i.qvec, i.tvec, i.camera_id, i.name, *initial.points2D.get(
            i.image_id, (np.zeros((0, 2)), np.zeros(0, np.int64)))) for i in images]
    camera = colmap.camera_model(cameras.intrinsics, cameras.distortion)
    model = colmap.model_files([camera], images,
                               colmap.Points.make(initial.xyz, initial.rgb, initial.error, initial.tracks))
    files = {f"{MODEL_DIR}/{name}": data for name, data in model.items()}
    if spec.kind != "none":
        files[PLY] = points_module.ply_bytes(initial, spec.kind)
    transforms = json_from_bytes(ds.read_bytes("transforms.json"), root / "transforms.json")
    transforms.pop("ply_file_path", None)
    if spec.kind != "none":
        transforms["ply_file_path"] = PLY
    scene = dict(ds.scene)
    scene["points"] = {
        "spec": spec.to_text(), "kind": spec.kind, "count": int(len(initial.xyz)),
        "requested": spec.count, "seed": seed, "note": note,
        "files": [f"{MODEL_DIR}/points3D.bin", f"{MODEL_DIR}/points3D.txt"] + ([PLY] if spec.kind != "none" else []),
        "distance_to_surface": distance_record,
    }
    scene["colmap"] = {
        "model": MODEL_DIR, "formats": ["bin", "txt"], "images": IMAGES_DIR,
        "images_are": "hard links to the train PNGs (copies where the file system has no links)",
        "camera": (f"{camera.model}: our intrinsics and lens distortion exactly (docs/conventions.md, "
                   "Lens distortion)" if cameras.distortion is not None
                   else "PINHOLE fx fy cx cy, our intrinsics exactly"),
        "convention": "world-to-camera quaternion (w, x, y, z) and translation, OpenCV axes (+X right, +Y down, "
                      "looks along +Z): c2w_cv = c2w_gl @ diag(1, -1, -1, 1); pixel (0, 0)'s centre at (0.5, 0.5)",
        "train_views": len(names),
    }
    _replace_in_dataset(root, files, {name: root / stem for name, stem in
                                      zip(names, (s + ".png" for s in cameras.stems))},
                        {"transforms.json": json_bytes(transforms), "scene.json": json_bytes(scene)},
                        ds.manifest_files)
    return {"points": int(len(initial.xyz)), "kind": spec.kind, "seconds": time.perf_counter() - start,
            "distance_mean": scene["points"]["distance_to_surface"]["mean"],
            "without_points": (f"without points ({note.removeprefix('no points: ')})"
                               if note in (NO_GEOMETRY, NO_VISIBLE_SURFACE) else None)}


def _replace_in_dataset(root: Path, files: dict, links: dict, replaced: dict, listed_before) -> None:
    """New files, then manifest removed, replaced files, stale export files removed, manifest
    last, listing what the old one listed (minus what was removed) and the new files."""
    for rel, data in files.items():
        owned.make_folder((root / rel).parent)
        write_bytes_atomic(root / rel, data)
    owned.make_folder(root / IMAGES_DIR)
    for name, source in links.items():
        _link_or_copy(source, root / IMAGES_DIR / name)
    manifest = root / dataset_module.MANIFEST
    if manifest.is_file():  # a rollback journal first: a killed export can be undone, then redone
        journal = {"manifest": manifest.read_text(),
                   "files": {rel: (root / rel).read_text() for rel in replaced if (root / rel).is_file()}}
        write_bytes_atomic(root / JOURNAL, json_bytes(journal))
        owned.remove_file(manifest)
    for rel, data in replaced.items():
        write_bytes_atomic(root / rel, data)
    keep = set(files) | {f"{IMAGES_DIR}/{name}" for name in links}
    removed = set()
    for folder in (root / IMAGES_DIR, root / MODEL_DIR):
        for path in sorted(folder.iterdir()):
            rel = path.relative_to(root).as_posix()
            if rel not in keep and not path.name.startswith(".") and (path.is_file() or path.is_symlink()):
                owned.remove_file(path)
                removed.add(rel)
    listed = (set(listed_before) - removed - {dataset_module.MANIFEST}) | keep | set(replaced)
    dataset_module.write_manifest(root, sorted(listed))
    owned.remove_file(root / JOURNAL)


def roll_back(root: Path) -> bool:
    """Undo an export killed after it removed manifest.json (its journal holds the manifest
    and the JSON files it replaced): the dataset is again what it was before. Call under
    the folder's lock. Returns whether there was anything to undo."""
    journal_path = root / JOURNAL
    if not journal_path.is_file() or (root / dataset_module.MANIFEST).is_file():
        return False
    texts, listed = read_journal(root)
    for rel, data in texts.items():
        write_bytes_atomic(root / rel, data)
    dataset_module.write_manifest(root, listed)
    owned.remove_file(journal_path)
    return True


def read_journal(root: Path) -> tuple[dict, list]:
    """The rollback journal checked as data (module docstring): ({name: bytes} to restore,
    the files the restored manifest lists). InputError, one line, when it is not one an
    export of this dataset wrote; nothing is written here."""
    path = root / JOURNAL
    refuse = "; refusing it (delete it and rerun nerfgauge generate for this dataset)"
    journal = read_json(path)
    if set(journal) != {"manifest", "files"} or not isinstance(journal["manifest"], str) \
            or not isinstance(journal["files"], dict):
        raise InputError(f"{path} is not an export journal (expected {{\"manifest\": text, \"files\": "
                         f"{{name: text}}}}, got keys {sorted(journal)[:4]}){refuse}")
    texts = {}
    for rel, text in journal["files"].items():
        if rel not in JOURNALED:
            raise InputError(f"{path} names {rel!r}; an export journal holds only {' and '.join(JOURNALED)}{refuse}")
        if not isinstance(text, str):
            raise InputError(f"{path}: {rel} should be the file's text, got {type(text).__name__}{refuse}")
        texts[rel] = text.encode()
        json_from_bytes(texts[rel], f"{path} ({rel})", finite=True)  # a JSON object, or one line
    where = f"{path} (manifest)"
    entries = validate.manifest(json_from_bytes(journal["manifest"].encode(), where, finite=True), where)
    listed = []
    for rel, entry in entries.items():  # relative, no "..": validate.manifest; no link: here
        owned.check_no_link(root / rel, "restore")
        validate.confine(root.resolve(), rel, where)
        exported = rel.startswith((f"{MODEL_DIR}/", f"{IMAGES_DIR}/"))
        if rel in texts:
            data = texts[rel]
        elif exported:  # rewritten by the export being undone, and by the one that follows
            if (root / rel).is_file():
                listed.append(rel)
            continue
        else:
            try:
                data = (root / rel).read_bytes()
            except OSError:
                raise InputError(f"{where} lists {rel}, which is not a readable file in {root}{refuse}") from None
        try:
            validate.content(data, entry, root / rel)
        except InputError:
            raise InputError(f"{where} does not match {rel} (sha256 or size differ from the file's content), so "
                             f"it is not the manifest of this dataset{refuse}") from None
        listed.append(rel)
    missing = sorted(set(texts) - set(entries))
    if missing:
        raise InputError(f"{where} does not list {missing[0]}, which the journal restores{refuse}")
    return texts, sorted(listed)


def export_current(root, spec) -> bool:
    """Whether the dataset at `root` already holds the export of `spec` (scene.json says so
    and manifest.json lists its model): `generate` then skips it when resuming."""
    root = Path(root)
    try:
        scene = read_json(root / "scene.json")
        manifest = dataset_module.read_manifest(root)
    except InputError:
        return False
    recorded = scene.get("points") if isinstance(scene.get("points"), dict) else {}
    return (recorded.get("spec") == points_module.parse_spec(spec).to_text()
            and all(f"{MODEL_DIR}/{name}" in manifest for name in colmap.model_files([], [], colmap.Points.make(
                np.zeros((0, 3)), np.zeros((0, 3))))))


def export_command(root, spec) -> dict:
    """`nerfgauge export colmap DS`: validate, then export under the dataset's write lock."""
    root = Path(root)
    spec = points_module.parse_spec(spec)
    if root.is_symlink():
        raise InputError(f"dataset {root} is a symbolic link; give the real path")
    if not root.is_dir():
        raise InputError(f"dataset folder not found: {root}")
    marker = read_marker(root)
    if marker is None or marker.get("kind") != "dataset":
        raise InputError(f"{root} is not a dataset nerfgauge generated (no dataset marker); "
                         "export writes only into nerfgauge's own datasets")
    if spec.kind == "sfm":
        require_pycolmap("--points sfm")
    if not (root / JOURNAL).is_file():
        check_exportable(Dataset(root))  # before the lock: bad input writes nothing
    with folder_lock(root):
        roll_back(root)  # an earlier export killed half-way: back to the dataset before it
        return export_colmap(root, spec)
