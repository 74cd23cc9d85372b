"""Other tools' render folders scored as they are (eval/predictions.py) and our scores written in
their result shapes (eval/foreign_results.py)."""

from __future__ import annotations

import base64
import gzip
import hashlib
import io
import json
import shutil
import statistics
import struct

import numpy as np
import pytest
from PIL import Image

from nerfgauge.cli import main
from nerfgauge.core import dataset
from nerfgauge.core.images import read_exr_single, read_png, write_exr, write_png
from nerfgauge.eval.evaluate import evaluate
from nerfgauge.eval.predictions import detect_format


@pytest.fixture(scope="module")
def ds(tmp_path_factory, make_dataset):
    """primitives, 4 train / 1 val / 3 test views at 24x24, 4 spp."""
    return make_dataset(tmp_path_factory.mktemp("foreign") / "primitives", views=4, val_views=1,
                        test_views=3, width=24, height=24)


@pytest.fixture(scope="module")
def stems(ds):
    return dataset.open_dataset(ds).cameras("test").stems


def predicted(ds, stem, k):
    """The ground-truth PNG with a frame-dependent stripe painted in: uint8 RGBA [H, W, 4]."""
    image = np.round(read_png(ds / (stem + ".png")) * 255).astype(np.uint8)
    image[2 + k: 5 + k, :, :3] = 40 * k
    image[2 + k: 5 + k, :, 3] = 255
    return image


def gt_depth(ds, stem):
    return read_exr_single(ds / (stem + "_distance.exr"))


@pytest.fixture(scope="module")
def reference(ds, stems, tmp_path_factory):
    """The same predictions in our own naming, scored: the numbers every format must give."""
    pred = tmp_path_factory.mktemp("ours")
    (pred / "test").mkdir()
    for k, stem in enumerate(stems):
        write_png(pred / (stem + ".png"), predicted(ds, stem, k))
    return evaluate(ds, pred, out=pred / "metrics.json")


def per_frame(document, metric="psnr"):
    return [frame[metric] for frame in document["frames"]]


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_nerfstudio_dataset_render_layout(ds, stems, reference, tmp_path):
    out = tmp_path / "renders"  # ns-render dataset --output-path renders --split test
    for k, stem in enumerate(stems):
        name = stem.split("/")[1]
        for folder in ("rgb", "gt-rgb", "depth"):
            (out / "test" / folder).mkdir(parents=True, exist_ok=True)
        image = predicted(ds, stem, k)
        white = np.round(image[..., :3] * (image[..., 3:] / 255.0) + 255 * (1 - image[..., 3:] / 255.0))
        write_png(out / "test" / "rgb" / f"{name}.png", white.astype(np.uint8))  # nerfstudio composites
        write_png(out / "test" / "depth" / f"{name}.png", np.zeros((24, 24, 3), np.uint8))  # colour-mapped: ignored
        write_png(out / "test" / "gt-rgb" / f"{name}.png", np.zeros((24, 24, 3), np.uint8))
        (out / "test" / "raw-depth").mkdir(exist_ok=True)
        with gzip.open(out / "test" / "raw-depth" / f"{name}.npy.gz", "wb") as handle:
            np.save(handle, gt_depth(ds, stem)[..., None])
    assert detect_format(out, "test") == "nerfstudio"
    document = evaluate(ds, out, out=tmp_path / "m.json")
    # compositing onto white by hand rounds to 8 bits: within half a level of the RGBA prediction
    assert per_frame(document) == pytest.approx(per_frame(reference), abs=0.2)
    assert all(frame["depth_absrel"] == 0.0 for frame in document["frames"] if frame["depth_absrel"] is not None)
    assert [frame["file"] for frame in document["frames"]] == [f"test/rgb/{s.split('/')[1]}.png" for s in stems]
    # the split folder itself works too
    assert per_frame(evaluate(ds, out / "test", out=tmp_path / "m2.json")) == per_frame(document)


def test_nerfbaselines_predictions_folder(ds, stems, reference, tmp_path):
    pred = tmp_path / "predictions"
    for folder in ("color", "gt-color", "depth"):
        (pred / folder).mkdir(parents=True)
    (pred / "info.json").write_text(json.dumps({"method": "someone", "evaluation_protocol": "default"}))
    for k, stem in enumerate(stems):
        name = stem.split("/")[1]
        write_png(pred / "color" / f"{name}.png", predicted(ds, stem, k))
        shutil.copy(ds / (stem + ".png"), pred / "gt-color" / f"{name}.png")
        depth = gt_depth(ds, stem)
        (pred / "depth" / f"{name}.bin").write_bytes(struct.pack("<ii", *depth.shape) + depth.astype("<f2").tobytes())
    assert detect_format(pred, "test") == "nerfbaselines"
    document = evaluate(ds, pred, out=tmp_path / "m.json")
    assert per_frame(document) == per_frame(reference)
    assert per_frame(document, "ssim") == per_frame(reference, "ssim")
    # float16 keeps 11 significant bits: relative error at most 2^-11 per pixel
    assert all(f["depth_absrel"] <= 2.0 ** -11 for f in document["frames"] if f["depth_absrel"] is not None)


