"""Scoring protocols (eval/protocols.py): `evaluate --protocol`, each protocol's metrics
against an independent statement of it, and the protocol-sensitivity table."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest

from nerfgauge.cli import main
from nerfgauge.core import dataset
from nerfgauge.core.images import read_png, write_png
from nerfgauge.eval import protocols as P
from nerfgauge.eval.evaluate import evaluate


@pytest.fixture(scope="module")
def ds(tmp_path_factory, make_dataset):
    """primitives, 4 train / 1 val / 2 test views at 40x40 (LPIPS-Alex needs 31 px)."""
    return make_dataset(tmp_path_factory.mktemp("protocols") / "primitives", views=4, val_views=1,
                        test_views=2, width=40, height=40)


@pytest.fixture(scope="module")
def renders(ds, tmp_path_factory):
    """RGBA predictions: the ground truth with a stripe painted in and its alpha kept."""
    pred = tmp_path_factory.mktemp("renders")
    (pred / "test").mkdir()
    for k, stem in enumerate(dataset.open_dataset(ds).cameras("test").stems):
        image = np.round(read_png(ds / (stem + ".png")) * 255).astype(np.uint8)
        image[5 + k: 12 + k, :, :3] = 90
        image[5 + k: 12 + k, :, 3] = 255
        write_png(pred / (stem + ".png"), image)
    return pred


def test_evaluate_names_the_protocol_and_scores_its_way(ds, renders, tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "no-weights"))
    ours = evaluate(ds, renders, out=tmp_path / "ours.json")
    theirs = evaluate(ds, renders, out=tmp_path / "nb.json", protocol="nerfbaselines")
    ns = evaluate(ds, renders, out=tmp_path / "ns.json", protocol="ns-eval")
    assert (ours["protocol"], theirs["protocol"], ns["protocol"]) == ("nerfgauge", "nerfbaselines", "ns-eval")
    assert theirs["evaluation_protocol"] == "nerf" and theirs["lpips_net"] == "vgg"
    assert (ours["protocol_background"], theirs["protocol_background"], ns["protocol_background"]) == \
        ("white", "white", "black")
    assert json.loads((tmp_path / "nb.json").read_text())["protocol"] == "nerfbaselines"
    # without weights every LPIPS is n/a with the line that says what to run
    assert theirs["mean"]["lpips"] is None and "nerfgauge lpips install" in theirs["notes"]["lpips"]
    assert "lpips_alex" in theirs["mean"] and "lpips_alex" in theirs["notes"]
    # uint8 truncation and another SSIM move the numbers, but not far on the same renders
    assert ours["mean"]["psnr"] != theirs["mean"]["psnr"]
    assert abs(ours["mean"]["psnr"] - theirs["mean"]["psnr"]) < 3.0
    assert 0.0 < ns["mean"]["ssim"] <= 1.0
    # what is ours stays ours: depth-free metrics such as psnr_foreground are the same
    assert ours["mean"]["psnr_foreground"] == theirs["mean"]["psnr_foreground"]


def test_nerfbaselines_pair_is_white_composited_and_truncated():
    rgb = np.full((2, 2, 3), 0.5)
    alpha = np.array([[1.0, 0.0], [0.5, 0.999]])
    gt = np.concatenate([np.full((2, 2, 3), 0.2), np.ones((2, 2, 1))], -1)
    pred, gt_out = P.prepare(P.get("nerfbaselines"), rgb, alpha, gt)
    # 0.5 * 255 = 127.5 -> 127 (truncated, not rounded); background white -> 255
    assert pred[0, 0, 0] == np.float32(127 / 255) and pred[0, 1, 0] == 1.0
    assert pred[1, 0, 0] == np.float32(191 / 255)  # 0.75 * 255 = 191.25
    assert gt_out[0, 0, 0] == np.float32(51 / 255)  # 0.2 * 255 = 51.000002 in float32
    black, _ = P.prepare(P.get("ns-eval"), rgb, alpha, gt)
    assert black[0, 1, 0] == 0.0 and black[1, 0, 0] == np.float32(0.25)


def test_our_protocol_is_an_ordinary_record_on_the_evaluations_background():
    """Ours is a Protocol like the others (no None sentinel in evaluate): it composites onto
    the evaluation's background, in float64 and unclipped, exactly as eval.metrics.composite
    does (the independent statement of our convention); the others keep their own."""
    from nerfgauge.eval.metrics import BACKGROUNDS, composite

    ours = P.get(P.DEFAULT)
    assert isinstance(ours, P.Protocol) and ours.float64 and not ours.quantise
    rgb = np.array([[[0.5, 0.25, 1.0], [0.1, 0.2, 0.3]]])
    alpha = np.array([[0.5, 1.0]])
    gt = np.array([[[0.2, 0.4, 0.6, 0.75], [0.0, 0.0, 0.0, 0.0]]])
    for name, colour in BACKGROUNDS.items():
        pred, gt_out = P.prepare(ours, rgb, alpha, gt, colour)
        assert pred.dtype == np.float64 and np.array_equal(pred, composite(np.concatenate([rgb, alpha[..., None]], -1),
                                                                            colour))
        assert np.array_equal(gt_out, composite(gt, colour))
        assert P.background_name(ours.composited_on(colour)) == name
        assert P.background_name(P.get("ns-eval").composited_on(colour)) == "black"


def _dm_pix_reference(a, b):
    """dm_pix.ssim as its docstring states it, written out with np.convolve (a slow oracle)."""
    k, sigma = 11, 1.5
    f = np.exp(-0.5 * ((np.arange(k) - k // 2) / sigma) ** 2)
    f /= f.sum()

    def blur(z):  # [H, W, C] valid along both axes
        z = np.stack([np.stack([np.convolve(z[:, j, c], f, "valid") for j in range(z.shape[1])], 1)
                      for c in range(z.shape[2])], -1)
        return np.stack([np.stack([np.convolve(z[i, :, c], f, "valid") for i in range(z.shape[0])], 0)
                         for c in range(z.shape[2])], -1)

    mu0, mu1 = blur(a), blur(b)
    s00, s11, s01 = blur(a * a) - mu0 ** 2, blur(b * b) - mu1 ** 2, blur(a * b) - mu0 * mu1
    eps = np.finfo(np.float32).eps ** 2
    s00, s11 = np.maximum(eps, s00), np.maximum(eps, s11)
    s01 = np.sign(s01) * np.minimum(np.sqrt(s00 * s11), np.abs(s01))
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return float(np.mean((2 * mu0 * mu1 + c1) * (2 * s01 + c2) / ((mu0 ** 2 + mu1 ** 2 + c1) * (s00 + s11 + c2))))


def test_dm_pix_ssim_matches_its_statement():
    rng = np.random.default_rng(3)
    a = rng.random((20, 17, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1).astype(np.float32)
    assert P.ssim_dm_pix(b, a) == pytest.approx(_dm_pix_reference(a.astype(np.float64), b.astype(np.float64)), abs=1e-9)
    assert P.ssim_dm_pix(a, a) == pytest.approx(1.0)


def test_torchmetrics_ssim_takes_its_range_from_the_images():
    rng = np.random.default_rng(4)
    a = rng.random((24, 24, 3)) * 0.5
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    value = P.ssim_torchmetrics(b, a)
    assert 0 < value < 1
    # scaling both images scales data_range with them: SSIM is unchanged (the skimage one is not)
    assert P.ssim_torchmetrics(b * 0.5, a * 0.5) == pytest.approx(value, abs=1e-9)


@pytest.mark.skipif(importlib.util.find_spec("torchmetrics") is None, reason="torchmetrics is not installed")
def test_torchmetrics_ssim_matches_torchmetrics():
    import torch
    from torchmetrics.functional import structural_similarity_index_measure

    rng = np.random.default_rng(5)
    a = rng.random((32, 28, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1).astype(np.float32)
    theirs = structural_similarity_index_measure(torch.from_numpy(b).permute(2, 0, 1)[None],
                                                 torch.from_numpy(a).permute(2, 0, 1)[None])
    assert P.ssim_torchmetrics(b, a) == pytest.approx(float(theirs), abs=1e-5)


@pytest.mark.skipif(importlib.util.find_spec("nerfbaselines") is None, reason="nerfbaselines is not installed")
def test_nerfbaselines_ssim_and_psnr_match_theirs():
    from nerfbaselines import metrics

    rng = np.random.default_rng(6)
    a = rng.random((1, 30, 26, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1).astype(np.float32)
    assert P.ssim_dm_pix(b[0], a[0]) == pytest.approx(float(metrics.ssim(a, b)[0]), abs=1e-5)
    assert P.psnr32(b[0], a[0]) == pytest.approx(float(metrics.psnr(b, a)[0]), abs=1e-4)


def test_an_unknown_protocol_is_one_line_exit_2(ds, renders, tmp_path, capsys):
    code = main(["evaluate", str(ds), "--pred", str(renders), "--out", str(tmp_path / "m.json"),
                 "--protocol", "nerfbaseline"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "unknown protocol 'nerfbaseline'" in err
    assert not (tmp_path / "m.json").exists()


def test_sensitivity_table_scores_the_same_renders_under_each_protocol(ds, renders, tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "no-weights"))
    table = P.sensitivity(ds, renders, "test")
    assert set(table["protocols"]) == set(P.PROTOCOLS) and table["frames"] == 2
    psnrs = [row["psnr"] for row in table["protocols"].values()]
    assert table["spread"]["psnr"] == pytest.approx(max(psnrs) - min(psnrs))
    assert table["spread"]["lpips"] is None  # no weights: n/a, not zero
    ours = evaluate(ds, renders, out=tmp_path / "m.json", held_out=False)
    assert table["protocols"]["nerfgauge"]["psnr"] == pytest.approx(ours["mean"]["psnr"])
    rows = P.sensitivity_rows({"stripe": table})
    assert rows[0][:3] == ["method", "protocol", "PSNR dB"] and len(rows) == 1 + 3 + 1
    assert rows[-1][1] == "spread (max - min)"
    assert "n/a (install: nerfgauge lpips install)" in P.format_rows(rows)


def test_suite_sensitivity_combines_datasets(ds, renders, tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "no-weights"))
    one = P.sensitivity(ds, renders, "test")
    board = P.suite_sensitivity({"stripe": [(ds, renders), (ds, renders)]})
    combined = board["stripe"]
    assert combined["datasets"] == 2 and combined["frames"] == 2 * one["frames"]
    for name in P.PROTOCOLS:
        assert combined["protocols"][name]["psnr"] == pytest.approx(one["protocols"][name]["psnr"])
    assert combined["spread"]["psnr"] == pytest.approx(one["spread"]["psnr"])
    assert len(P.sensitivity_rows(board)) == 1 + 3 + 1
