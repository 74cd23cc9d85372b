"""Prediction files, found and read: our own naming (`nerfgauge` format, described in
eval/evaluate.py's docstring) and other tools' render folders, read as they are:
`nerfgauge evaluate DATASET --pred DIR [--pred-format auto|nerfgauge|nerfstudio|nerfbaselines|folder]`.

Formats (checked against the tools' own writers):

- `nerfstudio`: `ns-render dataset --output-path OUT --split test` writes
  OUT/<split>/<output name>/<image name>.png|.jpg, the image name being the dataset image's
  path relative to the common folder of the split's images (nerfstudio scripts/render.py,
  DatasetRender). For a nerfgauge dataset's transforms.json that is r_007. Colour comes
  from rgba/ (straight alpha) when present, else rgb/ (composited by nerfstudio);
  raw-depth/<name>.npy.gz (float [H, W, 1], already divided by the dataparser scale) is
  read as depth of the --depth-kind given (nerfacto's is ray distance, splatfacto's z).
  The colour-mapped depth/ and gt-* folders are ignored. DIR may be OUT or OUT/<split>.
- `nerfbaselines`: a `nerfbaselines render` predictions folder: info.json (must parse as a
  JSON object), color/<relative name>.png, gt-color/ (the tool's copy of the ground truth,
  not used: ours is read from the dataset, hashes checked), optional depth/<name>.bin
  (int32 height, width, then float16 values: nerfbaselines io.save_depth).
- `folder`: plain PNG, JPEG or EXR colour images in DIR/<split>/ or DIR.
- `nerfgauge`: our own naming, r_007.png / r_007_depth.exr (find_prediction below).

`auto` picks nerfbaselines when DIR has info.json and color/, nerfstudio when it has
<split>/rgb(a)/ or rgb(a)/, nerfgauge when a file is named like r_<digits>[_kind].png|exr|npy,
folder when DIR/<split> or DIR holds other images, else nerfgauge (whose error names what
is missing).

Matching images to the split's frames (nerfstudio, nerfbaselines, folder): by file stem
when any image is named after a frame (then every image must be, and every frame must have
one: the names that do not match are reported), else by natural sort order (then the
counts must be equal). A split without frames is refused (nothing would be scored). Every
image's header is read first and its size checked against the ground truth's, and the
file's size against what that header's pixels can take, before it is read or decoded
(nerfgauge.core.images); depth files are bounded by the frame's size
(nerfgauge.core.bounded). Every problem is an InputError with one line.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from nerfgauge.core import bounded, dataset, validate
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json
from nerfgauge.core.images import image_header, linear_to_srgb, read_exr, read_jpeg, read_png

FORMATS = ("auto", "nerfgauge", "nerfstudio", "nerfbaselines", "folder")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")
NERFSTUDIO_COLOUR = ("rgba", "rgb")  # output names, first found wins
NERFGAUGE_FILE = re.compile(r"^r_\d+(?:_[A-Za-z]+)?\.(?:png|exr|npy)$")
DEPTH_SUFFIXES = {"distance": ("_depth", "_distance"), "z": ("_depth", "_zdepth")}
DEPTH_HEADER = {"distance": "ray_distance", "z": "z_depth"}
FRAME_FILE = re.compile(r"^(r_\d+)(?:_[A-Za-z]+)?\.(?:png|exr|npy)$")


@dataclass(frozen=True)
class PredictionFiles:
    """Where one frame's prediction lives; depth and opacity may be absent."""

    colour: Path
    depth: Optional[Path]
    opacity: Optional[Path]


# --- finding and reading predictions ----------------------------------------------------


