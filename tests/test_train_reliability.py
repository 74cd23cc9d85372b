"""Runs that can always restart: resuming from any checkpoint gives exactly the model of an
uninterrupted run, a run killed before its first checkpoint starts over, a torn log line
is dropped, foreign or damaged checkpoints and bad flags are one line and exit 2.

The equality tests compare every tensor with torch.equal at 2 CPU threads (the config's
`threads`), both in model.pt and in the final checkpoint.pt (float32: model.pt's pruned
grid is float16, which could hide a difference below its resolution).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
import torch
from cli_errors import one_line_exit_2
from nerfgauge.nerf import train as train_module
from nerfgauge.nerf.config import TrainConfig
from nerfgauge.nerf.train import train

from nerfgauge.cli import main
from nerfgauge.core.errors import InputError


class Killed(Exception):
    """Stands for the process dying at this point."""


def tiny_config(dataset, **overrides) -> TrainConfig:
    """Small batches and grids so a step takes milliseconds; view-dependent colour so the
    colour MLP and its Adam moments are part of the state; val PSNR points every 0.2 s of
    training time, so they fall at different steps in every run."""
    settings = dict(dataset=str(dataset), steps=20, batch_rays=128, eval_rays=256, eval_views=1, final_resolution=24,
                    start_resolution=12, view_dependent=True, eval_every_seconds=0.2, checkpoint_every=10, threads=2)
    return TrainConfig(**(settings | overrides))


def kill_after_checkpoint(monkeypatch, step: int) -> None:
    """The next training run dies right after writing the checkpoint of `step`."""
    real = train_module._save_checkpoint

    def save(run_dir, training, config, recipe):
        real(run_dir, training, config, recipe)
        if training.loop.step == step:
            raise Killed

    monkeypatch.setattr(train_module, "_save_checkpoint", save)


def tensors(obj, prefix=""):
    """{path: tensor} of every tensor in a nested payload."""
    if isinstance(obj, torch.Tensor):
        return {prefix: obj}
    if isinstance(obj, dict):
        return {k: v for key, value in obj.items() for k, v in tensors(value, f"{prefix}/{key}").items()}
    if isinstance(obj, (list, tuple)):
        return {k: v for i, value in enumerate(obj) for k, v in tensors(value, f"{prefix}/{i}").items()}
    return {}


def assert_same_model(run_a, run_b):
    """model.pt and the final checkpoint's model and Adam state: equal tensor for tensor."""
    for name, part in (("model.pt", lambda p: p), ("checkpoint.pt", lambda p: {k: p[k] for k in ("model", "optimizer")})):
        a = tensors(part(torch.load(run_a / name, weights_only=True)))
        b = tensors(part(torch.load(run_b / name, weights_only=True)))
        assert a.keys() == b.keys() and a
        different = [key for key in a if not torch.equal(a[key], b[key])]
        assert not different, f"{name}: {different}"


def log_steps(run):
    return [json.loads(line)["step"] for line in (run / "log.jsonl").read_text().splitlines()]


def test_resume_from_a_checkpoint_equals_an_uninterrupted_run(tiny_dataset, tmp_path, monkeypatch):
    config = tiny_config(tiny_dataset)
    global_rng = torch.get_rng_state()
    train(config, tmp_path / "whole", progress=False)
    assert torch.equal(torch.get_rng_state(), global_rng)  # training draws only from its own generators
    kill_after_checkpoint(monkeypatch, 10)
    with pytest.raises(Killed):
        train(config, tmp_path / "resumed", progress=False)
    assert not (tmp_path / "resumed" / "model.pt").exists()
    monkeypatch.undo()
    train(config, tmp_path / "resumed", resume=True, progress=False)
    assert_same_model(tmp_path / "whole", tmp_path / "resumed")
    steps = log_steps(tmp_path / "resumed")
    assert steps[0] == 0 and steps[-1] == 20 and steps == sorted(set(steps))


