"""The method interface (nerfgauge.methods): every method goes through it, ours, the
baselines, a user's Python class and another tool's command lines (a TOML spec).

The external method in these tests is a small Python program written here: it trains by
writing a file (and allocating a stated amount of memory, spinning a stated CPU time), and
renders by copying the ground truth's frames, so its scores are known (SSIM 1) and the
harness's scores can be compared with `nerfgauge evaluate` on the same renders.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from nerfgauge.core.errors import InputError
from nerfgauge.generate.variant import cuda_available
from nerfgauge.methods.builtin import builtin_methods
from nerfgauge.methods.external import MethodFailed, read_spec
from nerfgauge.methods.interface import Method, Needs, TrainRequest, missing_needs
from nerfgauge.methods.registry import resolve
from nerfgauge.methods.interface import check_name

PROGRAM = textwrap.dedent('''
    import os, pathlib, shutil, sys, time
    mode = sys.argv[1]
    if mode == "train":
        run, steps, megabytes, cpu = pathlib.Path(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])
        block = bytearray(megabytes << 20)  # touched: resident
        for i in range(0, len(block), 4096):
            block[i] = 1
        start = time.process_time()
        while time.process_time() - start < cpu:
            pass
        (run / "out").mkdir(exist_ok=True)
        (run / "out" / "weights.txt").write_text(f"{steps}\\n")
        print("trained", steps, "tmp", os.environ["TMPDIR"])
    elif mode == "render":
        dataset, split, out, weights = map(pathlib.Path, sys.argv[2:6])
        assert weights.read_text().strip().isdigit()
        (out / split).mkdir(parents=True, exist_ok=True)
        for frame in sorted((dataset / split).glob("r_*.png")):
            if frame.stem.count("_") == 1:  # r_000.png, not r_000_mask.png
                shutil.copy(frame, out / split / frame.name)
    elif mode == "fail":
        sys.exit(3)
    elif mode == "sleep":
        import subprocess
        subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])  # a grandchild in the group
        time.sleep(60)
    elif mode == "nothing":
        pass
''')


def write_spec(folder: Path, name="copycat", train=("train", "{run}", "{steps}", "0", "0"), render=None,
               length="steps", extra="") -> Path:
    program = folder / "program.py"
    program.write_text(PROGRAM)
    render = render or ("render", "{dataset}", "{split}", "{out}", "{weights}")
    argv = lambda args: json.dumps([sys.executable, str(program), *args])  # noqa: E731
    spec = folder / f"{name}.toml"
    spec.write_text(f'name = "{name}"\nsummary = "a test method"\n[train]\ncommand = {argv(train)}\n'
                    f'length = "{length}"\n[render]\ncommand = {argv(render)}\nlayout = "nerfgauge"\n'
                    f'[files]\nweights = "{{run}}/out/*.txt"\n' + extra)
    return spec


# --- the registry ----------------------------------------------------------------------------


def test_every_builtin_method_goes_through_the_interface():
    methods = builtin_methods()
    assert {"compact", "vanilla", "nearest", "lightfield-nearest", "lightfield-quadrilinear", "refocus"} <= set(methods)
    for name, method in methods.items():
        assert isinstance(method, Method) and method.name == name
        assert resolve(name) is not None and check_name(name) == name


@pytest.mark.parametrize("spec, message", [
    ("nerfacto-unknown", "unknown method"),
    ("", "a method is a name"),
    ("os:path", "not a subclass"),
    ("no_such_module_xyz:Thing", "cannot import"),
    ("a b:c", "not a Python class"),
    ("missing.toml", "method spec not found"),
])
def test_a_method_that_cannot_be_found_is_one_line(spec, message):
    with pytest.raises(InputError, match=message) as error:
        resolve(spec)
    assert "\n" not in str(error.value)


def test_a_users_class_is_named_as_module_colon_class(tmp_path, monkeypatch):
    (tmp_path / "my_methods.py").write_text(textwrap.dedent('''
        from nerfgauge.methods import Method, Needs, TrainResult
        class Constant(Method):
            name = "constant"
            needs = Needs(transforms=True)
            def __init__(self, colour=0.5):
                self.colour = colour
            def train(self, request):
                return TrainResult(seconds=0.0, steps=0)
    '''))
    monkeypatch.syspath_prepend(str(tmp_path))
    method = resolve("my_methods:Constant", {"colour": 0.25})
    assert method.name == "constant" and method.colour == 0.25
    with pytest.raises(InputError, match="does not take these settings"):
        resolve("my_methods:Constant", {"shade": 1})


@pytest.mark.parametrize("name", ["", "Upper", "a/b", "..", "-x", "a" * 65, "m$\\frac$x", "a\0b"])
def test_method_names_are_folder_names(name):
    with pytest.raises(InputError):
        check_name(name)


def test_the_methods_command_lists_needs_and_produces(capsys):
    from nerfgauge.cli import main

    assert main(["methods", "--json"]) == 0
    rows = {row["name"]: row for row in json.loads(capsys.readouterr().out)}
    assert rows["compact"]["needs"] == ["transforms", "manifest", "scene bounds"]
    assert rows["lightfield-nearest"]["needs"] == ["transforms", "lightfield layout"]
    assert rows["nearest"]["learned"] is False and "depth" in rows["compact"]["produces"]


# --- what a dataset lacks --------------------------------------------------------------------


def test_a_method_is_told_what_a_dataset_lacks(tiny_dataset):
    from nerfgauge.core.dataset import Dataset

    ds = Dataset(tiny_dataset)
    methods = builtin_methods()
    assert missing_needs(methods["compact"], ds) == []
    assert missing_needs(methods["nearest"], ds) == []
    assert missing_needs(methods["lightfield-nearest"], ds) == ["needs a light-field camera grid "
                                                                 "(generate --layout lightfield)"]

    class Splats(Method):
        needs = Needs(initial_points=True, masks=True)
    assert missing_needs(Splats(), ds) == []  # our datasets carry a COLMAP model and masks


# --- specs: read -----------------------------------------------------------------------------


@pytest.mark.parametrize("body, message", [
    ('name = "x"\n[train]\ncommand = "ns-train nerfacto"\n[render]\ncommand = ["a"]\nlayout = "nerfgauge"',
     "non-empty list of arguments"),
    ('name = "x"\n[train]\ncommand = ["a", "{dataset}/{bogus}"]\n[render]\ncommand = ["a"]\nlayout = "nerfgauge"',
     "unknown placeholder {bogus}"),
    ('name = "x"\n[train]\ncommand = ["a", "{seed!r}"]\n[render]\ncommand = ["a"]\nlayout = "nerfgauge"',
     "plain {name}"),
    ('name = "x"\n[train]\ncommand = ["a"]\n[render]\ncommand = ["a", "{split}"]\nlayout = "colmap"',
     "render.layout must be one of"),
    ('name = "X Y"\n[train]\ncommand = ["a"]\n[render]\ncommand = ["a"]\nlayout = "nerfgauge"', "name 'X Y'"),
    ('name = "x"\nshell = true\n[train]\ncommand = ["a"]\n[render]\ncommand = ["a"]\nlayout = "nerfgauge"',
     "unknown field 'shell'"),
    ('name = "x"\n[train]\ncommand = ["a"]\n[render]\ncommand = ["a"]\nlayout = "nerfgauge"\n[files]\nw = "/etc/*"',
     "inside the run folder"),
    ('name = "x"\n[train]\ncommand = ["a"]\nlength = "minutes"\n[render]\ncommand = ["a"]\nlayout = "nerfgauge"',
     "train.length must be one of"),
    ('name = "x"\n[train\n', "not valid TOML"),
])
def test_a_bad_spec_is_one_line_when_read(tmp_path, body, message):
    spec = tmp_path / "bad.toml"
    spec.write_text(body)
    with pytest.raises(InputError, match=message.replace("{", r"\{").replace("}", r"\}").replace("(", r"\(")) as error:
        read_spec(spec)
    assert "\n" not in str(error.value)


# --- specs: run ------------------------------------------------------------------------------


@pytest.mark.slow
def test_an_external_method_trains_renders_and_scores_as_evaluate_does(tiny_dataset, tmp_path):
    from nerfgauge.eval.evaluate import evaluate

    spec = write_spec(tmp_path, train=("train", "{run}", "{steps}", "120", "0.3"))
    method = resolve(str(spec))
    result = method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", seed=3, steps=7))
    # the child's own usage: it touched 120 MiB and spun 0.3 s of CPU
    assert result.peak_memory_bytes >= 120 << 20
    # an interpreter is well under 100 MiB; the harness's own size (torch imported: hundreds of
    # MiB) must not count: a child forked from it would report at least that
    assert result.peak_memory_bytes < (120 << 20) + (100 << 20)
    assert result.cpu_seconds >= 0.3 and result.steps == 7 and result.seconds >= result.cpu_seconds * 0.5
    log = (tmp_path / "run" / "train.log").read_text()
    assert "trained 7" in log and str(tmp_path / "run" / ".tmp") in log  # its TMPDIR is inside the run
    rendered = method.render(tmp_path / "run", tiny_dataset, "test", tmp_path / "renders")
    assert rendered.frames == 2 and rendered.pred_format == "nerfgauge"
    through_spec = evaluate(tiny_dataset, rendered.out, split="test")
    direct = subprocess.run([sys.executable, "-m", "nerfgauge.cli", "evaluate", str(tiny_dataset), "--pred",
                             str(tmp_path / "renders"), "--out", str(tmp_path / "m.json")], capture_output=True)
    assert direct.returncode == 0, direct.stderr
    document = json.loads((tmp_path / "m.json").read_text())
    for metric in ("ssim", "edge_fraction"):
        assert through_spec["mean"][metric] == pytest.approx(document["mean"][metric], abs=1e-9)
    assert through_spec["mean"]["ssim"] == pytest.approx(1.0, abs=1e-9)  # the ground truth itself


def test_a_command_that_fails_says_so_with_its_log(tiny_dataset, tmp_path):
    method = resolve(str(write_spec(tmp_path, train=("fail",))))
    with pytest.raises(MethodFailed, match="exited with status 3") as error:
        method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=1))
    assert error.value.method == "copycat" and str(tmp_path / "run" / "train.log") in error.value.reason


def test_a_command_past_twice_its_budget_is_stopped_with_its_process_group(tiny_dataset, tmp_path):
    method = resolve(str(write_spec(tmp_path, train=("sleep",), length="seconds")))
    start = time.perf_counter()
    with pytest.raises(MethodFailed, match=r"ran past 1 s \(twice its budget\)"):
        method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", budget_seconds=0.5))
    assert time.perf_counter() - start < 10
    survivors = subprocess.run(["pgrep", "-f", "time.sleep\\(60\\)"], capture_output=True, text=True).stdout.split()
    assert not [pid for pid in survivors if int(pid) != os.getpid()], "the command's grandchild outlived it"


def test_a_method_that_writes_no_renders_fails_with_the_reason(tiny_dataset, tmp_path):
    method = resolve(str(write_spec(tmp_path, render=("nothing",))))
    method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=1))
    with pytest.raises(MethodFailed, match="wrote no images"):
        method.render(tmp_path / "run", tiny_dataset, "test", tmp_path / "renders")


def test_a_missing_program_names_its_install(tiny_dataset, tmp_path):
    spec = tmp_path / "ns.toml"
    spec.write_text('name = "ns"\ninstall = "pip install nerfstudio"\n[train]\ncommand = ["ns-train-not-here-xyz"]\n'
                    '[render]\ncommand = ["x"]\nlayout = "nerfstudio"\n')
    with pytest.raises(MethodFailed, match="not found on its PATH"):
        resolve(str(spec)).train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=1))


def test_the_run_record_is_data_not_instructions(tiny_dataset, tmp_path):
    method = resolve(str(write_spec(tmp_path)))
    method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=2))
    record_path = tmp_path / "run" / "method.json"
    record = json.loads(record_path.read_text())
    record["request"]["threads"] = "1; rm -rf ~"
    record_path.write_text(json.dumps(record))
    with pytest.raises(InputError, match="method.json"):
        method.render(tmp_path / "run", tiny_dataset, "test", tmp_path / "renders")
    record["request"]["threads"] = 2
    record["spec"]["render"] = ["/bin/sh", "-c", "touch /tmp/owned"]
    record_path.write_text(json.dumps(record))
    with pytest.raises(InputError, match="not a record of method copycat as its spec is now"):
        method.render(tmp_path / "run", tiny_dataset, "test", tmp_path / "renders")


def test_a_steps_method_refuses_a_budget(tiny_dataset, tmp_path):
    method = resolve(str(write_spec(tmp_path)))
    assert method.accepts_budget is False
    with pytest.raises(InputError, match="takes a step count"):
        method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", budget_seconds=5))


# --- ours through the interface ----------------------------------------------------------------


def test_a_baseline_through_the_interface_equals_nerfgauge_baseline(tiny_dataset, tmp_path):
    method = resolve("nearest")
    result = method.render(None, tiny_dataset, "test", tmp_path / "via-method")
    assert result.frames == 2
    from nerfgauge.cli import main

    assert main(["baseline", str(tiny_dataset), "--method", "nearest", "--out", str(tmp_path / "via-cli")]) == 0
    for frame in ("r_000.png", "r_001.png"):
        assert (tmp_path / "via-method" / "test" / frame).read_bytes() == (tmp_path / "via-cli" / "test" / frame).read_bytes()


@pytest.mark.slow
def test_our_nerf_through_the_interface_equals_nerfgauge_train(tiny_dataset, tmp_path):
    import torch

    from nerfgauge.nerf.config import TrainConfig
    from nerfgauge.nerf.train import train

    method = resolve("compact")
    result = method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "via-method", seed=4, steps=30, threads=1))
    train(TrainConfig(dataset=str(tiny_dataset), seed=4, steps=30, threads=1), tmp_path / "direct", progress=False)
    assert result.steps == 30 and result.model_bytes > 0 and result.cpu_seconds > 0
    ours = torch.load(tmp_path / "via-method" / "model.pt", weights_only=True)
    theirs = torch.load(tmp_path / "direct" / "model.pt", weights_only=True)
    assert ours.keys() == theirs.keys()
    for key, value in ours.items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(value, theirs[key]), key
    rendered = method.render(tmp_path / "via-method", tiny_dataset, "test", tmp_path / "renders")
    assert rendered.frames == 2 and (tmp_path / "renders" / "test" / "r_000_depth.exr").is_file()
    with pytest.raises(InputError, match="set by the job"):
        method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "x", steps=1, settings={"seed": 2}))
    with pytest.raises(InputError, match="unknown setting 'learning_rate'"):
        method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "x", steps=1, settings={"learning_rate": 2}))


def test_a_command_killed_by_a_signal_reports_the_signal(tiny_dataset, tmp_path):
    spec = tmp_path / "killed.toml"
    spec.write_text(f'name = "killed"\n[train]\ncommand = {json.dumps([sys.executable, "-c", "import os; os.kill(os.getpid(), 9)"])}\n'
                    '[render]\ncommand = ["x"]\nlayout = "nerfgauge"\n')
    with pytest.raises(MethodFailed, match="exited with status -9"):
        resolve(str(spec)).train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=1))


# --- specs: settings, devices, environments, prepare steps (nerfgauge.methods.external) ------------


def echo_spec(folder: Path, body: str, name="echo") -> Path:
    """A spec whose training prints its arguments and a few variables (JSON) and writes its weights."""
    program = folder / "echo.py"
    program.write_text(textwrap.dedent('''
        import json, os, pathlib, sys
        run = pathlib.Path(os.getcwd())
        (run / "out").mkdir(exist_ok=True)
        (run / "out" / "weights.txt").write_text("1\\n")
        print("ECHO " + json.dumps({"argv": sys.argv[1:], "env": {k: os.environ.get(k) for k in
              ("PYTHONPATH", "VIRTUAL_ENV", "MARK", "PATH")}}))
        if sys.argv[1:2] == ["render"]:
            out = pathlib.Path(sys.argv[2]) / "test"
            out.mkdir(parents=True, exist_ok=True)
            (out / "r_000.png").write_bytes(b"not scored here")
    '''))
    spec = folder / f"{name}.toml"
    spec.write_text(f'name = "{name}"\n' + body.replace("PROGRAM", json.dumps(str(program))))
    return spec


def echoed(log: Path) -> dict:
    line = [line for line in log.read_text().splitlines() if line.startswith("ECHO ")][-1]
    return json.loads(line[len("ECHO "):])


SETTINGS_SPEC = '''
[settings]
rays = 4096
scale = 1.5
mask = true
label = "a b"
[train]
command = ["{python}", PROGRAM, "--rays", "{rays}", "--scale", "{scale}", "--mask", "{mask}", "--label", "{label}"]
devices = { cpu = ["--device", "cpu"], auto = [] }
[render]
command = ["{python}", PROGRAM, "render", "{out}", "{rays}"]
layout = "nerfgauge"
[files]
weights = "{run}/out/weights.txt"
'''


def settings_spec(tmp_path) -> Path:
    return echo_spec(tmp_path, SETTINGS_SPEC.replace('"{python}"', json.dumps(sys.executable)))


def test_a_specs_settings_fill_its_command_and_a_job_overrides_them(tiny_dataset, tmp_path):
    method = resolve(str(settings_spec(tmp_path)), {"rays": 256})
    method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=1, device="cpu",
                              settings={"scale": 2, "mask": False}))
    argv = echoed(tmp_path / "run" / "train.log")["argv"]
    assert argv == ["--rays", "256", "--scale", "2.0", "--mask", "False", "--label", "a b", "--device", "cpu"]
    # rendering uses the settings the run was trained with, whatever the method object's
    resolve(str(settings_spec(tmp_path))).render(tmp_path / "run", tiny_dataset, "test", tmp_path / "renders")
    assert echoed(tmp_path / "run" / "render-test.log")["argv"][-1] == "256"
    assert json.loads((tmp_path / "run" / "method.json").read_text())["settings"] == {
        "rays": 256, "scale": 2.0, "mask": False, "label": "a b"}


@pytest.mark.parametrize("settings, message", [
    ({"ray": 5}, "unknown setting 'ray' (its spec's settings: label, mask, rays, scale)"),
    ({"rays": "many"}, "setting rays must be a int like its default 4096, got 'many'"),
    ({"rays": True}, "setting rays must be a int"),
    ({"mask": 1}, "setting mask must be a bool"),
    ({"scale": float("nan")}, "setting scale must be a float"),
])
def test_a_bad_setting_is_one_line_before_anything_runs(tiny_dataset, tmp_path, settings, message):
    spec = settings_spec(tmp_path)
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")) as error:
        resolve(str(spec), settings)
    assert "\n" not in str(error.value)
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        resolve(str(spec)).train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=1, settings=settings))
    assert not (tmp_path / "run").exists()


def test_a_device_the_spec_does_not_name_is_refused_before_anything_runs(tiny_dataset, tmp_path):
    method = resolve(str(settings_spec(tmp_path)))
    with pytest.raises(InputError, match="runs on cpu, auto, not on device 'cuda'"):
        method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=1, device="cuda"))
    assert not (tmp_path / "run").exists()
    # auto: the machine's device where the table names it (here cpu, without a GPU), else the auto entry
    method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=1))
    argv = echoed(tmp_path / "run" / "train.log")["argv"]
    if cuda_available():
        assert argv[-1] == "a b"  # cuda: not in the table, the auto entry (nothing appended)
    else:
        assert argv[-2:] == ["--device", "cpu"]


@pytest.mark.parametrize("body, message", [
    ('[settings]\nsteps = 3\n[train]\ncommand = ["a"]\n[render]\ncommand = ["a"]\nlayout = "nerfgauge"',
     "settings.steps: a name of lower-case letters"),
    ('[settings]\nx = [1, 2]\n[train]\ncommand = ["a"]\n[render]\ncommand = ["a"]\nlayout = "nerfgauge"',
     "settings.x must be a boolean, number or string"),
    ('[train]\ncommand = ["a"]\ndevices = { gpu = [] }\n[render]\ncommand = ["a"]\nlayout = "nerfgauge"',
     "train.devices.gpu: not a device"),
    ('[train]\ncommand = ["a", "{env}/x"]\n[render]\ncommand = ["a"]\nlayout = "nerfgauge"',
     "the spec names no environment"),
    ('[environment]\nname = "a"\nbin = "/x"\n[train]\ncommand = ["a"]\n[render]\ncommand = ["a"]\nlayout = "nerfgauge"',
     "not both"),
    ('[prepare]\ntorchvision_alexnet = "/tmp/torch"\n[train]\ncommand = ["a"]\n[render]\ncommand = ["a"]\n'
     'layout = "nerfgauge"', "prepare.torchvision_alexnet must be a path inside the run folder"),
    ('[prepare]\ndownload = "{run}/x"\n[train]\ncommand = ["a"]\n[render]\ncommand = ["a"]\nlayout = "nerfgauge"',
     "unknown field prepare.download"),
    ('install = [["pip", "install", "{run}"]]\n[environment]\nname = "a"\n[train]\ncommand = ["a"]\n'
     '[render]\ncommand = ["a"]\nlayout = "nerfgauge"', "unknown placeholder {run}"),
    ('install = "pip install x"\n[environment]\nvariables = { X = "{out}" }\n[train]\ncommand = ["a"]\n'
     '[render]\ncommand = ["a"]\nlayout = "nerfgauge"', "unknown placeholder {out}"),
])
def test_a_bad_spec_field_of_the_new_kinds_is_one_line(tmp_path, body, message):
    spec = tmp_path / "bad.toml"
    spec.write_text('name = "x"\n' + body)
    with pytest.raises(InputError, match=message.replace("{", r"\{").replace("}", r"\}")) as error:
        read_spec(spec)
    assert "\n" not in str(error.value)


def test_a_method_with_its_own_schedule_takes_no_steps(tiny_dataset, tmp_path):
    spec = echo_spec(tmp_path, f'[train]\ncommand = [{json.dumps(sys.executable)}, PROGRAM]\nlength = "own"\n'
                               '[render]\ncommand = ["x"]\nlayout = "nerfgauge"\n')
    method = resolve(str(spec))
    with pytest.raises(InputError, match="trains its own schedule"):
        method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=10))
    result = method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run"))
    assert result.steps is None and method.accepts_budget is False


# --- named environments and their install ------------------------------------------------------


def env_spec(tmp_path, install_lines: list, extra_arguments=()) -> Path:
    """A spec whose environment "toolbox" is built by `install_lines` (python -c programs,
    given {env} and then `extra_arguments`)."""
    install = json.dumps([[sys.executable, "-c", code, "{env}", *extra_arguments] for code in install_lines])
    return echo_spec(tmp_path, f'install = {install}\n[environment]\nname = "toolbox"\n'
                               'variables = { MARK = "{env}" }\n'
                               '[train]\ncommand = ["tool", PROGRAM]\n[render]\ncommand = ["tool"]\n'
                               'layout = "nerfgauge"\n', name="toolbox")


MAKE_TOOL = ("import os, sys, pathlib; b = pathlib.Path(sys.argv[1]) / 'bin'; b.mkdir(parents=True); "
             f"t = b / 'tool'; t.write_text('#!/bin/sh\\nexec {sys.executable} \"$@\"\\n'); t.chmod(0o755)")


def test_a_named_environment_is_installed_and_used_by_its_method(tiny_dataset, tmp_path, monkeypatch, capsys):
    from nerfgauge.cli import main

    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    monkeypatch.delenv("NERFGAUGE_ENV_TOOLBOX", raising=False)
    monkeypatch.setenv("PYTHONPATH", str(tmp_path / "ours"))
    spec = env_spec(tmp_path, [MAKE_TOOL])
    method = resolve(str(spec))
    with pytest.raises(MethodFailed, match=r"its environment .*toolbox is not installed: run `nerfgauge methods "
                                           r"install toolbox`, or set NERFGAUGE_ENV_TOOLBOX"):
        method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=1))
    assert not (tmp_path / "run").exists()
    assert main(["methods", "install", str(spec)]) == 0
    folder = tmp_path / "data" / "nerfgauge" / "envs" / "toolbox"
    assert f"toolbox: environment installed: {folder}" in capsys.readouterr().out
    assert json.loads((folder / "nerfgauge-environment.json").read_text())["state"] == "complete"
    method.train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=1))
    seen = echoed(tmp_path / "run" / "train.log")["env"]
    assert seen["MARK"] == str(folder) and seen["VIRTUAL_ENV"] == str(folder)
    assert seen["PATH"].split(os.pathsep)[0] == str(folder / "bin") and seen["PYTHONPATH"] is None
    assert main(["methods", "install", str(spec)]) == 0
    assert "already installed" in capsys.readouterr().out
    # another folder: the method is told where it looks
    assert main(["methods", "install", str(spec), "--env", str(tmp_path / "elsewhere")]) == 0
    assert f"set NERFGAUGE_ENV_TOOLBOX={tmp_path / 'elsewhere'}" in capsys.readouterr().out


def test_an_interrupted_install_is_never_taken_for_a_complete_one(tiny_dataset, tmp_path, capsys, monkeypatch):
    from nerfgauge.cli import main

    target = tmp_path / "env"
    monkeypatch.setenv("NERFGAUGE_ENV_TOOLBOX", str(target))
    failing = env_spec(tmp_path, [MAKE_TOOL, "import sys; sys.exit(4)"])
    assert main(["methods", "install", str(failing), "--env", str(target)]) == 2
    error = capsys.readouterr().err
    assert "line 2 of 2" in error and "exited with status 4" in error and "\n" not in error.strip()
    assert json.loads((target / "nerfgauge-environment.json").read_text())["state"] == "building"
    # its bin/tool was made by the first line, but the method refuses the half-built environment
    assert (target / "bin" / "tool").is_file()
    with pytest.raises(MethodFailed, match=f"its environment {target} is incomplete .*install toolbox` again"):
        resolve(str(failing)).train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=1))
    assert not (tmp_path / "run").exists()
    fixed = env_spec(tmp_path, [MAKE_TOOL])  # the same folder, built again from scratch
    assert main(["methods", "install", str(fixed), "--env", str(target)]) == 0
    assert "environment installed" in capsys.readouterr().out and (target / "bin" / "tool").is_file()
    assert json.loads((target / "nerfgauge-environment.json").read_text())["state"] == "complete"
    resolve(str(fixed)).train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=1))


def test_a_file_beside_the_spec_that_its_install_names_is_part_of_the_environment(tmp_path, capsys):
    """{spec_folder}/pins.txt (a constraints file): the same file, nothing to do; another
    content, built again; no such file, one line before anything runs."""
    from nerfgauge.cli import main

    target, pins = tmp_path / "env", tmp_path / "pins.txt"
    copy = MAKE_TOOL + "; (b.parent / 'pins-used').write_text(pathlib.Path(sys.argv[2]).read_text())"
    spec = str(env_spec(tmp_path, [copy], ["{spec_folder}/pins.txt"]))
    pins.write_text("tool==1\n")
    assert main(["methods", "install", spec, "--env", str(target)]) == 0
    assert (target / "pins-used").read_text() == "tool==1\n" and "environment installed" in capsys.readouterr().out
    assert main(["methods", "install", spec, "--env", str(target)]) == 0
    assert "already installed" in capsys.readouterr().out
    pins.write_text("tool==2\n")
    assert main(["methods", "install", spec, "--env", str(target)]) == 0
    assert (target / "pins-used").read_text() == "tool==2\n" and "environment installed" in capsys.readouterr().out
    pins.unlink()
    assert main(["methods", "install", spec, "--env", str(target)]) == 2
    error = capsys.readouterr().err
    assert f"its install lines name {pins}, which is not a file" in error and "\n" not in error.strip()
    assert (target / "pins-used").read_text() == "tool==2\n"  # refused before anything was touched


def test_install_refuses_a_folder_it_did_not_build_untouched(tmp_path, capsys):
    from nerfgauge.cli import main

    users = tmp_path / "my-venv"
    users.mkdir()
    (users / "keep.txt").write_text("mine")
    assert main(["methods", "install", str(env_spec(tmp_path, [MAKE_TOOL])), "--env", str(users)]) == 2
    assert "was not built by `nerfgauge methods install`" in capsys.readouterr().err
    assert sorted(p.name for p in users.iterdir()) == ["keep.txt"]


def test_install_lines_that_do_not_make_the_command_leave_it_incomplete(tmp_path, capsys):
    from nerfgauge.cli import main

    target = tmp_path / "env"
    assert main(["methods", "install", str(env_spec(tmp_path, ["pass"])), "--env", str(target)]) == 2
    assert "holds no tool" in capsys.readouterr().err
    assert json.loads((target / "nerfgauge-environment.json").read_text())["state"] == "building"


def test_the_torchvision_alexnet_step_names_the_lpips_install_when_weights_are_missing(tiny_dataset, tmp_path,
                                                                                    monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "empty-cache"))
    spec = write_spec(tmp_path, extra='[prepare]\ntorchvision_alexnet = "{run}/torch-home"\n')
    with pytest.raises(MethodFailed, match=r"prepare.torchvision_alexnet: .*run `nerfgauge lpips install`"):
        resolve(str(spec)).train(TrainRequest(dataset=tiny_dataset, run=tmp_path / "run", steps=1))
    assert not (tmp_path / "run" / "train.log").exists()  # nothing ran
