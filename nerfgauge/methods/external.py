"""Other tools' methods, run from their own command lines: a method spec (TOML) says how.

    name = "nerfacto"                       # the method's name (its results folder)
    summary = "nerfstudio's nerfacto"
    install = "python -m venv ~/venvs/ns && ..."   # how to make its environment (documentation)
    [needs]                                 # interface.Needs fields (default: transforms only)
    colmap_model = true
    [produces]                              # interface.Produces fields (default: colour only)
    depth = true
    [environment]
    bin = "~/venvs/ns/bin"                  # put first on PATH: the tool's own interpreter and scripts
    variables = { TORCH_HOME = "{run}/torch-home" }
    [train]
    command = ["ns-train", "nerfacto", "--data", "{dataset}", "--output-dir", "{run}/out",
               "--max-num-iterations", "{steps}", "--machine.seed", "{seed}"]
    length = "steps"                        # what the tool takes: "steps", "seconds" or "both"
    [render]
    command = ["ns-render", "dataset", "--load-config", "{config}", "--output-path", "{out}",
               "--split", "{split}"]
    layout = "nerfstudio"                   # how `evaluate` reads the renders (eval.predictions)
    renders = "{out}"                       # the folder evaluate's --pred takes (default {out})
    [files]
    config = "{run}/out/**/config.yml"      # named files found after training, as placeholders

Placeholders, replaced in every argument and variable: {dataset} {run} {seed} {steps}
{budget_seconds} {threads} {device} {split} {out}, and the [files] entries (a glob inside
the run folder that must match exactly one file). An unknown placeholder is refused when the
spec is read, not when the command runs.

Each command runs as a subprocess from an argument list (never a shell), in the run folder,
with its output in the run folder (train.log, render-<split>.log). The harness records wall
time, CPU time and peak memory from the child's own resource usage (os.wait4) and its exit
status; a command that runs past twice its budget (steps-counted tools: `timeout_seconds`,
default none) is stopped with its whole process group. A method that fails (non-zero exit,
stopped, or no renders) raises `MethodFailed` with the reason; suites give it its row and go
on with their other jobs.
"""

from __future__ import annotations

import glob
import os
import re
import string
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from nerfgauge.core import arguments, bounded
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, write_json
from nerfgauge.core.folders import claim_folder, read_marker, recipe_hash, remove_owned
from nerfgauge.core.owned import make_folder, open_append
from nerfgauge.methods.interface import Method, Needs, Produces, RenderResult, TrainRequest, TrainResult, check_name
from nerfgauge.methods.measure import Finished, run_process

LAYOUTS = ("nerfgauge", "nerfstudio", "nerfbaselines", "folder")
LENGTHS = ("steps", "seconds", "both")
TRAIN_PLACEHOLDERS = ("dataset", "run", "seed", "steps", "budget_seconds", "threads", "device")
RENDER_PLACEHOLDERS = (*TRAIN_PLACEHOLDERS, "split", "out")
OVERRUN = 2.0  # a command is stopped once it has run this many times its budget
RESULT = "method.json"  # RUN/method.json: the spec, the request and what training cost


class MethodFailed(InputError):
    """The method ran and failed: its row on a leaderboard says `reason`."""

    def __init__(self, method: str, reason: str):
        super().__init__(f"method {method}: {reason}")
        self.method, self.reason = method, reason


@dataclass(frozen=True)
class Command:
    argv: tuple  # templates
    timeout_seconds: float | None = None


@dataclass(frozen=True)
class Spec:
    name: str
    summary: str
    source: str
    install: str
    needs: Needs
    produces: Produces
    bin: str | None
    variables: dict
    train: Command
    length: str
    render: Command
    layout: str
    renders: str
    files: dict = field(default_factory=dict)

    def definition(self) -> dict:
        """What makes a run of this spec what it is (recorded in the run, part of its recipe)."""
        return {"name": self.name, "train": list(self.train.argv), "render": list(self.render.argv),
                "length": self.length, "layout": self.layout, "renders": self.renders, "files": self.files,
                "variables": self.variables}


# --- reading a spec --------------------------------------------------------------------------


def _placeholders(template: str, where: str) -> set:
    """The names of `{name}` placeholders in a template; format specs and conversions refused."""
    names = set()
    try:
        parsed = list(string.Formatter().parse(template))
    except ValueError as error:
        raise InputError(f"{where}: {template!r} is not a valid template: {error}") from None
    for _, name, spec, conversion in parsed:
        if name is None:
            continue
        if spec or conversion or not re.fullmatch(r"[a-z_][a-z0-9_]*", name):
            raise InputError(f"{where}: {template!r}: a placeholder is a plain {{name}}, got {{{name}}}")
        names.add(name)
    return names