def find_prediction(pred_dir: Path, stem: str, depth_kind: str) -> Optional[PredictionFiles]:
    """The files predicting frame `stem` (e.g. "test/r_007"), or None when there are none."""
    split, name = stem.split("/")[0], Path(stem).name
    found = {}
    for folder in (pred_dir / split, pred_dir):
        colour = next((folder / (name + ext) for ext in (".png", ".exr") if (folder / (name + ext)).is_file()), None)
        if colour is not None:
            found[folder] = colour
    if len(found) > 1:
        first, second = found.values()
        raise InputError(f"frame {stem}: predicted twice, as {first} and {second}; keep one")
    if not found:
        return None
    (folder, colour), = found.items()
    depth_names = [name + suffix + ext for suffix in DEPTH_SUFFIXES[depth_kind] for ext in (".exr", ".npy")]
    depth = next((folder / n for n in depth_names if (folder / n).is_file()), None)
    opacity = next((folder / (name + "_opacity" + ext) for ext in (".png", ".npy")
                    if (folder / (name + "_opacity" + ext)).is_file()), None)
    return PredictionFiles(colour, depth, opacity)


def extra_frames(pred_dir: Path, split: str, names: set) -> list[Path]:
    """Files in DIR/<split>/ or DIR that look like frames but belong to none of `names`."""
    extras = []
    for folder in (pred_dir / split, pred_dir):
        if folder.is_dir():
            for path in sorted(folder.iterdir()):
                match = FRAME_FILE.match(path.name)
                if path.is_file() and match and match.group(1) not in names:
                    extras.append(path)
    return extras


def require_finite(values: np.ndarray, path: Path) -> np.ndarray:
    finite = np.isfinite(values)
    if not finite.all():
        n_nan = int(np.isnan(values).sum())
        raise InputError(f"{path} holds {n_nan} NaN and {int((~finite).sum()) - n_nan} inf values "
                         f"out of {values.size}; no metrics computed")
    return values


def _sized(values: np.ndarray, path: Path, intrinsics) -> np.ndarray:
    if values.shape[:2] != (intrinsics.height, intrinsics.width):
        raise InputError(f"prediction {path} is {values.shape[1] if values.ndim > 1 else '?'}x{values.shape[0]}, "
                         f"the ground truth is {intrinsics.width}x{intrinsics.height}")
    return values


def _header_sized(path: Path, intrinsics) -> None:
    """An image prediction's header (read alone) states the ground truth's size: checked
    before the file is read or decoded."""
    header = image_header(path)
    _sized(np.empty((header.height, header.width, 0)), path, intrinsics)


def read_colour(path: Path, intrinsics) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """(sRGB [H, W, 3] in [0, 1], straight alpha [H, W] or None) from a PNG, JPEG or EXR."""
    _header_sized(path, intrinsics)
    if path.suffix.lower() in (".jpg", ".jpeg"):
        return read_jpeg(path, expected_size=intrinsics).astype(np.float64), None
    if path.suffix == ".exr":
        channels, _ = read_exr(path, expected_size=intrinsics)
        if "RGBA" in channels or "RGB" in channels:
            image = channels.get("RGBA", channels.get("RGB"))
        elif {"R", "G", "B"} <= set(channels):
            image = np.stack([channels[c] for c in "RGBA" if c in channels], axis=-1)
        else:
            raise InputError(f"{path} has no R, G, B channels (has {sorted(channels)})")
        image = require_finite(_sized(np.asarray(image, np.float64), path, intrinsics), path)
        if image.shape[-1] == 3:
            return linear_to_srgb(image), None
        alpha = np.clip(image[..., 3], 0.0, 1.0)  # [H, W]
        straight = np.divide(image[..., :3], image[..., 3:4], out=np.zeros_like(image[..., :3]),
                             where=image[..., 3:4] > 0)  # [H, W, 3]
        return linear_to_srgb(straight), alpha
    image = _sized(read_png(path, expected_size=intrinsics).astype(np.float64), path, intrinsics)
    if image.ndim == 2:
        image = image[..., None]
    if image.shape[-1] in (1, 2):  # gray (+ alpha)
        image = np.concatenate([np.repeat(image[..., :1], 3, -1), image[..., 1:]], axis=-1)
    return image[..., :3], (image[..., 3] if image.shape[-1] == 4 else None)


