"""Other tools' methods, run from their own command lines: a method spec (TOML) says how.

    name = "nerfacto"                       # the method's name (its results folder)
    summary = "nerfstudio's nerfacto"
    install = [["{python}", "-m", "venv", "{env}"],        # how to build its environment, run by
               ["{env}/bin/python", "-m", "pip", "install", "nerfstudio==1.1.5"]]  # `nerfgauge methods install`
    [needs]                                 # interface.Needs fields (default: transforms only)
    colmap_model = true
    [produces]                              # interface.Produces fields (default: colour only)
    depth = true
    [environment]
    name = "nerfstudio"                     # a named environment (below), or:
    # bin = "~/venvs/ns/bin"                # a folder put first on PATH: the tool's own interpreter and scripts
    variables = { TORCH_HOME = "{run}/torch-home", OMP_NUM_THREADS = "{threads}" }
    [settings]                              # the method's own settings with their defaults, as placeholders;
    rays = 4096                             # a job's settings table overrides them (same type)
    [prepare]                               # files the harness makes in the run before each command
    torchvision_alexnet = "{run}/torch-home"
    [train]
    command = ["ns-train", "nerfacto", "--data", "{dataset}", "--output-dir", "{run}/out",
               "--max-num-iterations", "{steps}", "--machine.seed", "{seed}",
               "--pipeline.datamanager.train-num-rays-per-batch", "{rays}"]
    length = "steps"                        # what the tool takes: "steps", "seconds", "both", or
                                            # "own" (it trains its own schedule: a job gives neither)
    devices = { cpu = ["--machine.device-type", "cpu"], cuda = ["--machine.device-type", "cuda"] }
    [render]
    command = ["ns-render", "dataset", "--load-config", "{config}", "--output-path", "{out}",
               "--split", "{split}"]
    layout = "nerfstudio"                   # how `evaluate` reads the renders (eval.predictions)
    renders = "{out}"                       # the folder evaluate's --pred takes (default {out})
    [files]
    config = "{run}/out/**/config.yml"      # named files found after training, as placeholders

Placeholders, replaced in every argument and variable: {dataset} {run} {seed} {steps}
{budget_seconds} {threads} {device} {env} (the environment's folder) {spec_folder} (the
folder of the spec file: scripts shipped beside it) and the [settings] names; rendering
adds {split} {out} and the [files] entries (a glob inside the run folder that must match
exactly one file); install lines take {env}, {python} (this interpreter: `{python} -m
venv {env}`) and {spec_folder} (a constraints file shipped beside the spec: the
environment's record holds each such file's hash, so changing one rebuilds it). An unknown
placeholder is refused when the spec is read, not when the command runs.

A named environment lives in $NERFGAUGE_ENV_<NAME> (the name upper-cased, '-' and '.' as
'_') when that is set, else in $XDG_DATA_HOME/nerfgauge/envs/<name> (default
~/.local/share/nerfgauge/envs/<name>); `nerfgauge methods install METHOD [--env DIR]` builds
it from the install lines (nerfgauge.methods.install). Its bin folder goes first on the
command's PATH, and PYTHONPATH and PYTHONHOME are dropped: the tool's interpreter sees
only its own packages.

`devices` (train or render): arguments appended for the job's device (auto, cpu or cuda);
a device the table does not name is refused before anything runs. A job's "auto" takes the
entry of this machine's device (cuda with a GPU, else cpu) where the table has one, else
the table's own auto entry (the tool's default). `prepare` steps
(PREPARE_STEPS) write into the run folder only: `torchvision_alexnet` writes torchvision's
AlexNet file, made from the installed LPIPS weights (eval.lpips.write_torchvision_alexnet),
into that TORCH_HOME, so a tool that builds torchmetrics' LPIPS at start-up (nerfstudio)
runs offline.

Each command runs as a subprocess from an argument list (never a shell), in the run folder,
with its output in the run folder (train.log, render-<split>.log). The harness records wall
time, CPU time and peak memory from the child's own resource usage (os.wait4) and its exit
status; a command that runs past twice its budget (steps-counted tools: `timeout_seconds`,
default none) is stopped with its whole process group. A method that fails (non-zero exit,
stopped, no renders, its environment not installed) raises `MethodFailed` with the reason;
suites give it its row and go on with their other jobs.

Shipped specs (nerfgauge/methods/specs/*.toml) are named by their file name, like the
built-in methods (nerfgauge.methods.registry).
"""

