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