def test_plain_folder_by_order_png_jpeg_and_exr(ds, stems, reference, tmp_path):
    pngs = tmp_path / "pngs"
    pngs.mkdir()
    names = ["shot_9.png", "shot_10.png", "shot_11.png"]  # natural order, not text order
    for k, (stem, name) in enumerate(zip(stems, names)):
        write_png(pngs / name, predicted(ds, stem, k))
    assert detect_format(pngs, "test") == "folder"
    document = evaluate(ds, pngs, out=tmp_path / "m.json")
    assert per_frame(document) == per_frame(reference)
    assert [frame["file"] for frame in document["frames"]] == names

    jpegs, exrs = tmp_path / "jpegs", tmp_path / "exrs"
    jpegs.mkdir()
    exrs.mkdir()
    for k, stem in enumerate(stems):
        rgba = predicted(ds, stem, k) / 255.0
        white = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])
        Image.fromarray(np.round(white * 255).astype(np.uint8)).save(jpegs / f"{k:02d}.jpg", quality=100, subsampling=0)
        linear = np.where(white <= 0.04045, white / 12.92, ((white + 0.055) / 1.055) ** 2.4).astype(np.float32)
        write_exr(exrs / (stem.split("/")[1] + ".exr"), {"RGB": linear})
    jpeg_doc = evaluate(ds, jpegs, out=tmp_path / "j.json")
    # quality 100 without chroma subsampling: within a level or two of the PNG, a fraction of a dB
    assert per_frame(jpeg_doc) == pytest.approx(per_frame(reference), abs=0.3)
    exr_doc = evaluate(ds, exrs, out=tmp_path / "e.json", pred_format="folder")
    assert per_frame(exr_doc) == pytest.approx(per_frame(reference), abs=0.2)  # 8-bit rounding of the white composite


def _folder_of(ds, stems, folder, names):
    folder.mkdir()
    for k, (stem, name) in enumerate(zip(stems, names)):
        write_png(folder / name, predicted(ds, stem, k))
    return folder


@pytest.mark.parametrize("names, words", [
    (["a.png", "b.png"], "cannot match them by order"),  # too few, by order
    (["r_000.png", "r_001.png", "other.png"], "named after no frame"),  # by name, one stray
    (["r_000.png", "r_001.png"], "no image for 1 frame"),  # by name, one missing
])
def test_count_and_name_mismatch_are_one_line_errors(ds, stems, tmp_path, capsys, names, words):
    folder = _folder_of(ds, stems, tmp_path / "p", names)
    code, out, err = run(capsys, "evaluate", ds, "--pred", folder, "--pred-format", "folder")
    assert code == 2 and words in err and len(err.strip().splitlines()) == 1
    assert not (folder / "metrics.json").exists()


def test_size_mismatch_and_bad_info_json(ds, stems, tmp_path, capsys):
    folder = tmp_path / "sized"
    folder.mkdir()
    for k in range(3):
        write_png(folder / f"{k}.png", np.zeros((20, 24, 4), np.uint8))
    code, _, err = run(capsys, "evaluate", ds, "--pred", folder)
    assert code == 2 and "24x20" in err and len(err.strip().splitlines()) == 1

    pred = tmp_path / "nb"
    (pred / "color").mkdir(parents=True)
    for k, stem in enumerate(stems):
        write_png(pred / "color" / f"{stem.split('/')[1]}.png", predicted(ds, stem, k))
    (pred / "info.json").write_text('{"method": "x",')
    code, _, err = run(capsys, "evaluate", ds, "--pred", pred)
    assert code == 2 and "info.json" in err and "not valid JSON" in err and len(err.strip().splitlines()) == 1
    assert not (pred / "metrics.json").exists()


def test_ns_eval_and_nerfbaselines_outputs(ds, stems, reference, tmp_path, capsys):
    pred = tmp_path / "mine"
    (pred / "test").mkdir(parents=True)
    for k, stem in enumerate(stems):
        write_png(pred / (stem + ".png"), predicted(ds, stem, k))
    code, _, err = run(capsys, "evaluate", ds, "--pred", pred, "--ns-eval", tmp_path / "ns.json",
                       "--nerfbaselines", tmp_path / "results.json", "--method-name", "mine")
    assert code == 0, err
    ns = json.loads((tmp_path / "ns.json").read_text())
    # ns-eval's four keys, plus the mark that makes the file ours to replace (core.outputs)
    assert set(ns) == {"experiment_name", "method_name", "checkpoint", "results", "tool", "kind"}
    assert ns["method_name"] == "mine" and (ns["tool"], ns["kind"]) == ("nerfgauge", "ns-eval")
    psnrs = per_frame(reference)
    assert ns["results"]["psnr"] == pytest.approx(statistics.fmean(psnrs), rel=1e-15)
    assert ns["results"]["psnr_std"] == pytest.approx(statistics.stdev(psnrs), rel=1e-12)  # torch.std: ddof 1
    assert {"ssim", "ssim_std"} <= set(ns["results"])

    nb = json.loads((tmp_path / "results.json").read_text())
    assert {"metrics", "metrics_raw", "metrics_sha256", "predictions_sha256", "ground_truth_sha256",
            "evaluation_protocol", "nb_info", "evaluate_datetime", "evaluate_version"} <= set(nb)
    raw = base64.b64decode(nb["metrics_raw"]["psnr"])
    assert list(struct.unpack(f"<{len(psnrs)}f", raw)) == [float(np.float32(v)) for v in psnrs]
    assert nb["metrics"]["psnr"] == round(statistics.fmean(psnrs), 5)
    pred_bytes = b"".join((pred / (stem + ".png")).read_bytes() for stem in stems)
    gt_bytes = b"".join((ds / (stem + ".png")).read_bytes() for stem in stems)
    assert nb["predictions_sha256"] == hashlib.sha256(pred_bytes).hexdigest()
    assert nb["ground_truth_sha256"] == hashlib.sha256(gt_bytes).hexdigest()