from __future__ import annotations

import glob
import os
import re
import shlex
import string
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from nerfgauge.core import arguments, bounded
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, write_json
from nerfgauge.core.folders import claim_folder, read_marker, recipe_hash, remove_owned
from nerfgauge.core.owned import make_folder, open_append
from nerfgauge.generate.variant import cuda_available
from nerfgauge.methods.interface import DEVICES, Method, Needs, Produces, RenderResult, TrainRequest, TrainResult, check_name
from nerfgauge.methods.measure import Finished, run_process

LAYOUTS = ("nerfgauge", "nerfstudio", "nerfbaselines", "folder")
LENGTHS = ("steps", "seconds", "both", "own")  # own: the tool trains its own schedule
CONTEXT_PLACEHOLDERS = ("env", "spec_folder")  # where the tool and the spec's own files are
TRAIN_PLACEHOLDERS = ("dataset", "run", "seed", "steps", "budget_seconds", "threads", "device", *CONTEXT_PLACEHOLDERS)
RENDER_PLACEHOLDERS = (*TRAIN_PLACEHOLDERS, "split", "out")
INSTALL_PLACEHOLDERS = ("env", "python", "spec_folder")
PREPARE_STEPS = ("torchvision_alexnet",)
SETTING_TYPES = (bool, int, float, str)
OVERRUN = 2.0  # a command is stopped once it has run this many times its budget
RESULT = "method.json"  # RUN/method.json: the spec, the request and what training cost
ENV_VARIABLE_PREFIX = "NERFGAUGE_ENV_"
ENVIRONMENT_RECORD = "nerfgauge-environment.json"  # in an environment `nerfgauge methods install` built
DROPPED_VARIABLES = ("PYTHONPATH", "PYTHONHOME")  # ours, not the tool's interpreter's


class MethodFailed(InputError):
    """The method ran and failed: its row on a leaderboard says `reason`."""

    def __init__(self, method: str, reason: str):
        super().__init__(f"method {method}: {reason}")
        self.method, self.reason = method, reason


@dataclass(frozen=True)
class Command:
    argv: tuple  # templates
    timeout_seconds: float | None = None
    devices: dict | None = None  # {device: tuple of argument templates appended}; None: any device, nothing added


@dataclass(frozen=True)
class Spec:
    name: str
    summary: str
    source: str
    install: str | tuple  # a line of text (shown), or argument lists (`nerfgauge methods install` runs them)
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
    environment: str | None = None  # a named environment (module docstring)
    settings: dict = field(default_factory=dict)  # {name: default}
    prepare: dict = field(default_factory=dict)  # {step: folder template inside the run}

    @property
    def folder(self) -> Path:
        return Path(self.source).parent

    def definition(self) -> dict:
        """What makes a run of this spec what it is (recorded in the run, part of its recipe)."""
        def command(c: Command) -> dict:
            return {"argv": list(c.argv), "devices": {k: list(v) for k, v in (c.devices or {}).items()} or None}

        return {"name": self.name, "train": command(self.train), "render": command(self.render),
                "length": self.length, "layout": self.layout, "renders": self.renders, "files": self.files,
                "variables": self.variables, "environment": self.environment, "settings": self.settings,
                "prepare": self.prepare}

    def install_lines(self, env: Path | str | None = None, spec_folder: Path | str | None = None) -> list[str]:
        """The install lines as a user would type them into a shell: {env} as `env` (the
        folder the method looks in), {python} as python3, {spec_folder} as `spec_folder`
        (default: the spec's own folder)."""
        if isinstance(self.install, str):
            return [self.install] if self.install else []
        values = {"env": "{env}" if env is None else str(env), "python": "python3",
                  "spec_folder": str(self.folder.resolve() if spec_folder is None else spec_folder)}
        return [shlex.join(fill(arg, values) for arg in argv) for argv in self.install]


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


def _arguments(value, allowed, where: str) -> tuple:
    if not isinstance(value, list):
        raise InputError(f"{where} must be a list of arguments (no shell)")
    return tuple(_check_template(arg, allowed, f"{where}[{i}]") for i, arg in enumerate(value))