def _check_template(template, allowed, where: str) -> str:
    if not isinstance(template, str) or "\0" in template:
        raise InputError(f"{where} must be a string without NUL, got {template!r}")
    for name in _placeholders(template, where):
        if name not in allowed:
            raise InputError(f"{where}: unknown placeholder {{{name}}} in {template!r}; known: "
                             + ", ".join(f"{{{p}}}" for p in allowed))
    return template


def _table(data: dict, key: str, source: str, allowed: set, required=()) -> dict:
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise InputError(f"{source}: [{key}] must be a table")
    unknown = sorted(set(value) - allowed)
    if unknown:
        raise InputError(f"{source}: unknown field {key}.{unknown[0]}; known: {', '.join(sorted(allowed))}")
    for name in required:
        if name not in value:
            raise InputError(f"{source}: missing field {key}.{name}")
    return value


def _flags(cls, table: dict, key: str, source: str):
    for name, value in table.items():
        if not isinstance(value, bool):
            raise InputError(f"{source}: {key}.{name} must be true or false, got {value!r}")
    return cls(**table)


def _command(table: dict, key: str, source: str, allowed) -> Command:
    argv = table["command"]
    if not isinstance(argv, list) or not argv:
        raise InputError(f"{source}: {key}.command must be a non-empty list of arguments (no shell)")
    argv = tuple(_check_template(arg, allowed, f"{source}: {key}.command[{i}]") for i, arg in enumerate(argv))
    timeout = table.get("timeout_seconds")
    if timeout is not None:
        arguments.SECONDS.check(timeout, f"{source}: {key}.timeout_seconds")
    return Command(argv, None if timeout is None else float(timeout))


def parse_spec(data: dict, source: str) -> Spec:
    top = {"name", "summary", "install", "needs", "produces", "environment", "train", "render", "files"}
    unknown = sorted(set(data) - top)
    if unknown:
        raise InputError(f"{source}: unknown field {unknown[0]!r}; known: {', '.join(sorted(top))}")
    if "name" not in data:
        raise InputError(f"{source}: missing field name")
    name = check_name(data["name"], f"{source}: name")
    for text in ("summary", "install"):
        if not isinstance(data.get(text, ""), str):
            raise InputError(f"{source}: {text} must be a string")
    files = data.get("files", {})
    if not isinstance(files, dict):
        raise InputError(f"{source}: [files] must be a table")
    for key, pattern in files.items():
        if key in RENDER_PLACEHOLDERS or not re.fullmatch(r"[a-z_][a-z0-9_]*", key):
            raise InputError(f"{source}: files.{key}: a name of lower-case letters, digits and '_', not a placeholder")
        _check_template(pattern, ("run",), f"{source}: files.{key}")
        if not pattern.startswith("{run}/") or ".." in Path(pattern).parts:
            raise InputError(f"{source}: files.{key} must be a pattern inside the run folder ({{run}}/...)")
    needs = _flags(Needs, _table(data, "needs", source, {f for f in Needs.__dataclass_fields__}), "needs", source)
    produces = _flags(Produces, _table(data, "produces", source, set(Produces.__dataclass_fields__)), "produces",
                      source)
    environment = _table(data, "environment", source, {"bin", "variables"})
    variables = environment.get("variables", {})
    if not isinstance(variables, dict):
        raise InputError(f"{source}: environment.variables must be a table of strings")
    for key, value in variables.items():
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", key):
            raise InputError(f"{source}: environment.variables: {key!r} is not a variable name")
        _check_template(value, (*TRAIN_PLACEHOLDERS, *files), f"{source}: environment.variables.{key}")
    bin_folder = environment.get("bin")
    if bin_folder is not None and (not isinstance(bin_folder, str) or not bin_folder or "\0" in bin_folder):
        raise InputError(f"{source}: environment.bin must be a folder path")
    train = _table(data, "train", source, {"command", "length", "timeout_seconds"}, required=("command",))
    render = _table(data, "render", source, {"command", "layout", "renders", "timeout_seconds"},
                    required=("command", "layout"))
    length = train.get("length", "steps")
    if length not in LENGTHS:
        raise InputError(f"{source}: train.length must be one of {', '.join(LENGTHS)}, got {length!r}")
    if render["layout"] not in LAYOUTS:
        raise InputError(f"{source}: render.layout must be one of {', '.join(LAYOUTS)}, got {render['layout']!r}")
    render_allowed = (*RENDER_PLACEHOLDERS, *files)
    return Spec(name=name, summary=data.get("summary", ""), source=source, install=data.get("install", ""),
                needs=needs, produces=produces,
                bin=None if bin_folder is None else os.path.expanduser(bin_folder), variables=dict(variables),
                train=_command(train, "train", source, TRAIN_PLACEHOLDERS), length=length,
                render=_command(render, "render", source, render_allowed), layout=render["layout"],
                renders=_check_template(render.get("renders", "{out}"), render_allowed, f"{source}: render.renders"),
                files=dict(files))