@pytest.fixture(scope="module")
def long_reference(tiny_dataset, tmp_path_factory):
    """130 steps: the grid is upsampled at step 100 (MIN_STAGE_STEPS), occupancy is then
    updated every 16 steps, visibility is measured at steps 52, 91 and 130."""
    config = tiny_config(tiny_dataset, steps=130)
    run = tmp_path_factory.mktemp("reference") / "whole"
    train(config, run, progress=False)
    assert torch.load(run / "model.pt", weights_only=True)["resolution"] != config.start_resolution
    return config, run


@pytest.mark.slow
def test_resume_across_upsampling_and_occupancy_updates(long_reference, tmp_path, monkeypatch):
    config, reference = long_reference
    run = tmp_path / "twice"
    for kill_at in (60, 110):  # before and after the upsampling (and the optimizer's re-init)
        kill_after_checkpoint(monkeypatch, kill_at)
        with pytest.raises(Killed):
            train(config, run, resume=kill_at != 60, progress=False)
        monkeypatch.undo()
    train(config, run, resume=True, progress=False)
    assert_same_model(reference, run)


@pytest.mark.slow
def test_sigkill_right_after_a_checkpoint(long_reference, tmp_path):
    """A real kill (SIGKILL: no cleanup, possibly mid-write of the log or a checkpoint)
    just after the second checkpoint file appears; resuming gives the reference model."""
    config, reference = long_reference
    run = tmp_path / "killed"
    code = ("import sys; from nerfgauge.nerf.config import TrainConfig; from nerfgauge.nerf.train import train; "
            f"train(TrainConfig(**{dataclasses.asdict(config)!r}), sys.argv[1], progress=False)")
    child = subprocess.Popen([sys.executable, "-c", code, str(run)])
    try:
        seen = set()
        deadline = time.monotonic() + 300
        while len(seen) < 2 and time.monotonic() < deadline and child.poll() is None:
            try:
                seen.add(os.stat(run / "checkpoint.pt").st_ino)  # each rewrite is a new file renamed into place
            except FileNotFoundError:
                pass
            time.sleep(0.005)
        child.send_signal(signal.SIGKILL)
    finally:
        child.wait()
    assert len(seen) == 2 and not (run / "model.pt").exists(), "the child finished before it was killed"
    train(config, run, resume=True, progress=False)
    assert_same_model(reference, run)
    assert not list(run.glob(".*.tmp*"))


def test_killed_before_its_first_checkpoint_the_same_command_starts_over(tiny_dataset, tmp_path, monkeypatch):
    run = tmp_path / "run"
    argv = ["train", str(tiny_dataset), "--out", str(run), "--steps", "3", "--quiet"]

    def die(*args):
        (run / ".checkpoint.pt.tmp99999").write_bytes(b"half a checkpoint")  # what a kill mid-write leaves
        raise Killed

    for again in ([], ["--resume"]):  # a rerun of the command, or asking to resume: both start over
        monkeypatch.setattr(train_module, "_save_checkpoint", die)
        with pytest.raises(Killed):
            main(argv)
        monkeypatch.undo()
        assert (run / "config.json").exists() and not (run / "checkpoint.pt").exists()
        assert main(argv + again) == 0
        assert log_steps(run) == [0, 3] and (run / "model.pt").exists()
        assert not list(run.glob(".*.tmp*"))
        shutil.rmtree(run)


def test_a_torn_last_log_line_is_dropped_on_resume(tiny_dataset, tmp_path):
    run = tmp_path / "run"
    assert main(["train", str(tiny_dataset), "--out", str(run), "--steps", "3", "--quiet"]) == 0
    with (run / "log.jsonl").open("a") as log:
        log.write('{"step": 4, "seconds": 1.2, "val_ps')  # killed mid-line
    assert main(["train", str(tiny_dataset), "--out", str(run), "--steps", "5", "--resume", "--quiet"]) == 0
    assert log_steps(run) == [0, 3, 5]



@pytest.fixture(scope="module")
def finished_run(tiny_dataset, tmp_path_factory):
    run = tmp_path_factory.mktemp("finished") / "run"
    assert main(["train", str(tiny_dataset), "--out", str(run), "--steps", "2", "--quiet"]) == 0
    return run