def _command(table: dict, key: str, source: str, allowed) -> Command:
    argv = table["command"]
    if not isinstance(argv, list) or not argv:
        raise InputError(f"{source}: {key}.command must be a non-empty list of arguments (no shell)")
    argv = _arguments(argv, allowed, f"{source}: {key}.command")
    timeout = table.get("timeout_seconds")
    if timeout is not None:
        arguments.SECONDS.check(timeout, f"{source}: {key}.timeout_seconds")
    devices = table.get("devices")
    if devices is not None:
        if not isinstance(devices, dict) or not devices:
            raise InputError(f"{source}: {key}.devices must be a table of device = [arguments]")
        unknown = sorted(set(devices) - set(DEVICES))
        if unknown:
            raise InputError(f"{source}: {key}.devices.{unknown[0]}: not a device; choose from {', '.join(DEVICES)}")
        devices = {device: _arguments(args, allowed, f"{source}: {key}.devices.{device}")
                   for device, args in devices.items()}
    return Command(argv, None if timeout is None else float(timeout), devices)


def _settings(data: dict, source: str, reserved) -> dict:
    table = data.get("settings", {})
    if not isinstance(table, dict):
        raise InputError(f"{source}: [settings] must be a table of name = default")
    for name, value in table.items():
        if not re.fullmatch(r"[a-z_][a-z0-9_]*", name) or name in reserved:
            raise InputError(f"{source}: settings.{name}: a name of lower-case letters, digits and '_', "
                             "not a placeholder or a [files] name")
        if not isinstance(value, SETTING_TYPES) or (isinstance(value, str) and "\0" in value):
            raise InputError(f"{source}: settings.{name} must be a boolean, number or string, got {value!r}")
    return dict(table)


def _install(value, source: str):
    if isinstance(value, str):
        return value
    if not isinstance(value, list) or not all(isinstance(argv, list) and argv for argv in value):
        raise InputError(f"{source}: install must be a line of text or a list of argument lists (no shell)")
    return tuple(_arguments(argv, INSTALL_PLACEHOLDERS, f"{source}: install[{i}]") for i, argv in enumerate(value))


def _inside_run(template: str, where: str) -> None:
    if not template.startswith("{run}/") or ".." in Path(template).parts:
        raise InputError(f"{where} must be a path inside the run folder ({{run}}/...), got {template!r}")