def read_spec(path) -> Spec:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"method spec not found: {path}")
    data = bounded.read_bytes(path, bounded.MAX_TOML_BYTES, "method spec")
    try:
        table = bounded.loads_toml(data, str(path))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"{path} is not valid TOML: {error}") from None
    return parse_spec(table, str(path))


def load_spec(path, settings: dict | None = None) -> "ExternalMethod":
    if settings:
        raise InputError(f"method spec {path}: settings go into the spec's commands, not a settings table")
    return ExternalMethod(read_spec(path))


# --- running it ------------------------------------------------------------------------------


def fill(template: str, values: dict) -> str:
    """The template with its placeholders replaced (every one was checked when read)."""
    return template.format_map(values)


def _environment(spec: Spec, values: dict, run: Path) -> dict:
    """The command's environment: ours, its bin folder first on PATH, its variables, and a
    temporary folder inside the run (so what the tool leaves behind stays with the job)."""
    env = dict(os.environ)
    env["TMPDIR"] = str(make_folder(run / ".tmp"))
    if spec.bin is not None:
        env["PATH"] = spec.bin + os.pathsep + env.get("PATH", "")
        env["VIRTUAL_ENV"] = str(Path(spec.bin).parent)
    env.update({key: fill(value, values) for key, value in spec.variables.items()})
    return env


def _executable(argv0: str, env: dict, method: str) -> str:
    """argv[0] as found on the command's own PATH (its environment's bin folder first)."""
    if os.sep in argv0:
        return argv0
    for folder in env.get("PATH", "").split(os.pathsep):
        candidate = Path(folder or ".") / argv0
        if candidate.is_file() and os.access(candidate, os.X_OK):
            return str(candidate)
    raise MethodFailed(method, f"command {argv0!r} not found on its PATH (is its environment installed? "
                               "see the spec's install lines)")


def run_command(argv: list, *, cwd: Path, env: dict, log: Path, timeout: float | None, method: str) -> Finished:
    """Run argv (no shell) in its own process group with stdout and stderr in `log`
    (measure.run_process: its own wall, CPU and peak memory; stopped past `timeout`);
    MethodFailed with the reason when it cannot start, is stopped or exits non-zero."""
    argv = [_executable(argv[0], env, method), *argv[1:]]
    with open_append(log) as output:
        output.write("$ " + " ".join(argv) + "\n")
        output.flush()
        try:
            finished = run_process(argv, cwd=cwd, env=env, stdout=output, timeout=timeout)
        except OSError as error:
            raise MethodFailed(method, f"cannot start {argv[0]}: {error.strerror or error}") from None
    if finished.stopped:
        raise MethodFailed(method, f"ran past {timeout:g} s (twice its budget) and was stopped; log: {log}")
    if finished.status != 0:
        raise MethodFailed(method, f"{Path(argv[0]).name} exited with status {finished.status}; log: {log}")
    return finished


def find_files(spec: Spec, run: Path) -> dict:
    """The [files] placeholders: each pattern must match exactly one file inside the run."""
    found = {}
    for key, pattern in spec.files.items():
        matches = sorted(glob.glob(fill(pattern, {"run": glob.escape(str(run))}), recursive=True))
        matches = [m for m in matches if Path(m).resolve().is_relative_to(run.resolve())]
        if len(matches) != 1:
            raise MethodFailed(spec.name, f"files.{key} ({pattern}) matched {len(matches)} files in {run}, not one")
        found[key] = matches[0]
    return found