def test_a_finished_run_is_refused_without_resume_and_replaced_with_overwrite(tiny_dataset, finished_run, tmp_path,
                                                                                capsys):
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    before = (run / "model.pt").read_bytes()
    one_line_exit_2(capsys, ["train", str(tiny_dataset), "--out", str(run), "--steps", "2"], "finished run")
    assert (run / "model.pt").read_bytes() == before
    one_line_exit_2(capsys, ["train", str(tiny_dataset), "--out", str(run), "--steps", "2", "--resume", "--overwrite"],
                    "not allowed with")
    (run / "renders").mkdir()
    (run / "renders" / "stale.png").write_bytes(b"")
    (run / "renders" / ".nerfgauge.json").write_text(json.dumps({"kind": "renders", "recipe": None}))
    assert main(["train", str(tiny_dataset), "--out", str(run), "--steps", "1", "--overwrite", "--quiet"]) == 0
    assert log_steps(run) == [0, 1] and not (run / "renders").exists()  # renders of the old model went with it


def test_a_folder_nerfgauge_did_not_make_is_never_used(tiny_dataset, tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("years of work")
    for extra in ([], ["--overwrite"], ["--resume"]):
        one_line_exit_2(capsys, ["train", str(tiny_dataset), "--out", str(mine), "--steps", "1", *extra],
                        str(mine))
    assert sorted(p.name for p in mine.iterdir()) == ["thesis.tex"]
    one_line_exit_2(capsys, ["train", str(tiny_dataset), "--out", str(tmp_path / "nowhere"), "--steps", "1",
                             "--resume"], "nothing to resume")
    assert not (tmp_path / "nowhere").exists()


@pytest.mark.parametrize("flags, expected", [
    (["--steps", "5", "--tv-weight", "nan"], "--tv-weight"),
    (["--steps", "5", "--tv-weight", "-1"], "--tv-weight"),
    (["--steps", "5", "--eval-every", "inf"], "--eval-every"),
    (["--steps", "5", "--eval-every", "0"], "--eval-every"),
    (["--budget-seconds", "nan"], "--budget-seconds"),
    (["--budget-seconds", "inf"], "--budget-seconds"),
    (["--steps", "-3"], "--steps"),
    (["--steps", "5", "--checkpoint-every", "0"], "--checkpoint-every"),
    (["--steps", "5", "--threads", "0"], "--threads"),
    (["--steps", "5", "--resolution", "nan"], "--resolution"),
    (["--steps", "5", "--resolution", "2"], "--resolution"),
    (["--steps", "5", "--seed", "-1"], "--seed"),
    (["--steps", "5", "--batch-rays", "0"], "--batch-rays"),
    (["--steps", "5", "--batch-rays", "1.5"], "--batch-rays"),
    (["--steps", "5", "--device", "tpu"], "tpu"),
    (["--steps", "5", "--out", ""], "--out"),
])
def test_bad_train_flags(tiny_dataset, tmp_path, capsys, flags, expected):
    argv = ["train", str(tiny_dataset), "--out", str(tmp_path / "run"), *flags]
    one_line_exit_2(capsys, argv, expected)
    assert not (tmp_path / "run").exists() and sorted(os.listdir(tmp_path)) == []


def test_an_empty_dataset_path_is_refused(tmp_path, capsys):
    one_line_exit_2(capsys, ["train", "", "--out", str(tmp_path / "run"), "--steps", "1"], "dataset")


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_cuda_without_a_gpu_is_one_line(tiny_dataset, tmp_path, capsys):
    one_line_exit_2(capsys, ["train", str(tiny_dataset), "--out", str(tmp_path / "run"), "--steps", "1",
                             "--device", "cuda"], "no CUDA GPU")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("field, value", [
    ("tv_weight", math.nan), ("tv_weight", math.inf), ("distortion_weight", math.nan), ("lr", math.inf),
    ("lr_mlp", math.nan), ("step_ratio", math.nan), ("step_ratio", 2.5), ("eval_every_seconds", math.inf),
    ("budget_seconds", math.nan), ("batch_rays", 0), ("batch_rays", 2.0), ("batch_rays", (1 << 20) + 1),
    ("threads", True), ("checkpoint_every", 0), ("dataset", ""), ("device", "cuda:x"), ("prune", "yes"),
])
def test_the_api_refuses_what_the_flags_refuse(field, value):
    settings = {"dataset": "data", "steps": 5} | ({"steps": None} if field == "budget_seconds" else {})
    with pytest.raises(InputError):
        TrainConfig(**(settings | {field: value})).validate()


@pytest.mark.parametrize("flags, expected", [
    (["--step-ratio", "nan"], "--step-ratio"),
    (["--step-ratio", "0"], "--step-ratio"),
    (["--threads", "0"], "--threads"),
    (["--out", ""], "--out"),
])
def test_bad_render_flags(finished_run, capsys, flags, expected):
    one_line_exit_2(capsys, ["render", str(finished_run), *flags], expected)


def test_render_claims_its_folder(tiny_dataset, finished_run, tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    one_line_exit_2(capsys, ["render", str(finished_run), "--out", str(mine), "--quiet"], "not made by nerfgauge")
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    out = tmp_path / "renders"
    assert main(["render", str(finished_run), "--out", str(out), "--quiet"]) == 0
    assert main(["render", str(finished_run), "--out", str(out), "--quiet"]) == 0  # same model: rendered again
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    assert main(["train", str(tiny_dataset), "--out", str(run), "--steps", "3", "--resume", "--quiet"]) == 0
    one_line_exit_2(capsys, ["render", str(run), "--out", str(out), "--quiet"], "--overwrite")  # another model
    assert main(["render", str(run), "--out", str(out), "--overwrite", "--quiet"]) == 0


# --------------------------------------------------------------------------------------
# foreign and damaged checkpoints


def resume_argv(dataset, run, *extra):
    return ["train", str(dataset), "--out", str(run), "--steps", "4", "--resume", *extra]


def test_a_run_of_another_dataset_or_resolution_is_not_resumed(tiny_dataset, finished_run, tmp_path, capsys):
    other = tmp_path / "other-data"  # the same frames, another manifest: another dataset as far as a hash knows
    shutil.copytree(tiny_dataset, other)
    manifest = json.loads((other / "manifest.json").read_text())
    (other / "manifest.json").write_text(json.dumps(manifest, indent=4))
    one_line_exit_2(capsys, resume_argv(other, finished_run), "another dataset")
    one_line_exit_2(capsys, resume_argv(tiny_dataset, finished_run, "--resolution", "20"), "final_resolution")
    one_line_exit_2(capsys, resume_argv(tiny_dataset, finished_run, "--model", "vanilla"), "model")
    one_line_exit_2(capsys, resume_argv(tiny_dataset, finished_run, "--view-dependent", "on"), "view_dependent")
    # a run made with another marching step (older runs in contracted space took half a
    # voxel): the message names the flag that resumes it
    one_line_exit_2(capsys, resume_argv(tiny_dataset, finished_run, "--step-ratio", "0.7"),
                    "step_ratio 0.5 (this command: 0.7; --step-ratio sets it)")
    one_line_exit_2(capsys, resume_argv(tiny_dataset, finished_run, "--batch-rays", "1000"),
                    "batch_rays 4096 (this command: 1000; --batch-rays sets it)")


def test_a_checkpoint_copied_from_another_run_is_refused(tiny_dataset, finished_run, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", str(tiny_dataset), "--out", str(run), "--steps", "2", "--resolution", "20", "--quiet"]) == 0
    shutil.copyfile(finished_run / "checkpoint.pt", run / "checkpoint.pt")
    one_line_exit_2(capsys, resume_argv(tiny_dataset, run, "--resolution", "20"), "comes from another run")


def damage(run, change):
    payload = torch.load(run / "checkpoint.pt", weights_only=True)
    change(payload)
    torch.save(payload, run / "checkpoint.pt")


class RunsCode:
    """A pickle that would run code when loaded (a file appears): weights_only refuses it."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.mark.parametrize("case, expected", [
    ("missing grid", "missing field.index"),
    ("grid shape", "field.index is"),
    ("index range", "addresses rows outside"),
    ("adam moment shape", "exp_avg"),
    ("adam moment dtype", "expected torch.float32"),
    ("adam step as bool", "expected a float or a wide integer"),
    ("adam step as uint8", "expected a float or a wide integer"),
    ("adam step below 0", "expected a finite count >= 0"),
    ("no loop", "no loop state"),
    ("edge points 0", "loop value edge_points is 0"),
    ("edge points as float", "loop value edge_points is 2.5"),
    ("generator", "generator"),
    ("old format", "not a nerfgauge checkpoint"),
    ("truncated", "not a readable"),
    ("code", "not a readable"),
])
def test_damaged_checkpoints_are_one_line(tiny_dataset, finished_run, tmp_path, capsys, case, expected):
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    marker = tmp_path / "code-ran"
    if case == "missing grid":
        damage(run, lambda p: p["model"]["state"].pop("field.index"))
    elif case == "grid shape":
        damage(run, lambda p: p["model"]["state"].update({"field.index": torch.zeros(5, 5, 5, dtype=torch.int32)}))
    elif case == "index range":
        damage(run, lambda p: p["model"]["state"]["field.index"].view(-1)[0:1].fill_(1 << 30))
    elif case == "adam moment shape":
        damage(run, lambda p: p["optimizer"]["state"][0].update({"exp_avg": torch.zeros(3)}))
    elif case == "adam moment dtype":
        damage(run, lambda p: p["optimizer"]["state"][0].update(exp_avg=p["optimizer"]["state"][0]["exp_avg"].double()))
    elif case.startswith("adam step"):
        step = {"adam step as bool": torch.tensor(True), "adam step as uint8": torch.tensor(5, dtype=torch.uint8),
                "adam step below 0": torch.tensor(-1.0)}[case]
        damage(run, lambda p: p["optimizer"]["state"][0].update(step=step))
    elif case == "no loop":
        damage(run, lambda p: p.pop("loop"))
    elif case.startswith("edge points"):  # rays per axis through an edge pixel: a whole number >= 1
        damage(run, lambda p: p["loop"].update(edge_points=0 if case.endswith("0") else 2.5))
    elif case == "generator":
        damage(run, lambda p: p.update(generator=torch.zeros(7, dtype=torch.uint8)))
    elif case == "old format":
        damage(run, lambda p: p.update(format="nerfgauge-model", version=1))
    elif case == "truncated":
        data = (run / "checkpoint.pt").read_bytes()
        (run / "checkpoint.pt").write_bytes(data[:len(data) // 2])
    elif case == "code":
        torch.save({"format": "nerfgauge-checkpoint", "payload": RunsCode(marker)}, run / "checkpoint.pt")
    one_line_exit_2(capsys, resume_argv(tiny_dataset, run), expected)
    assert not marker.exists()


def test_a_second_writer_is_refused_while_a_run_trains(tiny_dataset, tmp_path, monkeypatch):
    run = tmp_path / "run"
    real = train_module._save_checkpoint
    attempts = []

    def save_and_intrude(run_dir, *args):
        real(run_dir, *args)
        if not attempts:  # another writer of the same run into the same folder, mid-run
            with pytest.raises(InputError) as refused:
                train(config, run, resume=True, progress=False)
            attempts.append(str(refused.value))

    config = tiny_config(tiny_dataset, steps=2)
    monkeypatch.setattr(train_module, "_save_checkpoint", save_and_intrude)
    train(config, run, progress=False)
    assert "in use" in attempts[0] and f"PID {os.getpid()}" in attempts[0]
    steps = log_steps(run)  # val points fall on the training clock: how many depends on the load
    assert steps[0] == 0 and steps[-1] == 2 and steps == sorted(set(steps)), steps