def parse_spec(data: dict, source: str) -> Spec:
    top = {"name", "summary", "install", "needs", "produces", "environment", "settings", "prepare", "train",
           "render", "files"}
    unknown = sorted(set(data) - top)
    if unknown:
        raise InputError(f"{source}: unknown field {unknown[0]!r}; known: {', '.join(sorted(top))}")
    if "name" not in data:
        raise InputError(f"{source}: missing field name")
    name = check_name(data["name"], f"{source}: name")
    if not isinstance(data.get("summary", ""), str):
        raise InputError(f"{source}: summary must be a string")
    install = _install(data.get("install", ""), source)
    files = data.get("files", {})
    if not isinstance(files, dict):
        raise InputError(f"{source}: [files] must be a table")
    for key, pattern in files.items():
        if key in RENDER_PLACEHOLDERS or not re.fullmatch(r"[a-z_][a-z0-9_]*", key):
            raise InputError(f"{source}: files.{key}: a name of lower-case letters, digits and '_', not a placeholder")
        _check_template(pattern, ("run",), f"{source}: files.{key}")
        _inside_run(pattern, f"{source}: files.{key}")
    settings = _settings(data, source, (*RENDER_PLACEHOLDERS, *files))
    needs = _flags(Needs, _table(data, "needs", source, {f for f in Needs.__dataclass_fields__}), "needs", source)
    produces = _flags(Produces, _table(data, "produces", source, set(Produces.__dataclass_fields__)), "produces",
                      source)
    environment = _table(data, "environment", source, {"bin", "name", "variables"})
    train_allowed = (*TRAIN_PLACEHOLDERS, *settings)
    variables = environment.get("variables", {})
    if not isinstance(variables, dict):
        raise InputError(f"{source}: environment.variables must be a table of strings")
    for key, value in variables.items():
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", key):
            raise InputError(f"{source}: environment.variables: {key!r} is not a variable name")
        _check_template(value, train_allowed, f"{source}: environment.variables.{key}")
    bin_folder, env_name = environment.get("bin"), environment.get("name")
    if bin_folder is not None and (not isinstance(bin_folder, str) or not bin_folder or "\0" in bin_folder):
        raise InputError(f"{source}: environment.bin must be a folder path")
    if env_name is not None:
        check_name(env_name, f"{source}: environment.name")
    if bin_folder is not None and env_name is not None:
        raise InputError(f"{source}: give environment.name (a named environment) or environment.bin, not both")
    prepare = _table(data, "prepare", source, set(PREPARE_STEPS))
    for step, template in prepare.items():
        _check_template(template, ("run",), f"{source}: prepare.{step}")
        _inside_run(template, f"{source}: prepare.{step}")
    train = _table(data, "train", source, {"command", "length", "timeout_seconds", "devices"}, required=("command",))
    render = _table(data, "render", source, {"command", "layout", "renders", "timeout_seconds", "devices"},
                    required=("command", "layout"))
    length = train.get("length", "steps")
    if length not in LENGTHS:
        raise InputError(f"{source}: train.length must be one of {', '.join(LENGTHS)}, got {length!r}")
    if render["layout"] not in LAYOUTS:
        raise InputError(f"{source}: render.layout must be one of {', '.join(LAYOUTS)}, got {render['layout']!r}")
    render_allowed = (*RENDER_PLACEHOLDERS, *files, *settings)
    spec = Spec(name=name, summary=data.get("summary", ""), source=source, install=install,
                needs=needs, produces=produces,
                bin=None if bin_folder is None else os.path.expanduser(bin_folder), variables=dict(variables),
                train=_command(train, "train", source, train_allowed), length=length,
                render=_command(render, "render", source, render_allowed), layout=render["layout"],
                renders=_check_template(render.get("renders", "{out}"), render_allowed, f"{source}: render.renders"),
                files=dict(files), environment=env_name, settings=settings, prepare=dict(prepare))
    uses_env = any("{env}" in arg for arg in (*spec.train.argv, *spec.render.argv, *variables.values()))
    if uses_env and bin_folder is None and env_name is None:
        raise InputError(f"{source}: {{env}} is used, but the spec names no environment ([environment] name or bin)")
    if not isinstance(install, str) and env_name is None and bin_folder is None:
        raise InputError(f"{source}: install lines build an environment: name it ([environment] name or bin)")
    return spec


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
    """The method a spec file describes; `settings` (checked against the spec's [settings])
    replace its defaults for every job of this method object."""
    return ExternalMethod(read_spec(path), settings)


def check_settings(spec: Spec, settings) -> dict:
    """The spec's settings with `settings` over its defaults; a name the spec does not
    declare, or a value of another type than its default, is an InputError."""
    if settings is None:
        return dict(spec.settings)
    if not isinstance(settings, dict):
        raise InputError(f"method {spec.name}: settings must be a table, got {settings!r}")
    merged = dict(spec.settings)
    for name, value in settings.items():
        if name not in spec.settings:
            known = ", ".join(sorted(spec.settings)) or "none"
            raise InputError(f"method {spec.name}: unknown setting {name!r} (its spec's settings: {known})")
        default = spec.settings[name]
        if isinstance(default, bool) or isinstance(value, bool):
            ok = isinstance(value, bool) and isinstance(default, bool)
        elif isinstance(default, float):
            ok = isinstance(value, (int, float))
        else:
            ok = isinstance(value, type(default))
        if not ok or (isinstance(value, float) and value != value) or (isinstance(value, str) and "\0" in value):
            raise InputError(f"method {spec.name}: setting {name} must be a {type(default).__name__} like its "
                             f"default {default!r}, got {value!r}")
        merged[name] = float(value) if isinstance(default, float) else value
    return merged


# --- where its environment is ------------------------------------------------------------------


def environment_variable(name: str) -> str:
    """$NERFGAUGE_ENV_<NAME>: where the named environment is, when set."""
    return ENV_VARIABLE_PREFIX + re.sub(r"[^A-Z0-9]", "_", name.upper())


def environments_root() -> Path:
    """$XDG_DATA_HOME/nerfgauge/envs, else ~/.local/share/nerfgauge/envs."""
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return Path(base) / "nerfgauge" / "envs"