def read_plane(path: Path, intrinsics, depth_kind: Optional[str] = None) -> np.ndarray:
    """A one-channel EXR, .npy, (opacity) PNG or foreign depth (.npy.gz, .bin) as [H, W] float64."""
    if path.name.endswith(".npy.gz") or path.suffix == ".bin":
        values = read_depth_file(path, max_elements=intrinsics.width * intrinsics.height)
    elif path.suffix == ".npy":  # at most [H, W, 1] values: the header is checked before reading
        values = bounded.read_npy(path, max_elements=intrinsics.width * intrinsics.height)
    elif path.suffix == ".exr":
        _header_sized(path, intrinsics)
        channels, header = read_exr(path, expected_size=intrinsics)
        if len(channels) != 1:
            raise InputError(f"{path} should hold one channel, has {sorted(channels)}")
        (values,) = channels.values()
        stored = header.get("nerfgauge_depth")
        if depth_kind and stored is not None and stored != DEPTH_HEADER[depth_kind]:
            raise InputError(f"{path} holds {stored} but --depth-kind {depth_kind} compares {DEPTH_HEADER[depth_kind]}")
    else:
        _header_sized(path, intrinsics)
        values = read_png(path, expected_size=intrinsics)
    values = np.asarray(values)
    if values.ndim == 3 and values.shape[-1] == 1:
        values = values[..., 0]
    if values.ndim != 2 or not np.issubdtype(values.dtype, np.number):
        raise InputError(f"{path} must be a numeric [H, W] array, got shape {values.shape} dtype {values.dtype}")
    return _sized(values.astype(np.float64), path, intrinsics)


def find_nerfgauge_predictions(pred_dir: Path, split: str, stems: tuple, depth_kind: str) -> dict:
    """{stem: PredictionFiles or None} in our own naming; files that look like frames of
    none of `stems` are an InputError."""
    extras = extra_frames(pred_dir, split, {Path(stem).name for stem in stems})
    if extras:
        raise InputError(f"{len(extras)} extra prediction file(s) not among the {len(stems)} frames of split "
                         f"{split}: {', '.join(str(p) for p in extras[:4])}{' ...' if len(extras) > 4 else ''}")
    return {stem: find_prediction(pred_dir, stem, depth_kind) for stem in stems}


# --- other tools' folders -----------------------------------------------------------------