class ExternalMethod(Method):
    """A method run through its spec's command lines (see the module docstring)."""

    def __init__(self, spec: Spec):
        self.spec = spec
        self.name, self.summary, self.needs, self.produces = spec.name, spec.summary, spec.needs, spec.produces
        self.accepts_budget = spec.length in ("seconds", "both")

    def describe(self) -> dict:
        return {**super().describe(), "spec": self.spec.source, "install": self.spec.install}

    def values(self, request: TrainRequest) -> dict:
        if self.spec.length == "steps" and request.steps is None:
            raise InputError(f"method {self.name} takes a step count (its spec's train.length is steps)")
        if self.spec.length == "seconds" and request.budget_seconds is None:
            raise InputError(f"method {self.name} takes a time budget (its spec's train.length is seconds)")
        return {"dataset": str(request.dataset.resolve()), "run": str(request.run.resolve()), "seed": request.seed,
                "steps": "" if request.steps is None else request.steps,
                "budget_seconds": "" if request.budget_seconds is None else f"{request.budget_seconds:g}",
                "threads": request.threads or 2, "device": request.device}

    def train(self, request: TrainRequest) -> TrainResult:
        values = self.values(request)
        recipe = recipe_hash({"spec": self.spec.definition(), **{k: v for k, v in values.items() if k != "run"}})
        run = request.run
        _clear_earlier_attempt(run, "run", recipe, request.overwrite)
        with claim_folder(run, "run", recipe):
            env = _environment(self.spec, values, run)
            timeout = (OVERRUN * request.budget_seconds if request.budget_seconds is not None
                       else self.spec.train.timeout_seconds)
            finished = run_command([fill(a, values) for a in self.spec.train.argv], cwd=run, env=env,
                                   log=run / "train.log", timeout=timeout, method=self.name)
            find_files(self.spec, run)  # the files rendering needs are there
            result = TrainResult(seconds=finished.seconds, steps=request.steps, cpu_seconds=finished.cpu_seconds,
                                 peak_memory_bytes=finished.peak_memory_bytes,
                                 extra={"exit_status": finished.status})
            write_json(run / RESULT, {"spec": self.spec.definition(), "request": values, "train": result.to_json()})
        return result

    def render(self, run, dataset, split, out, *, overwrite=False, progress=False) -> RenderResult:
        run, out = Path(run), Path(out)
        recorded = _recorded(run, self)
        values = {**recorded["request"], "run": str(run.resolve()), "dataset": str(Path(dataset).resolve()),
                  "split": split, "out": str(out.resolve()), **find_files(self.spec, run)}
        recipe = recipe_hash({"spec": self.spec.definition(), "run": recorded["train"], "split": split,
                              "dataset": values["dataset"]})
        _clear_earlier_attempt(out, "renders", recipe, overwrite)
        with claim_folder(out, "renders", recipe):
            env = _environment(self.spec, values, run)
            finished = run_command([fill(a, values) for a in self.spec.render.argv], cwd=run, env=env,
                                   log=run / f"render-{split}.log", timeout=self.spec.render.timeout_seconds,
                                   method=self.name)
        renders = Path(fill(self.spec.renders, values))
        frames = _count_images(renders)
        if frames == 0:
            raise MethodFailed(self.name, f"its render command wrote no images under {renders}")
        return RenderResult(out=renders, frames=frames, seconds=finished.seconds, pred_format=self.spec.layout)


def _recorded(run: Path, method: ExternalMethod) -> dict:
    """RUN/method.json, re-checked as on entry: a state file is data, so its request is
    rebuilt through TrainRequest's checks and the spec it names must be this one."""
    path = run / RESULT
    if not path.is_file():
        raise InputError(f"{run} holds no trained run of method {method.name} (no {RESULT}): train it first")
    record = read_json(path, finite=True)
    request, train = record.get("request"), record.get("train")
    if not isinstance(request, dict) or not isinstance(train, dict) or record.get("spec") != method.spec.definition():
        raise InputError(f"{path} is not a record of method {method.name} as its spec is now: train it again")
    try:
        checked = TrainRequest(dataset=run, run=run, seed=request["seed"],
                               steps=request["steps"] if request["steps"] != "" else None,
                               budget_seconds=float(request["budget_seconds"]) if request["budget_seconds"] != "" else None,
                               threads=request["threads"], device=request["device"])
    except (KeyError, TypeError, ValueError) as error:
        raise InputError(f"{path}: a malformed request ({error})") from None
    return {"request": {key: value for key, value in method.values(checked).items() if key not in ("dataset", "run")},
            "train": train}


def _clear_earlier_attempt(folder: Path, kind: str, recipe: str, overwrite: bool) -> None:
    """A job starts clean: an earlier attempt at the same recipe (interrupted, or failed) or,
    with overwrite, any folder of ours of this kind is removed first, so a tool never finds
    its own half-written outputs (two timestamped folders) from before."""
    marker = read_marker(folder) if folder.is_dir() and not folder.is_symlink() else None
    if marker is not None and marker.get("kind") == kind and (overwrite or marker.get("recipe") == recipe):
        remove_owned(folder, kind)


def _count_images(folder: Path) -> int:
    if not folder.is_dir():
        return 0
    return sum(1 for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in (".png", ".jpg", ".jpeg", ".exr"))