def environment_folder(spec: Spec) -> Path | None:
    """The folder of the spec's environment (module docstring); None when it names none."""
    if spec.bin is not None:
        return Path(spec.bin).parent
    if spec.environment is None:
        return None
    chosen = os.environ.get(environment_variable(spec.environment))  # relative: to where we run, not the tool
    return Path(os.path.expanduser(chosen)).absolute() if chosen else environments_root() / spec.environment


def bin_folder(spec: Spec) -> Path | None:
    if spec.bin is not None:
        return Path(spec.bin)
    folder = environment_folder(spec)
    return None if folder is None else folder / "bin"


def _check_installed(spec: Spec) -> None:
    """The spec's environment is there; one we build must be complete (an install cut short
    leaves its record saying "building"). A folder without our record is the user's own."""
    folder = bin_folder(spec)
    if folder is None:
        return
    record = folder.parent / ENVIRONMENT_RECORD
    if folder.is_dir():
        if record.is_file() and not record.is_symlink():
            try:
                complete = read_json(record).get("state") == "complete"
            except InputError:
                complete = False
            if not complete:
                raise MethodFailed(spec.name, f"its environment {folder.parent} is incomplete (an install was cut "
                                              f"short): run `nerfgauge methods install {spec.name}` again")
        return
    if spec.environment is not None:
        raise MethodFailed(spec.name, f"its environment {folder.parent} is not installed: run `nerfgauge methods "
                                      f"install {spec.name}`, or set {environment_variable(spec.environment)} to "
                                      "the folder of one you built")
    raise MethodFailed(spec.name, f"its environment's bin folder {folder} does not exist (see the spec's install lines)")


# --- running it ------------------------------------------------------------------------------


def fill(template: str, values: dict) -> str:
    """The template with its placeholders replaced (every one was checked when read)."""
    return template.format_map(values)


def _context(spec: Spec) -> dict:
    folder = environment_folder(spec)
    return {"env": "" if folder is None else str(folder), "spec_folder": str(spec.folder.resolve())}


def _device_for(command: Command, device: str) -> str:
    """The device whose arguments a job gets. "auto" is this machine's device (cuda when a
    CUDA driver reports a GPU, else cpu) wherever the command's devices table names that
    device: a tool whose own default is CUDA (nerfstudio's) then runs on a machine without
    one. Where the table does not name it, "auto" keeps the table's auto entry (the tool
    decides)."""
    if device == "auto" and command.devices is not None:
        machine = "cuda" if cuda_available() else "cpu"
        if machine in command.devices:
            return machine
    return device


def _check_device(command: Command, device: str, method: str) -> str:
    """The device the job runs on (`_device_for`); InputError when the table does not name it."""
    device = _device_for(command, device)
    if command.devices is not None and device not in command.devices:
        raise InputError(f"method {method} runs on {', '.join(command.devices)}, not on device {device!r}")
    return device


def _argv(command: Command, values: dict, device: str, method: str) -> list:
    """The command's arguments for `device`: its own, then those its devices table gives
    that device; a device the table does not name is refused."""
    device = _check_device(command, device, method)
    extra = () if command.devices is None else command.devices[device]
    return [fill(arg, values) for arg in (*command.argv, *extra)]


def _environment(spec: Spec, values: dict, run: Path) -> dict:
    """The command's environment: ours, its bin folder first on PATH (and our PYTHONPATH and
    PYTHONHOME dropped), its variables, and a temporary folder inside the run (so what the
    tool leaves behind stays with the job)."""
    env = dict(os.environ)
    env["TMPDIR"] = str(make_folder(run / ".tmp"))
    folder = bin_folder(spec)
    if folder is not None:
        for name in DROPPED_VARIABLES:
            env.pop(name, None)
        env["PATH"] = str(folder) + os.pathsep + env.get("PATH", "")
        env["VIRTUAL_ENV"] = str(folder.parent)
    env.update({key: fill(value, values) for key, value in spec.variables.items()})
    return env


def _prepare(spec: Spec, values: dict) -> None:
    """The spec's [prepare] steps, each writing into its folder inside the run."""
    for step, template in spec.prepare.items():
        folder = Path(fill(template, values))
        if step == "torchvision_alexnet":
            from nerfgauge.eval.lpips import write_torchvision_alexnet  # torch

            try:
                write_torchvision_alexnet(folder)
            except InputError as error:
                raise MethodFailed(spec.name, f"prepare.{step}: {error}") from None


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