def natural_key(text: str) -> list:
    """"r_10" after "r_9": digit runs compare as numbers."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", text)]


def detect_format(pred_dir: Path, split: str) -> str:
    """The format of a prediction folder (see the module docstring for the rules)."""
    pred_dir = Path(pred_dir)
    if (pred_dir / "info.json").is_file() and (pred_dir / "color").is_dir():
        return "nerfbaselines"
    if any((folder / name).is_dir() for folder in (pred_dir / split, pred_dir) for name in NERFSTUDIO_COLOUR):
        return "nerfstudio"
    plain = False
    for folder in (pred_dir / split, pred_dir):
        if folder.is_dir():
            files = [p for p in folder.iterdir() if p.is_file()]
            if any(NERFGAUGE_FILE.match(p.name) for p in files):
                return "nerfgauge"
            plain = plain or any(p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") for p in files)
    return "folder" if plain else "nerfgauge"  # no images at all: our naming's message says what is missing


def _images(folder: Path, suffixes=IMAGE_SUFFIXES) -> list[Path]:
    """Image files under `folder` (recursively: nerfbaselines keeps relative sub-folders),
    naturally sorted by their path relative to it."""
    files = [p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in suffixes
             and not p.name.startswith(".")]
    return sorted(files, key=lambda p: natural_key(p.relative_to(folder).as_posix()))


def match_frames(images: list[Path], folder: Path, stems: tuple, what: str) -> dict:
    """{frame stem: image path}: by name when any image is named after a frame, else by order.

    A name is the image's path relative to `folder` without its suffix, compared with the
    frame's stem ("test/r_007") and with its last part ("r_007")."""
    if not images:
        raise InputError(f"no {what} images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
    keys = {}
    for stem in stems:
        keys[stem] = stem
        keys[Path(stem).name] = stem
    by_name, unmatched = {}, []
    for path in images:
        name = path.relative_to(folder).with_suffix("").as_posix()
        stem = keys.get(name)
        if stem is None:
            unmatched.append(path)
        elif stem in by_name:
            raise InputError(f"frame {stem}: predicted twice, as {by_name[stem]} and {path}; keep one")
        else:
            by_name[stem] = path
    if by_name:  # named after the frames: every name must match
        missing = [stem for stem in stems if stem not in by_name]
        if unmatched or missing:
            parts = []
            if unmatched:
                parts.append(f"{len(unmatched)} image(s) named after no frame ({', '.join(p.name for p in unmatched[:3])}"
                             f"{' ...' if len(unmatched) > 3 else ''})")
            if missing:
                more = " ..." if len(missing) > 3 else ""
                parts.append(f"no image for {len(missing)} frame(s) ({', '.join(missing[:3])}{more})")
            raise InputError(f"{what} images in {folder} do not match the split's {len(stems)} frames by name: "
                             + "; ".join(parts))
        return by_name
    if len(images) != len(stems):
        raise InputError(f"{folder} holds {len(images)} {what} image(s) named after none of the split's frames, "
                         f"and the split has {len(stems)} frames: cannot match them by order")
    return dict(zip(stems, images))


def _split_folder(pred_dir: Path, split: str, has) -> Path:
    """DIR/<split> when it holds the output (`has(folder)`), else DIR itself."""
    return pred_dir / split if (pred_dir / split).is_dir() and has(pred_dir / split) else pred_dir


def locate(pred_dir, fmt: str, split: str, stems: tuple) -> dict:
    """{frame stem: PredictionFiles} for a foreign folder of format `fmt` (not "nerfgauge")."""
    pred_dir = Path(pred_dir)
    if fmt == "nerfstudio":
        base = _split_folder(pred_dir, split, lambda f: any((f / n).is_dir() for n in NERFSTUDIO_COLOUR))
        colour_dir = next((base / n for n in NERFSTUDIO_COLOUR if (base / n).is_dir()), None)
        if colour_dir is None:
            raise InputError(f"{pred_dir} is not an ns-render dataset output: no {split}/rgb/ or rgb/ folder")
        colours = match_frames(_images(colour_dir, (".png", ".jpg", ".jpeg")), colour_dir, stems, "nerfstudio " + colour_dir.name)
        depth_dir = base / "raw-depth"
        return {stem: PredictionFiles(path, _sibling(depth_dir, colour_dir, path, ".npy.gz"), None)
                for stem, path in colours.items()}
    if fmt == "nerfbaselines":
        read_info(pred_dir)
        colour_dir = pred_dir / "color"
        if not colour_dir.is_dir():
            raise InputError(f"{pred_dir} is not a NerfBaselines predictions folder: no color/ folder")
        colours = match_frames(_images(colour_dir), colour_dir, stems, "NerfBaselines color")
        return {stem: PredictionFiles(path, _sibling(pred_dir / "depth", colour_dir, path, ".bin"), None)
                for stem, path in colours.items()}
    if fmt == "folder":
        base = _split_folder(pred_dir, split, lambda f: bool(_images(f)))
        images = [p for p in _images(base) if p.parent == base]  # flat: sub-folders are not frames
        return {stem: PredictionFiles(path, None, None)
                for stem, path in match_frames(images, base, stems, "colour").items()}
    raise InputError(f"unknown prediction format {fmt!r}; choose one of {', '.join(FORMATS)}")


def _sibling(folder: Path, colour_dir: Path, colour: Path, suffix: str):
    """The file in `folder` with the same relative name as `colour` and `suffix`, if any."""
    candidate = folder / (colour.relative_to(colour_dir).with_suffix("").as_posix() + suffix)
    return candidate if candidate.is_file() else None


def read_info(pred_dir: Path) -> dict:
    """NerfBaselines' info.json as a dict; a file that does not parse is an InputError."""
    path = Path(pred_dir) / "info.json"
    if not path.is_file():
        raise InputError(f"{pred_dir} is not a NerfBaselines predictions folder: no info.json")
    return read_json(path)


# --- reading foreign files ------------------------------------------------------------


def read_depth_file(path: Path, max_elements: int = validate.MAX_IMAGE_SIDE ** 2) -> np.ndarray:
    """nerfstudio raw-depth (.npy.gz, [H, W] or [H, W, 1]) or NerfBaselines depth (.bin:
    int32 height, width, float16 values) as a float64 array. max_elements: the most depth
    values the file may hold (the frame's H * W); a .npy.gz is refused while inflating as
    soon as it passes the bytes of that many float64 values, and a .bin before it is read."""
    try:
        if path.name.endswith(".npy.gz"):
            data = bounded.inflate_gzip(path, bounded.npy_bytes_limit(max_elements))
            values = bounded.read_npy(path, data, max_elements=max_elements)
        else:
            data = bounded.read_bytes(path, 8 + 2 * max_elements, "depth file")
            if len(data) < 8:
                raise ValueError("shorter than its 8-byte header")
            height, width = np.frombuffer(data[:8], "<i4")
            if height <= 0 or width <= 0 or len(data) != 8 + 2 * int(height) * int(width):
                raise ValueError(f"header says {width}x{height} but holds {len(data) - 8} bytes of float16")
            values = np.frombuffer(data[8:], "<f2").reshape(int(height), int(width))
    except InputError:
        raise
    except (OSError, ValueError, EOFError) as error:
        raise InputError(f"cannot read depth {path}: {error}") from None
    return np.asarray(values, np.float64)


def read_prediction(files: PredictionFiles, intrinsics) -> tuple:
    """A prediction's straight sRGB [H, W, 3] and its alpha [H, W] (the opacity plane when
    it has one, else the colour's alpha; None for an RGB prediction)."""
    rgb, alpha = read_colour(files.colour, intrinsics)
    if files.opacity is not None:
        alpha = require_finite(read_plane(files.opacity, intrinsics), files.opacity)
    return rgb, alpha


def locate_predictions(ds: dataset.Dataset, pred_dir: Path, split: str, pred_format: str, depth_kind: str) -> dict:
    """{stem: PredictionFiles} for every frame of `split`, in `pred_format` (FORMATS;
    "auto" detects it); an InputError naming the frames without a prediction."""
    stems = ds.cameras(split).stems
    if not stems:  # nothing would be scored, and an empty score is not a result
        raise InputError(f"split {split} of {ds.root} has no frames, so there is nothing to score "
                         f"(splits with frames: {', '.join(ds.splits) or 'none'})")
    if pred_format not in FORMATS:
        raise InputError(f"unknown prediction format {pred_format!r}; choose one of {', '.join(FORMATS)}")
    if pred_format == "auto":
        pred_format = detect_format(pred_dir, split)
    if pred_format == "nerfgauge":
        found = find_nerfgauge_predictions(pred_dir, split, stems, depth_kind)
    else:
        found = locate(pred_dir, pred_format, split, stems)
    missing = [stem for stem, files in found.items() if files is None]  # nerfgauge format only
    if missing:
        raise InputError(f"no prediction for {len(missing)} of {len(found)} frames of split {split}: "
                         f"{', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''} (looked for "
                         f"{pred_dir}/{missing[0]}.png|.exr and {pred_dir}/{Path(missing[0]).name}.png|.exr)")
    return found