def run_command(argv: list, *, cwd: Path, env: dict, log: Path, timeout: float | None, method: str,
                limit: str = "twice its budget") -> Finished:
    """Run argv (no shell) in its own process group with stdout and stderr in `log`
    (measure.run_process: its own wall, CPU and peak memory; stopped past `timeout`, which
    `limit` names in the reason); MethodFailed with the reason when it cannot start, is
    stopped or exits non-zero."""
    argv = [_executable(argv[0], env, method), *argv[1:]]
    with open_append(log) as output:
        output.write("$ " + " ".join(argv) + "\n")
        output.flush()
        try:
            finished = run_process(argv, cwd=cwd, env=env, stdout=output, timeout=timeout)
        except OSError as error:
            raise MethodFailed(method, f"cannot start {argv[0]}: {error.strerror or error}") from None
    if finished.stopped:
        raise MethodFailed(method, f"ran past {timeout:g} s ({limit}) and was stopped; log: {log}")
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
    """A method run through its spec's command lines (see the module docstring).
    `settings` (checked against the spec's [settings]) replace the spec's defaults; a job's
    own settings (TrainRequest.settings) go over those."""

    def __init__(self, spec: Spec, settings: dict | None = None):
        self.spec = spec
        self.name, self.summary, self.needs, self.produces = spec.name, spec.summary, spec.needs, spec.produces
        self.accepts_budget = spec.length in ("seconds", "both")
        self.settings = check_settings(spec, settings)

    def describe(self) -> dict:
        folder = environment_folder(self.spec)
        return {**super().describe(), "spec": self.spec.source, "install": self.spec.install_lines(folder),
                "environment": None if folder is None else str(folder), "settings": self.settings}

    def check(self, request: TrainRequest) -> None:
        """The spec's train.length against the request (steps, seconds, both or its own
        schedule), and the request's settings against the spec's [settings]."""
        if self.spec.length == "steps" and request.steps is None:
            instead = ", not a time budget" if request.budget_seconds is not None else ""
            raise InputError(f"method {self.name} takes a step count{instead} (its spec's train.length is steps)")
        if self.spec.length == "seconds" and request.budget_seconds is None:
            raise InputError(f"method {self.name} takes a time budget (its spec's train.length is seconds)")
        if self.spec.length == "own" and (request.steps is not None or request.budget_seconds is not None):
            raise InputError(f"method {self.name} trains its own schedule (its spec's train.length is own): "
                             "give it neither steps nor a time budget")
        check_settings(self.spec, {**self.settings, **request.settings})

    def train_length(self, steps: int | None, budget_seconds: float | None) -> tuple:
        """What a suite or a bench gives this method: neither to a spec whose train.length is
        "own" (the tool's own schedule), only the budget to one of "seconds" (with no budget
        offered, check refuses it in one line), as Method.train_length otherwise."""
        if self.spec.length == "own":
            return None, None
        if self.spec.length == "seconds":
            return None, budget_seconds
        return super().train_length(steps, budget_seconds)

    def job(self, request: TrainRequest) -> tuple[dict, dict]:
        """(the request's placeholders, the job's settings: the method's over the spec's
        defaults, the request's over those)."""
        self.check(request)
        settings = check_settings(self.spec, {**self.settings, **request.settings})
        return {"dataset": str(request.dataset.resolve()), "run": str(request.run.resolve()), "seed": request.seed,
                "steps": "" if request.steps is None else request.steps,
                "budget_seconds": "" if request.budget_seconds is None else f"{request.budget_seconds:g}",
                "threads": request.threads or 2, "device": request.device}, settings

    def placeholders(self, job: dict, settings: dict) -> dict:
        """Every placeholder of a job (settings as str spells them: True/False, as Python and tyro do)."""
        return {**job, **{name: str(value) for name, value in settings.items()}, **_context(self.spec)}

    def command_line(self, which: str, values: dict, device: str) -> list:
        """The `which` ("train" or "render") command run on `device` with these placeholders
        and the method's settings (what `nerfgauge methods` users and tests check)."""
        return _argv(getattr(self.spec, which), {**values, **self.placeholders({}, self.settings)}, device, self.name)

    def train(self, request: TrainRequest) -> TrainResult:
        job, settings = self.job(request)
        recorded = {k: v for k, v in job.items() if k != "run"}
        recipe = recipe_hash({"spec": self.spec.definition(), "settings": settings, **recorded})
        values = self.placeholders(job, settings)
        argv = _argv(self.spec.train, values, request.device, self.name)
        _check_installed(self.spec)
        run = request.run
        _clear_earlier_attempt(run, "run", recipe, request.overwrite)
        with claim_folder(run, "run", recipe):
            env = _environment(self.spec, values, run)
            _prepare(self.spec, values)
            budgeted = request.budget_seconds is not None
            timeout = OVERRUN * request.budget_seconds if budgeted else self.spec.train.timeout_seconds
            finished = run_command(argv, cwd=run, env=env, log=run / "train.log", timeout=timeout, method=self.name,
                                   limit="twice its budget" if budgeted else "its spec's train.timeout_seconds")
            find_files(self.spec, run)  # the files rendering needs are there
            result = TrainResult(seconds=finished.seconds, steps=request.steps, cpu_seconds=finished.cpu_seconds,
                                 peak_memory_bytes=finished.peak_memory_bytes,
                                 extra={"exit_status": finished.status})
            write_json(run / RESULT, {"spec": self.spec.definition(), "request": recorded, "settings": settings,
                                      "train": result.to_json()})
        return result

    def render(self, run, dataset, split, out, *, overwrite=False, progress=False) -> RenderResult:
        run, out = Path(run), Path(out)
        job, settings, train = _recorded(run, self)
        _check_device(self.spec.render, job["device"], self.name)
        _check_installed(self.spec)
        job = {**job, "run": str(run.resolve()), "dataset": str(Path(dataset).resolve())}
        values = {**self.placeholders(job, settings), "split": split, "out": str(out.resolve()),
                  **find_files(self.spec, run)}
        recipe = recipe_hash({"spec": self.spec.definition(), "run": train, "split": split,
                              "dataset": job["dataset"], "settings": settings})
        _clear_earlier_attempt(out, "renders", recipe, overwrite)
        with claim_folder(out, "renders", recipe):
            env = _environment(self.spec, values, run)
            _prepare(self.spec, values)
            finished = run_command(_argv(self.spec.render, values, job["device"], self.name), cwd=run, env=env,
                                   log=run / f"render-{split}.log", timeout=self.spec.render.timeout_seconds,
                                   method=self.name, limit="its spec's render.timeout_seconds")
        renders = Path(fill(self.spec.renders, values))
        frames = _count_images(renders)
        if frames == 0:
            raise MethodFailed(self.name, f"its render command wrote no images under {renders}")
        return RenderResult(out=renders, frames=frames, seconds=finished.seconds, pred_format=self.spec.layout)


def _recorded(run: Path, method: ExternalMethod) -> tuple[dict, dict, dict]:
    """RUN/method.json, re-checked as on entry: a state file is data, so its request is
    rebuilt through TrainRequest's checks, its settings through the spec's, and the spec it
    names must be this one. Returns (the job's placeholders, its settings, what training cost)."""
    path = run / RESULT
    if not path.is_file():
        raise InputError(f"{run} holds no trained run of method {method.name} (no {RESULT}): train it first")
    record = read_json(path, finite=True)
    request, train, settings = record.get("request"), record.get("train"), record.get("settings", {})
    if not isinstance(request, dict) or not isinstance(train, dict) or record.get("spec") != method.spec.definition():
        raise InputError(f"{path} is not a record of method {method.name} as its spec is now: train it again")
    try:
        checked = TrainRequest(dataset=run, run=run, seed=request["seed"],
                               steps=request["steps"] if request["steps"] != "" else None,
                               budget_seconds=float(request["budget_seconds"]) if request["budget_seconds"] != "" else None,
                               threads=request["threads"], device=request["device"], settings=settings)
        job, settings = ExternalMethod(method.spec).job(checked)  # the spec's defaults under the recorded settings
    except (KeyError, TypeError, ValueError) as error:
        raise InputError(f"{path}: a malformed request ({error})") from None
    except InputError as error:
        raise InputError(f"{path}: {error}") from None
    return job, settings, train


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
