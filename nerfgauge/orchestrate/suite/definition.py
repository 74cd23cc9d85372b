"""Benchmark suites: versioned sets of datasets, and results tied to them.

A suite is a TOML file (suites/*.toml, installed as the package nerfgauge.suites; or any
path ending in .toml):

    name = "smoke"                 # required
    version = 1                    # required, a positive integer: bump it on any change
    description = "..."            # optional
    [dataset]                      # required: nerfgauge generate settings (GenerateConfig
    width = 16 ...                 #   fields but scene and seed, the train-view degradations
                                   #   too); width, height, views, test_views and spp are required
    [train]                        # required: the length every learned method's job is
    steps = 80                     #   offered: steps (required: reproducible), budget_seconds,
                                   #   threads (orchestrate.suite.methods)
    [scoring]                      # required: how renders are scored: split, background,
    split = "test" ...             #   depth_kind; optional protocol (eval.protocols: nerfgauge,
                                   #   nerfbaselines, ns-eval; default ours) and geometry
                                   #   {resolution, samples} (our NeRF's mesh scored)
    [[methods]]                    # what runs (orchestrate.suite.methods): a built-in method,
    method = "compact"             #   a spec file, module:Class, with settings and length
    settings = { ... }             #   (and points: the initial points its datasets hold,
                                   #   orchestrate.suite.points); without [[methods]], [train]'s
                                   #   other keys are our compact NeRF's settings (compact-nerf)
    [[scenes]]                     # at least one: scene (a registered recipe) and seed are
    scene = "primitives"           #   required; id (default: the scene) names its folder;
    seed = 0                       #   any [dataset] key overrides the default for it
    [[scenes]]                     # or ground truth nerfgauge did not write: folder (relative
    id = "lego"                    #   to the .toml's folder) is a NeRF-synthetic, nerfstudio
    folder = "nerf_synthetic/lego" #   or COLMAP text-model folder (core.foreign_dataset); id
                                   #   defaults to its name; no other key

A missing or unknown field, a wrong type, an unknown scene, or two entries with one id is an
InputError naming the file and the field. The suite's identity is its version and the
sha256 of its canonical JSON (`Suite.sha256`: its name, version, description, scoring and
datasets; not the methods run on it): editing a suite without bumping its version still
changes the hash, and results are refused either way.

The scoring table was called [protocol] (and listed the baselines) before a suite could
choose the scoring protocol: such a file is still read, with a one-line note
(`Suite.notes`), its baselines run as methods; [protocol] and [scoring] together are refused.

A suite folder (`nerfgauge suite generate SUITE --out DIR`, a nerfgauge "suite" folder):
    DIR/suite.json                  the suite as parsed: name, version, sha256, definition
    DIR/datasets/<id>/              one nerfgauge dataset per scene entry
    DIR/suite-manifest.json         written last, when every dataset is complete: every
                                    dataset's manifest.json sha256 and every file's sha256
    DIR/results/<method>/<id>/metrics.json  `suite evaluate` (eval.evaluate's document)
    DIR/results/<method>/<id>/seed-<s>/metrics.json, DIR/results/<method>/<id>/aggregate.json
                                    `suite run --seeds`: one per training seed, and their
                                    aggregate (eval.uncertainty.aggregate_runs)
    DIR/results/<method>/result.json        written last: suite version and sha256, each
                                    dataset's manifest sha256, training time, model size
Generation is resumable: a dataset whose manifest verifies and whose recipe matches is
skipped; an interrupted one is resumed by the generator.

A folder entry is not rendered: `suite generate` reads the folder as `evaluate` does
(core.dataset.Dataset: validated, every file read hashed), reads every frame's image, and
records its identity in the suite manifest in place of manifest_sha256: format, split rule,
the sha256 of every file read (`files`) and `ground_truth_sha256`, the sha256 of that
{file: sha256} table's canonical JSON. `suite evaluate`, `suite report` and read_results
hash the folder again and refuse it (one line naming both hashes) when it changed; each
metrics.json's ground_truth.files must agree with the recorded files. The suite's
definition holds the folder as written (so its sha256 does not depend on where the suite
folder lives); suite.json's "folders" holds where it was found. Methods that need what such
a folder lacks (our NeRF's runs are bound to a manifest; the nearest baseline needs scene
bounds; light-field baselines a camera grid) are skipped there with the reason (result.json
"skipped", the leaderboard's n/a cells); metrics it cannot give are null ("unavailable").

State files are data, never instructions (suite.json, suite-manifest.json, result.json,
jobs/<key>.json; anyone who can write the folder can rewrite them, hashes included):
- every name that becomes a path (the suite's name, dataset ids, methods) passes
  `folder_name` where it enters and again wherever a file gives it back;
- suite.json's definition is parsed by the suite file's own checks (`suite_from_definition`),
  and its sha256 is recomputed from it and compared with the hashes other files hold (the
  folder marker `suite generate` wrote from the suite file, the suite manifest, each
  result.json), never with the one suite.json states about itself; each recipe entry is
  compared with the config.json of the dataset it names (hashed in that dataset's
  manifest, whose own hash the suite manifest holds);
- the suite manifest, result.json and job records are checked field by field
  (`check_suite_manifest`, `check_result`, `job_result`), and every path they hold must be
  the one their writer makes (results/<method>/<id>/...), so nothing outside is read;
  derived figures (aggregates over seeds) are recomputed, not read back.
A malformed or inconsistent file is one line, exit 2.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.resources
import re
import time
import tomllib
import unicodedata
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from nerfgauge.core import arguments, bounded, dataset, owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import json_bytes, read_json, sha256_file, write_json
from nerfgauge.core.folders import MARKER, claim_folder, folder_lock, read_marker
from nerfgauge.eval.check import finite_number, shown
from nerfgauge.eval.geometry import SUMMARY_NAMES
from nerfgauge.eval.evaluate import BACKGROUNDS, evaluate
from nerfgauge.eval.metrics import METRIC_NAMES
from nerfgauge.eval.uncertainty import aggregate_runs, mean_of
from nerfgauge.eval.predictions import DEPTH_SUFFIXES, FORMATS as PRED_FORMATS
from nerfgauge.generate.distributed import check_reachable
from nerfgauge.orchestrate.suite import methods as suite_methods
from nerfgauge.generate.pipeline import CONFIG as CONFIG_FILE, GenerateConfig, generate
from nerfgauge.scenes.registry import RECIPES

SUITE_FILE = "suite.json"
SUITE_MANIFEST = "suite-manifest.json"
RESULT_FILE = "result.json"
AGGREGATE_FILE = "aggregate.json"  # results/<method>/<id>/aggregate.json: a method's runs over seeds
SCHEMA = 1
REQUIRED = {"dataset": ("width", "height", "views", "test_views", "spp"), "train": ("steps",),
            "scoring": ("split", "background", "depth_kind")}
SCORING_KEYS = {"split": str, "background": str, "depth_kind": str, "protocol": str, "geometry": dict}
OLD_SCORING = "protocol"  # the scoring table's name before a suite could choose the scoring protocol
GEOMETRY_KEYS = ("resolution", "samples")
GENERATE_FIELDS = frozenset(f.name for f in dataclasses.fields(GenerateConfig)) - {"scene", "seed"}
NAME_BYTES = 255  # NAME_MAX: the longest name of one folder or file
SHA256 = re.compile(r"[0-9a-f]{64}")


@dataclass(frozen=True)
class SceneEntry:
    id: str
    scene: Optional[str]  # None for a folder entry
    seed: int
    dataset: dict  # GenerateConfig fields (the suite's [dataset] with this entry's overrides)
    folder: Optional[str] = None  # a foreign ground-truth folder, as written in the suite file
    path: Optional[str] = field(default=None, compare=False)  # where that folder was found

    @property
    def foreign(self) -> bool:
        return self.folder is not None

    def definition(self) -> dict:
        if self.foreign:
            return {"id": self.id, "folder": self.folder}
        return {"id": self.id, "scene": self.scene, "seed": self.seed, "dataset": self.dataset}


@dataclass(frozen=True)
class Suite:
    name: str
    version: int
    description: str
    scoring: dict  # split, background, depth_kind, protocol (eval.protocols), geometry
    scenes: tuple  # SceneEntry
    source: str  # where it was read from (named in errors)
    train: dict = field(default_factory=dict, compare=False)  # the jobs' length: steps, budget_seconds, threads
    methods: tuple = field(default=(), compare=False)  # orchestrate.suite.methods.MethodEntry: what runs
    notes: tuple = field(default=(), compare=False)  # one line each, for the user (an older file's names)

    def definition(self) -> dict:
        """Everything that makes results comparable (not where the file lives, not the
        methods run on it)."""
        return {"name": self.name, "version": self.version, "description": self.description,
                "scoring": self.scoring, "scenes": [entry.definition() for entry in self.scenes]}

    @property
    def sha256(self) -> str:
        return hashlib.sha256(json_bytes(self.definition())).hexdigest()

    def generate_config(self, entry: SceneEntry):
        return GenerateConfig(scene=entry.scene, seed=entry.seed, **entry.dataset)

    def identity(self) -> dict:
        return {"suite": self.name, "version": self.version, "suite_sha256": self.sha256}


# --- reading suite files ----------------------------------------------------------------


def builtin_suites() -> dict:
    """{name: path-like} of the suites shipped with nerfgauge."""
    folder = importlib.resources.files("nerfgauge.orchestrate.suite.builtin")
    return {item.name[:-5]: item for item in sorted(folder.iterdir(), key=lambda i: i.name) if item.name.endswith(".toml")}


def load_suite(spec) -> Suite:
    """A suite by built-in name ("smoke") or from a .toml path; InputError (one line) if bad."""
    spec = str(spec)
    if spec.endswith(".toml"):
        path = Path(spec)
        if not path.is_file():
            raise InputError(f"suite file not found: {path}")
        text, source = bounded.read_bytes(path, bounded.MAX_TOML_BYTES, "suite file"), str(path)
        base = path.parent
    else:
        known = builtin_suites()
        if spec not in known:
            raise InputError(f"unknown suite {spec!r}; known: {', '.join(known)} (or give a path to a .toml file)")
        text, source = known[spec].read_bytes(), f"suites/{spec}.toml"
        base = Path(str(known[spec])).parent
    try:
        data = bounded.loads_toml(text, source)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"{source} is not valid TOML: {error}") from None
    return parse_suite(data, source, base)


def _table(data: dict, key: str, source: str) -> dict:
    if key not in data:
        raise InputError(f"{source}: missing field [{key}]")
    if not isinstance(data[key], dict):
        raise InputError(f"{source}: [{key}] must be a table, got {type(data[key]).__name__}")
    for field in REQUIRED.get(key, ()):
        if field not in data[key]:
            raise InputError(f"{source}: missing field {key}.{field}")
    return dict(data[key])


def _check_fields(values: dict, allowed: set, where: str) -> None:
    unknown = sorted(set(values) - allowed)
    if unknown:
        raise InputError(f"{where}: unknown field {unknown[0]!r}; known: {', '.join(sorted(allowed))}")


def folder_name(value, what: str) -> str:
    """`value` when it can name one folder or file of a suite folder (a suite's name, a
    dataset id, a method): a non-empty string of at most NAME_BYTES bytes in UTF-8, without
    '/', NUL or another control character, not starting with '.' (so not '.' or '..').
    InputError naming `what` otherwise. The one check of such a name, where it enters (the
    suite file, --method) and wherever a state file gives it back (suite.json,
    suite-manifest.json, result.json, job records), so a name read back is exactly a name
    that could have entered."""
    if not isinstance(value, str) or not value:
        raise InputError(f"{what} must be a folder name (a non-empty string), got {shown(value)}")
    try:
        size = len(value.encode("utf-8"))
    except UnicodeEncodeError:
        raise InputError(f"{what} must be a folder name in UTF-8, got {shown(value)}") from None
    if any(char == "/" or unicodedata.category(char) == "Cc" for char in value) or value.startswith("."):
        raise InputError(f"{what} must be a folder name (no '/', NUL or control characters, not starting with '.'), "
                         f"got {shown(value)}")
    if size > NAME_BYTES:
        raise InputError(f"{what} must be a folder name of at most {NAME_BYTES} bytes, got {size}")
    return value


def _seed(value, where: str) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise InputError(f"{where}: seed must be a non-negative integer, got {shown(value)}")
    return value


def parse_suite(data: dict, source: str, base=None) -> Suite:
    """A suite file's parsed TOML, every field checked, its methods resolved and their
    requests checked (orchestrate.suite.methods). base: the folder relative `folder`
    entries and spec files are resolved against (the .toml's)."""
    _check_fields(data, {"name", "version", "description", "dataset", "train", "scoring", OLD_SCORING, "methods",
                         "scenes"}, source)
    notes = ()
    if OLD_SCORING in data:
        if "scoring" in data:
            raise InputError(f"{source}: [{OLD_SCORING}] is the older name of [scoring]; give one of them")
        if "methods" in data and "baselines" in (data[OLD_SCORING] if isinstance(data[OLD_SCORING], dict) else {}):
            raise InputError(f"{source}: list the baselines as [[methods]] entries, not {OLD_SCORING}.baselines")
        old = data
        data = {**{k: v for k, v in data.items() if k != OLD_SCORING}, "scoring": data[OLD_SCORING]}
        notes = (f"note: {source}: [{OLD_SCORING}] is now called [scoring] (and its baselines are [[methods]]); "
                 "the file is read as before",)
    scoring, baselines = data.get("scoring"), []
    if notes and isinstance(scoring, dict):  # the older table's baselines: methods now
        scoring = {key: value for key, value in scoring.items() if key != "baselines"}
        baselines, data = old[OLD_SCORING].get("baselines", []), {**data, "scoring": scoring}
    elif isinstance(scoring, dict) and "baselines" in scoring:
        raise InputError(f"{source}: scoring.baselines: list each baseline as a [[methods]] entry "
                         '(method = "nearest")')
    dataset_defaults = _table(data, "dataset", source)
    _check_fields(dataset_defaults, GENERATE_FIELDS, f"{source} [dataset]")
    suite = _suite(data, source, dataset_defaults, lambda raw, where: _folder_entry(raw, where, base))
    train = _table(data, "train", source)
    if "methods" in data:
        train = suite_methods.check_train(train, source)
        methods = suite_methods.parse_methods(data["methods"], train, source, base)
    else:
        train, methods = suite_methods.shorthand_methods(train, baselines, source)
    return dataclasses.replace(suite, train=train, methods=methods, notes=notes)


def suite_from_definition(recorded: dict, source: str) -> Suite:
    """The suite a suite.json records, checked exactly as `parse_suite` checks a suite file
    (the same functions, field by field): its definition holds each entry's dataset
    settings in full (no [dataset] defaults), a folder entry's folder as written, and
    "folders" where each was found (checked again: a folder, not a nerfgauge dataset)."""
    definition = recorded.get("definition")
    if not isinstance(definition, dict):
        raise InputError(f"{source}: no suite definition (an object), got {shown(definition)}")
    where = f"{source} definition"
    if OLD_SCORING in definition:
        raise InputError(f"{source} records a suite in the format before [scoring]: make the folder again with "
                         "nerfgauge suite generate SUITE --out DIR --overwrite")
    _check_fields(definition, {"name", "version", "description", "scoring", "scenes"}, where)
    folders = recorded.get("folders", {})
    if not isinstance(folders, dict):
        raise InputError(f"{source}: folders must be an object of id: path, got {shown(folders)}")

    def folder_entry(raw: dict, at: str) -> SceneEntry:
        _check_fields(raw, {"id", "folder"}, f"{at} (a folder entry)")
        entry_id = folder_name(raw.get("id"), f"{at}: id")
        path = folders.get(entry_id)
        if not isinstance(path, str) or "\0" in path or not Path(path).is_absolute():
            raise InputError(f"{source}: folders.{entry_id} must be the absolute path of the folder entry, "
                             f"got {shown(path)}")
        return _ground_truth_folder(entry_id, raw.get("folder"), Path(path), at)

    return _suite({**definition, "dataset": {}}, where, {}, folder_entry, recorded=True)


def _suite(data: dict, source: str, dataset_defaults: dict, folder_entry, recorded: bool = False) -> Suite:
    """The fields parse_suite and suite_from_definition share: name, version, description,
    [scoring] and the entries (a recorded definition's entries carry every dataset
    setting; folder_entry(raw, where) reads a folder entry)."""
    for field in ("name", "version"):
        if field not in data:
            raise InputError(f"{source}: missing field {field}")
    name, version = data["name"], data["version"]
    if not isinstance(name, str) or not name.strip():
        raise InputError(f"{source}: name must be a non-empty string, got {shown(name)}")
    folder_name(name, f"{source}: name")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise InputError(f"{source}: version must be a positive integer, got {shown(version)}")
    description = data.get("description", "")
    if not isinstance(description, str):
        raise InputError(f"{source}: description must be a string, got {shown(description)}")
    scoring = check_scoring(_table(data, "scoring", source), source)
    scenes = data.get("scenes")
    if scenes is None:
        raise InputError(f"{source}: missing field [[scenes]]")
    if not isinstance(scenes, list) or not scenes or not all(isinstance(s, dict) for s in scenes):
        raise InputError(f"{source}: [[scenes]] must be a non-empty list of tables")
    entries, ids = [], set()
    for k, raw in enumerate(scenes):
        where = f"{source} scenes[{k}]"
        if "folder" in raw:
            entry = folder_entry(raw, where)
        elif recorded:
            _check_fields(raw, {"id", "scene", "seed", "dataset"}, where)
            settings = raw.get("dataset")
            if not isinstance(settings, dict) or "id" not in raw:
                raise InputError(f"{where}: a recorded entry needs its id and its dataset settings (an object)")
            _check_fields(settings, GENERATE_FIELDS, f"{where} dataset")
            entry = _recipe_entry({**settings, **{key: raw[key] for key in ("id", "scene", "seed") if key in raw}},
                                  dataset_defaults, where)
        else:
            entry = _recipe_entry(raw, dataset_defaults, where)
        if entry.id in ids:
            raise InputError(f"{where}: id {entry.id!r} is used twice; give each entry its own id")
        ids.add(entry.id)
        entries.append(entry)
    return Suite(name, version, description, scoring, tuple(entries), source)


def check_scoring(scoring: dict, source: str) -> dict:
    """[scoring]: split, background, depth_kind (required), protocol (eval.protocols;
    default ours), geometry {resolution, samples}. A protocol that composites onto a fixed
    background (ns-eval: black) needs that background: scores are compared like with like."""
    from nerfgauge.eval import protocols  # the scoring protocols

    _check_fields(scoring, set(SCORING_KEYS), f"{source} [scoring]")
    for key, kind in SCORING_KEYS.items():
        if key in scoring and not isinstance(scoring[key], kind):
            raise InputError(f"{source}: scoring.{key} must be a {kind.__name__}, got {shown(scoring[key])}")
    if scoring["background"] not in BACKGROUNDS or scoring["depth_kind"] not in DEPTH_SUFFIXES:
        raise InputError(f"{source}: scoring.background must be one of {', '.join(BACKGROUNDS)} and "
                         f"scoring.depth_kind one of {', '.join(DEPTH_SUFFIXES)}")
    if scoring["split"] not in dataset.SPLITS:
        raise InputError(f"{source}: scoring.split must be one of {', '.join(dataset.SPLITS)}, "
                         f"got {shown(scoring['split'])}")
    scoring.setdefault("protocol", protocols.DEFAULT)
    if scoring["protocol"] not in protocols.PROTOCOLS:
        raise InputError(f"{source}: scoring.protocol must be one of {', '.join(protocols.PROTOCOLS)}, "
                         f"got {shown(scoring['protocol'])}")
    fixed = protocols.PROTOCOLS[scoring["protocol"]].background
    if fixed is not None and tuple(BACKGROUNDS[scoring["background"]]) != tuple(fixed):
        wanted = next(name for name, value in BACKGROUNDS.items() if tuple(value) == tuple(fixed))
        raise InputError(f"{source}: scoring.protocol {scoring['protocol']} composites onto {wanted}: "
                         f"set scoring.background = \"{wanted}\"")
    if "geometry" in scoring:
        geometry = scoring["geometry"]
        _check_fields(geometry, set(GEOMETRY_KEYS), f"{source} scoring.geometry")
        for key in GEOMETRY_KEYS:
            if not isinstance(geometry.get(key), int) or isinstance(geometry.get(key), bool) or geometry[key] < 2:
                raise InputError(f"{source}: scoring.geometry.{key} must be an integer >= 2, "
                                 f"got {shown(geometry.get(key))}")
    return scoring


def _recipe_entry(raw: dict, dataset_defaults: dict, where: str) -> SceneEntry:
    """A [[scenes]] entry rendered from a recipe: scene, seed, id (default: the scene) and
    any [dataset] key overriding the defaults; GenerateConfig validates it."""
    _check_fields(raw, GENERATE_FIELDS | {"id", "scene", "seed"}, where)
    for field in ("scene", "seed"):
        if field not in raw:
            raise InputError(f"{where}: missing field {field}")
    if not isinstance(raw["scene"], str) or raw["scene"] not in RECIPES:
        raise InputError(f"{where}: unknown scene {shown(raw['scene'])}; known: {', '.join(RECIPES)}")
    seed = _seed(raw["seed"], where)
    entry_id = folder_name(raw.get("id", raw["scene"]), f"{where}: id")
    settings = {**dataset_defaults, **{key: value for key, value in raw.items() if key in GENERATE_FIELDS}}
    missing = [field for field in REQUIRED["dataset"] if field not in settings]
    if missing:
        raise InputError(f"{where}: missing field dataset.{missing[0]}")
    if isinstance(settings.get("elevation"), list):
        settings["elevation"] = tuple(settings["elevation"])
    entry = SceneEntry(entry_id, raw["scene"], seed, settings)
    try:
        config = GenerateConfig(scene=entry.scene, seed=entry.seed, **settings)
        config.validate()
    except (TypeError, ValueError) as error:  # InputError is a ValueError
        raise InputError(f"{where}: {str(error).splitlines()[0] if str(error) else type(error).__name__}") from None
    return entry


def _folder_entry(raw: dict, where: str, base) -> SceneEntry:
    """A [[scenes]] entry naming a ground-truth folder nerfgauge did not write."""
    _check_fields(raw, {"id", "folder"}, f"{where} (a folder entry)")
    folder = raw["folder"]
    if not isinstance(folder, str) or not folder.strip() or "\0" in folder:
        raise InputError(f"{where}: folder must be a path, got {shown(folder)}")
    path = Path(folder).expanduser()
    if not path.is_absolute():
        path = Path(base if base is not None else ".") / path
    path = path.resolve()
    return _ground_truth_folder(raw.get("id", path.name), folder, path, where)


def _ground_truth_folder(entry_id, folder, path: Path, where: str) -> SceneEntry:
    """A folder entry's checks, on first entry and read back from suite.json: the id a
    folder name, the folder (as written) a string, the path a folder that is not a
    nerfgauge dataset (those are listed by recipe)."""
    if not isinstance(folder, str) or not folder.strip() or "\0" in folder:
        raise InputError(f"{where}: folder must be a path, got {shown(folder)}")
    entry_id = folder_name(entry_id, f"{where}: id")
    if not path.is_dir():
        raise InputError(f"{where}: folder {folder!r} not found (looked for {path})")
    if (path / dataset.MANIFEST).is_file() or (path / dataset.MARKER).exists():
        raise InputError(f"{where}: folder {path} is a nerfgauge dataset; folder entries are for ground truth "
                         f"nerfgauge did not write (list our scenes by recipe: scene and seed)")
    return SceneEntry(entry_id, None, 0, {}, folder=folder, path=str(path))


# --- the suite folder --------------------------------------------------------------------


def claim_suite_folder(suite: Suite, out, *, overwrite: bool = False):
    """claim_folder(out, "suite", sha256), refusing first with one line when `out` holds
    another suite or another version of this one."""
    out = Path(out)
    if (out / SUITE_FILE).is_file() and not overwrite:
        check_same_suite(suite, read_json(out / SUITE_FILE), f"{out / SUITE_FILE}",
                         remedy="choose another --out, or pass --overwrite to replace it")
    return claim_folder(out, "suite", suite.sha256, overwrite=overwrite)


def check_same_suite(suite: Suite, identity: dict, where: str,
                     remedy: str = "results against another suite version are refused") -> None:
    """Refuse (InputError) results or folders made for another suite, version or definition."""
    name, version = identity.get("suite", identity.get("name")), identity.get("version")
    sha = identity.get("suite_sha256", identity.get("sha256"))
    if name != suite.name:
        raise InputError(f"{where} is for suite {name!r}, not {suite.name!r}; {remedy}")
    if version != suite.version:
        raise InputError(f"{where} was made with suite {name} version {version}, not version {suite.version}; "
                         f"{remedy}")
    recorded = identity.get("definition")
    if sha != suite.sha256 and isinstance(recorded, dict) and OLD_SCORING in recorded:
        raise InputError(f"{where} was made by an older nerfgauge, whose suites' hashes covered [train] and "
                         f"[{OLD_SCORING}]; {remedy}")
    if sha != suite.sha256:
        raise InputError(f"{where} was made with another definition of suite {name} version {version} "
                         f"(sha256 {str(sha)[:12]}..., this one {suite.sha256[:12]}...); bump the version when editing a suite")


def dataset_dir(out, entry: SceneEntry) -> Path:
    """Where the entry's ground truth is: out/datasets/<id>/, or a folder entry's folder."""
    if entry.foreign:
        return Path(entry.path)
    return Path(out) / "datasets" / entry.id


def identity_key(record: dict) -> str:
    """The suite-manifest key that identifies an entry's ground truth: manifest_sha256 for
    our datasets, ground_truth_sha256 for folders nerfgauge did not write."""
    return "ground_truth_sha256" if "ground_truth_sha256" in record else "manifest_sha256"


def files_sha256(files: dict) -> str:
    """sha256 of a {relative path: sha256} table's canonical JSON."""
    return hashlib.sha256(json_bytes(dict(sorted(files.items())))).hexdigest()


def folder_identity(entry: SceneEntry) -> dict:
    """A folder entry's record: read as `evaluate` reads it (validated), every frame's image
    read too, so `files` holds the sha256 of every file any evaluation of it can read."""
    try:
        ds = dataset.Dataset(entry.path)
        if ds.foreign is None:
            raise InputError(f"{entry.path} is a nerfgauge dataset, not a foreign ground-truth folder")
        for split in ds.splits:
            for index in range(len(ds.frames(split))):
                ds.image(split, index)  # decoded like evaluate decodes it: header and size checked
    except InputError as error:
        raise InputError(f"suite entry {entry.id}: {error}") from None
    record = ds.ground_truth_record()
    return {"path": entry.path, "folder": entry.folder, "format": record["format"],
            "split_rule": record["split_rule"], "unavailable": record["unavailable"],
            "ground_truth_sha256": files_sha256(record["files"]), "files": record["files"]}


def check_folder(entry: SceneEntry, record: dict, where: str) -> None:
    """Refuse (one line naming both hashes) a folder entry whose files changed since `where`."""
    now = folder_identity(entry)
    if now["ground_truth_sha256"] != record.get("ground_truth_sha256"):
        changed = sorted(rel for rel in set(now["files"]) | set(record.get("files", {}))
                         if now["files"].get(rel) != record.get("files", {}).get(rel))
        raise InputError(f"ground-truth folder {entry.path} ({entry.id}) changed since suite generate: its files hash "
                         f"to {now['ground_truth_sha256']}, {where} recorded {record.get('ground_truth_sha256')} "
                         f"({len(changed)} files differ, e.g. {', '.join(changed[:2])}); "
                         f"run nerfgauge suite generate --overwrite to record it again")


def generate_suite(suite: Suite, out, *, overwrite: bool = False, progress: bool = False, log=print,
                   scheduler: str | None = None) -> dict:
    """Every dataset of the suite into out/datasets/<id>/, then suite-manifest.json. Returns it.
    scheduler: tcp://HOST:PORT or local:N renders every dataset's views as tasks on a dask
    cluster (generate.distributed); None renders here."""
    out = Path(out)
    if scheduler is not None:
        check_reachable(scheduler)  # a malformed or unreachable address is one line before anything is written
    for entry in suite.scenes:
        if not entry.foreign:
            suite.generate_config(entry).validate()
    foreign = {entry.id: folder_identity(entry) for entry in suite.scenes if entry.foreign}  # refused before writing
    with claim_suite_folder(suite, out, overwrite=overwrite):
        folders = {"folders": {entry.id: entry.path for entry in suite.scenes if entry.foreign}} if foreign else {}
        write_json(out / SUITE_FILE, {**suite.identity(), "schema": SCHEMA, "definition": suite.definition(),
                                      **folders})
        manifest_path = out / SUITE_MANIFEST
        previous = _previous_manifest(suite, manifest_path, overwrite)
        for entry_id, record in foreign.items():  # a folder changed under recorded results: say so
            before = previous["datasets"].get(entry_id, {}).get("ground_truth_sha256")
            if before is not None and before != record["ground_truth_sha256"] and not overwrite:
                raise InputError(f"ground-truth folder {record['path']} ({entry_id}) changed since suite generate: its "
                                 f"files hash to {record['ground_truth_sha256']}, {manifest_path} recorded {before}; "
                                 "pass --overwrite to record it again (results scored against it are then refused)")
        if manifest_path.is_file():
            owned.remove_file(manifest_path)  # rewritten below once every dataset is complete
        for index, entry in enumerate(suite.scenes, 1):
            folder = dataset_dir(out, entry)
            if entry.foreign:
                log(f"[{index}/{len(suite.scenes)}] {entry.id}: {foreign[entry.id]['format']} folder {folder}, "
                    f"{len(foreign[entry.id]['files'])} files hashed (not rendered)")
                continue
            if _unchanged(folder, previous["datasets"].get(entry.id)):
                log(f"[{index}/{len(suite.scenes)}] {entry.id}: complete, skipped")
                continue
            log(f"[{index}/{len(suite.scenes)}] {entry.id}: generate {entry.scene} (seed {entry.seed})")
            start = time.perf_counter()
            generate(suite.generate_config(entry), folder, overwrite=overwrite, progress=progress, scheduler=scheduler)
            log(f"    {entry.id}: generated in {time.perf_counter() - start:.1f} s")
        document = {**suite.identity(), "schema": SCHEMA, "datasets": {
            entry.id: foreign[entry.id] if entry.foreign else dataset_record(out, entry) for entry in suite.scenes}}
        write_json(manifest_path, document)
    return document


def _previous_manifest(suite: Suite, path: Path, overwrite: bool) -> dict:
    """The suite manifest a resumed `suite generate` finds (what it may skip), checked as
    read_suite_folder checks it; none yet: no datasets. A malformed one is refused (one line)
    unless overwrite, which records every dataset again."""
    if not path.is_file():
        return {"datasets": {}}
    try:
        return check_suite_manifest(read_json(path, finite=True), suite, str(path))
    except InputError as error:
        if overwrite:
            return {"datasets": {}}
        raise InputError(f"{error}; pass --overwrite to record every dataset again") from None


def _unchanged(folder: Path, recorded) -> bool:
    """The dataset is complete and its manifest is the one recorded, every file verifying."""
    manifest = folder / dataset.MANIFEST
    if not recorded or not manifest.is_file() or sha256_file(manifest) != recorded.get("manifest_sha256"):
        return False
    return not dataset.verify_manifest(folder)


def dataset_record(out: Path, entry: SceneEntry) -> dict:
    folder = dataset_dir(out, entry)
    files = {rel: item.sha256 for rel, item in dataset.read_manifest(folder).items()}
    return {"path": folder.relative_to(out).as_posix(), "scene": entry.scene, "seed": entry.seed,
            "manifest_sha256": sha256_file(folder / dataset.MANIFEST), "files": files}


def read_suite_folder(suite: Suite, out) -> dict:
    """The suite manifest of a complete suite folder made from `suite`; InputError otherwise.
    Nothing a file says about itself is taken on its word: the suite's sha256 (recomputed
    from `suite`) must be the one the folder's marker and the suite manifest record (and
    suite.json, which also holds the definition it hashes); the manifest is checked field by
    field (`check_suite_manifest`); each dataset's manifest.json must hash to the recorded
    sha256 and its config.json (checked against that manifest) must hold the generate
    settings of the suite's entry; each folder entry's files are hashed again."""
    out = Path(out)
    if not (out / SUITE_FILE).is_file():
        raise InputError(f"{out} is not a suite folder (no {SUITE_FILE}); make it with nerfgauge suite generate")
    check_same_suite(suite, read_json(out / SUITE_FILE), str(out / SUITE_FILE))
    marker = read_marker(out)
    if marker is None or marker.get("kind") != "suite" or marker.get("recipe") != suite.sha256:
        raise InputError(f"{out / MARKER} records {'no suite' if marker is None or marker.get('kind') != 'suite' else 'suite sha256 ' + str(marker.get('recipe'))[:12] + '...'}, "
                         f"not this suite's ({suite.sha256[:12]}...): the folder was made from another definition; "
                         "regenerate with nerfgauge suite generate --overwrite")
    if not (out / SUITE_MANIFEST).is_file():
        raise InputError(f"suite folder {out} is incomplete (no {SUITE_MANIFEST}); finish it with nerfgauge suite generate")
    manifest = check_suite_manifest(read_json(out / SUITE_MANIFEST, finite=True), suite, str(out / SUITE_MANIFEST))
    for entry in suite.scenes:
        record = manifest["datasets"][entry.id]
        if entry.foreign:
            check_folder(entry, record, str(out / SUITE_MANIFEST))
            continue
        path = dataset_dir(out, entry) / dataset.MANIFEST
        if not path.is_file() or sha256_file(path) != record["manifest_sha256"]:
            raise InputError(f"dataset {dataset_dir(out, entry)}: its manifest hash differs from the one in "
                             f"{out / SUITE_MANIFEST}; regenerate with nerfgauge suite generate --overwrite")
        check_dataset_recipe(suite, out, entry)
    return manifest


def check_suite_manifest(document: dict, suite: Suite, where: str) -> dict:
    """`document` (a suite-manifest.json) when it is this suite's and every record is what
    generate_suite writes: one per entry and no other, a recipe's {path
    "datasets/<id>", scene, seed, manifest_sha256, files}, a folder's {path, folder,
    format, split_rule, unavailable, ground_truth_sha256, files}, every sha256 64 hex
    digits. InputError (one line naming the field) otherwise."""
    check_same_suite(suite, document, where)
    datasets = document.get("datasets")
    if not isinstance(datasets, dict):
        raise InputError(f"{where}: datasets must be an object of id: record, got {shown(datasets)}")
    ids = {entry.id for entry in suite.scenes}
    extra = sorted(set(datasets) - ids)
    if extra:
        raise InputError(f"{where} lists a dataset the suite does not have: {shown(extra[0])}")
    for entry in suite.scenes:
        record = datasets.get(entry.id)
        at = f"{where}: datasets.{entry.id}"
        if record is None:
            raise InputError(f"{where} lists no dataset {entry.id!r}")
        if not isinstance(record, dict):
            raise InputError(f"{at} must be an object, got {shown(record)}")
        if entry.foreign != ("ground_truth_sha256" in record):
            raise InputError(f"{where}: dataset {entry.id!r} was recorded as "
                             f"{'a folder' if 'ground_truth_sha256' in record else 'a recipe'}; regenerate with "
                             "nerfgauge suite generate --overwrite")
        if entry.foreign:
            _check_keys(record, {"path", "folder", "format", "split_rule", "unavailable", "ground_truth_sha256",
                                 "files"}, at)
            _sha256(record["ground_truth_sha256"], f"{at}.ground_truth_sha256")
            if not isinstance(record["path"], str):
                raise InputError(f"{at}.path must be a path, got {shown(record['path'])}")
        else:
            _check_keys(record, {"path", "scene", "seed", "manifest_sha256", "files"}, at)
            _sha256(record["manifest_sha256"], f"{at}.manifest_sha256")
            expected = {"path": f"datasets/{entry.id}", "scene": entry.scene, "seed": entry.seed}
            for key, value in expected.items():
                if record[key] != value or isinstance(record[key], bool):
                    raise InputError(f"{at}.{key} is {shown(record[key])}, the suite's entry says {value!r}")
        files = record["files"]
        if not isinstance(files, dict) or not all(isinstance(rel, str) for rel in files):
            raise InputError(f"{at}.files must be an object of path: sha256, got {shown(files)}")
        for rel, digest in files.items():
            _sha256(digest, f"{at}.files.{rel}")
    return document


def _check_keys(record: dict, keys: set, where: str) -> None:
    if set(record) != keys:
        missing, unknown = sorted(keys - set(record)), sorted(set(record) - keys)
        raise InputError(f"{where}: " + (f"missing field {missing[0]}" if missing else f"unknown field {unknown[0]!r}"))


def _sha256(value, where: str) -> str:
    if not isinstance(value, str) or not SHA256.fullmatch(value):
        raise InputError(f"{where} must be a sha256 (64 hex digits), got {shown(value)}")
    return value


def check_dataset_recipe(suite: Suite, out, entry: SceneEntry) -> None:
    """The suite's entry against the dataset it names: the dataset's config.json (its
    recipe, hashed against the dataset's own manifest) must hold the entry's generate
    settings, so a definition edited in suite.json (its hashes recomputed to match) is
    caught by the datasets it claims to describe."""
    folder = dataset_dir(out, entry)
    listed = dataset.read_manifest(folder).get(CONFIG_FILE)
    path = folder / CONFIG_FILE
    if listed is None or not path.is_file() or path.is_symlink() or sha256_file(path) != listed.sha256:
        raise InputError(f"dataset {folder}: {CONFIG_FILE} is missing or differs from its manifest; regenerate with "
                         "nerfgauge suite generate --overwrite")
    recorded = read_json(path, finite=True).get("config")
    if recorded != suite.generate_config(entry).to_json():
        raise InputError(f"dataset {folder} was generated from other settings than the suite's entry {entry.id!r} "
                         f"({CONFIG_FILE} differs); regenerate with nerfgauge suite generate --overwrite")


# --- results ----------------------------------------------------------------------------


def evaluate_suite(suite: Suite, out, method: str, pred_root, *, pred_format: str = "auto",
                   extras: dict | None = None, log=print, entries=None, skipped: dict | None = None,
                   seeds=None) -> dict:
    """Score PRED_ROOT/<id>/ against every dataset of the suite (eval.evaluate, the same
    function as `nerfgauge evaluate`, under the suite's [scoring]) into
    out/results/<method>/; result.json last.

    extras: {id: {"train_seconds", "model_bytes", "geometry"}} known to the caller.
    PRED_ROOT/<id>/train.json ({"seconds", "model_bytes"}), when present, gives the same for
    another tool's runs. A PRED_ROOT/suite.json naming another suite or version is refused.
    entries: the suite's SceneEntry to score (default all). skipped: {id: why the method
    does not apply}, kept in result.json for the leaderboard.

    seeds: training seeds (the method was run once per seed): PRED_ROOT/seed-<s>/<id>/ holds
    each seed's renders; each is scored into results/<method>/<id>/seed-<s>/metrics.json,
    and results/<method>/<id>/aggregate.json (eval.uncertainty.aggregate_runs) holds every
    run's means, the two-level bootstrap interval over seeds and views, the per-seed spread
    and the variance split. extras may then be {id: {seed: {...}}}."""
    out, pred_root = Path(out), Path(pred_root)
    folder_name(method, "--method")
    manifest = read_suite_folder(suite, out)
    if not pred_root.is_dir():
        raise InputError(f"prediction folder not found: {pred_root}")
    if (pred_root / SUITE_FILE).is_file():
        check_same_suite(suite, read_json(pred_root / SUITE_FILE), str(pred_root / SUITE_FILE))
    entries = suite.scenes if entries is None else tuple(entries)
    seeds = None if seeds is None else tuple(seeds)
    roots = [pred_root] if seeds is None else [pred_root / seed_folder(seed) for seed in seeds]
    missing = [f"{root.relative_to(pred_root).as_posix() + '/' if root != pred_root else ''}{entry.id}"
               for root in roots for entry in entries if not (root / entry.id).is_dir()]
    if missing:
        raise InputError(f"{pred_root} has no predictions for {len(missing)} of the suite's {len(suite.scenes)} "
                         f"datasets: {', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''} "
                         f"(expected {pred_root}/{'' if seeds is None else 'seed-<s>/'}<id>/ for each)")
    renders = {entry.id: {seed: (str(pred_root / (entry.id if seed is None else f"{seed_folder(seed)}/{entry.id}")),
                                 pred_format) for seed in (seeds or (None,))} for entry in entries}
    tasks = scoring_tasks(suite, out, method, renders)
    with folder_lock(out):
        owned.remove_file(out / "results" / method / RESULT_FILE)  # no stale result.json beside new metrics
        documents = []
        for index, task in enumerate(tasks, 1):
            log(f"[{index}/{len(tasks)}] evaluate {method} on {task['entry']}"
                + ("" if task["seed"] is None else f" (seed {task['seed']})"))
            documents.append(score_renders(**task["kwargs"]))
        return write_result(suite, out, manifest, method, tasks, documents, seeds=seeds, extras=extras,
                            skipped=skipped, pred_root=str(pred_root))


def seed_folder(seed: int) -> str:
    """The folder of one training seed's run, renders and metrics: seed-<s>."""
    return f"seed-{seed}"


def scoring_tasks(suite: Suite, out, method: str, renders: dict, threads: int | None = None,
                  failures: bool = False, datasets: dict | None = None) -> list[dict]:
    """The scoring jobs of one method: renders {entry id: {seed or None: (folder, pred
    format)}} (seed None: the method was run once) in the suite's order, each {"key" (the
    job's), "method", "entry", "seed", "metrics" (its path relative to out), "kwargs" of score_renders}.
    datasets: {entry id: the copy of its dataset with the arm's points} (orchestrate.suite.points:
    the same ground truth, checked), scored on in place of the entry's folder."""
    datasets = datasets or {}
    out, tasks = Path(out), []
    for entry in suite.scenes:
        for seed, (folder, pred_format) in renders.get(entry.id, {}).items():
            metrics = Path("results") / method / entry.id / ("" if seed is None else seed_folder(seed)) / "metrics.json"
            key = f"score/{method}/" + ("" if seed is None else f"{seed_folder(seed)}/") + entry.id
            tasks.append({"key": key, "method": method, "entry": entry.id, "seed": seed, "metrics": metrics.as_posix(), "kwargs": dict(
                dataset=str(datasets.get(entry.id, dataset_dir(out, entry))), renders=str(folder), metrics=str(out / metrics),
                scoring=suite.scoring, pred_format=pred_format, threads=threads, failures=failures)})
    return tasks


def score_renders(dataset: str, renders: str, metrics: str, scoring: dict, pred_format: str = "auto",
                  threads: int | None = None, failures: bool = False) -> dict:
    """eval.evaluate of one folder of renders under a suite's [scoring] into `metrics`: its
    document. A job: `suite run` runs these here or on its dask cluster like the training
    jobs (orchestrate.suite.jobs.run_jobs). threads: torch's thread count while it scores
    (then restored): LPIPS's float32 convolutions sum in an order that depends on it, so a
    cluster's scores equal a local run's at the same count. failures: an InputError (renders
    that cannot be scored: a method's fault in `suite run`) comes back as {"failed": line}."""
    import torch  # torch: only where a scoring job runs

    before = torch.get_num_threads()
    try:
        if threads is not None:
            torch.set_num_threads(threads)
        return evaluate(dataset, renders, split=scoring["split"], out=metrics, background=scoring["background"],
                        depth_kind=scoring["depth_kind"], pred_format=pred_format,
                        protocol=scoring.get("protocol", "nerfgauge"))
    except InputError as error:
        if not failures:
            raise
        return {"failed": f"its renders could not be scored: {error}"}
    finally:
        torch.set_num_threads(before)


def write_result(suite: Suite, out, manifest: dict, method: str, tasks: list, documents: list, *, seeds=None,
                 extras: dict | None = None, skipped: dict | None = None, failed: dict | None = None,
                 pred_root: str | None = None) -> dict:
    """results/<method>/result.json from its scoring tasks' documents (scoring_tasks,
    score_renders): a row per dataset (seeds: its runs and aggregate.json), the training
    figures of `extras` beside each, the datasets where it was skipped or failed with why.
    A dataset where any seed's scoring failed is failed. Written last; returns it."""
    out, extras, failed = Path(out), extras or {}, dict(failed or {})
    by_entry = {}
    for task, document in zip(tasks, documents):
        by_entry.setdefault(task["entry"], []).append((task, document))
    rows = {}
    for entry in suite.scenes:
        scored = by_entry.get(entry.id)
        if not scored:
            continue
        broken = [(task, document) for task, document in scored if "failed" in document]
        if broken:
            task, document = broken[0]
            failed[entry.id] = document["failed"] if task["seed"] is None else f"seed {task['seed']}: {document['failed']}"
            continue
        record = manifest["datasets"][entry.id]
        key = identity_key(record)
        runs, docs = [], []
        for task, document in scored:
            extra = extras.get(entry.id, {}) if seeds is None else extras.get(entry.id, {}).get(task["seed"], {})
            runs.append(_result_row(out, entry, record, task, document, extra))
            docs.append(document)
        if seeds is None:
            rows[entry.id] = {key: record[key], **runs[0]}
            continue
        runs = [{**run, "seed": task["seed"]} for run, (task, _) in zip(runs, scored)]
        aggregate = aggregate_runs(docs, list(seeds), [m for m in METRIC_NAMES if m in docs[0]["mean"]])
        aggregate_path = out / "results" / method / entry.id / AGGREGATE_FILE
        write_json(aggregate_path, {"method": method, "scene": entry.id, **aggregate})
        rows[entry.id] = {key: record[key], "metrics": runs[0]["metrics"],
                          "aggregate": aggregate_path.relative_to(out).as_posix(), "seeds": list(seeds),
                          "runs": runs, **{name: _mean_of(runs, name) for name in COST_FIELDS},
                          "geometry": _mean_geometry(runs)}
    result = {**suite.identity(), "schema": SCHEMA, "method": method,
              **({"pred_root": pred_root} if pred_root is not None else {}),
              "datasets": rows, **({"skipped": dict(skipped)} if skipped else {}),
              **({"failed": failed} if failed else {}), **({"seeds": list(seeds)} if seeds is not None else {})}
    write_json(owned.make_folder(out / "results" / method) / RESULT_FILE, result)
    return result


def _result_row(out: Path, entry, record: dict, task: dict, document: dict, extras: dict) -> dict:
    """One run's row of result.json: where its metrics are, its render time and the
    training figures known for it; its metrics.json gains a "training" block where the
    step count is known (check prints it)."""
    metrics_path = out / task["metrics"]
    if identity_key(record) == "ground_truth_sha256":  # the files this scoring read are the ones recorded
        read = document.get("ground_truth", {}).get("files", {})
        changed = sorted(rel for rel, digest in read.items() if record["files"].get(rel) != digest)
        if changed:
            owned.remove_file(metrics_path)
            raise InputError(f"ground-truth folder {dataset_dir(out, entry)} ({entry.id}): {changed[0]} "
                             f"changed while it was scored ({len(changed)} files differ from {SUITE_MANIFEST})")
    renders = Path(task["kwargs"]["renders"])
    inside = renders.is_relative_to(out / "predictions" / task["method"])  # suite run's: kept relative, so the
    row = {"metrics": task["metrics"], "renders": renders.relative_to(out).as_posix() if inside  # folder can move
           else str(renders), "pred_format": task["kwargs"]["pred_format"],
           "ms_per_frame": document["timing"].get("ms_per_frame"), "train_seconds": None, "model_bytes": None,
           "geometry": None}
    train_file = Path(task["kwargs"]["renders"]) / "train.json"
    if not extras and train_file.is_file():  # another tool's figures beside its renders (suite evaluate)
        info = read_json(train_file, finite=True)
        row["train_seconds"], row["model_bytes"] = info.get("seconds"), info.get("model_bytes")
    row.update({name: value for name, value in extras.items() if name != "ms_per_frame"})
    if row["ms_per_frame"] is None:  # renders without our timing.json: the render job's own time
        row["ms_per_frame"] = extras.get("ms_per_frame")
    if isinstance(extras.get("steps"), int):  # the training beside its scores (check prints it)
        document["training"] = {"steps": extras["steps"], "seconds": extras.get("train_seconds"),
                                "steps_per_second": extras.get("steps_per_second"),
                                "budget_seconds": extras.get("budget_seconds"),
                                **({"seed": extras["seed"]} if isinstance(extras.get("seed"), int) else {})}
        write_json(metrics_path, document)
    return row


def _mean_of(runs: list, name: str):
    """The mean of a cost figure over the runs that have it (None when none has)."""
    values = [run[name] for run in runs if isinstance(run.get(name), (int, float)) and not isinstance(run.get(name), bool)]
    return mean_of(values, f"the runs' mean {name}") if values else None


def _mean_geometry(runs: list):
    """The runs' geometry figures averaged (those defined in some run); None when no run has any."""
    tables = [run["geometry"] for run in runs if isinstance(run.get("geometry"), dict) and "n/a" not in run["geometry"]]
    if not tables:
        return next((run["geometry"] for run in runs if isinstance(run.get("geometry"), dict)), None)
    return {name: _mean_of(tables, name) for name in sorted({k for table in tables for k in table})}


def read_results(suite: Suite, out) -> dict:
    """{method: result.json} of every method in out/results/, each checked against the suite
    folder (`check_result`): another suite version, definition or dataset manifest hash is
    refused, and so is a malformed record. A method may lack some datasets (shown as not
    applicable)."""
    out = Path(out)
    manifest = read_suite_folder(suite, out)
    results = {}
    folder = out / "results"
    for path in sorted(folder.glob(f"*/{RESULT_FILE}")) if folder.is_dir() else []:
        result = check_result(read_json(path, finite=True), suite, manifest, path)
        results[result["method"]] = result
    if not results:
        raise InputError(f"{out} holds no results yet (no results/<method>/{RESULT_FILE}); "
                         "run nerfgauge suite evaluate or suite run")
    return results


COST_FIELDS = ("ms_per_frame", "train_seconds", "model_bytes", "steps", "steps_per_second", "cpu_seconds",
               "peak_memory_bytes", "budget_seconds")


def check_result(result: dict, suite: Suite, manifest: dict, path: Path) -> dict:
    """A results/<method>/result.json as evaluate_suite writes it, or InputError (one line
    naming the field): this suite's identity; its method the folder's name (folder_name);
    only the suite's datasets; each row scored against the recorded dataset; every path in
    it exactly the one evaluate_suite writes under results/<method>/<id>/ (so no file
    outside it is read); seeds as --seeds takes them; costs and geometry finite numbers or
    null; skipped reasons strings."""
    check_same_suite(suite, result, str(path))
    method = folder_name(result.get("method"), f"{path}: method")
    if method != path.parent.name:
        raise InputError(f"{path} is for method {method!r}, but lies in results/{path.parent.name}/")
    rows, ids = result.get("datasets"), {entry.id for entry in suite.scenes}
    if not isinstance(rows, dict) or not set(rows) <= ids:
        raise InputError(f"{path}: datasets must be an object of the suite's dataset ids, got "
                         f"{shown(sorted(set(rows) - ids)[0] if isinstance(rows, dict) else rows)}")
    for name in ("skipped", "failed"):
        reasons = result.get(name, {})
        if not isinstance(reasons, dict) or not set(reasons) <= ids or not all(isinstance(v, str) for v in reasons.values()):
            raise InputError(f"{path}: {name} must be an object of dataset id: reason, got {shown(reasons)}")
    if "seeds" in result:
        _seeds(result["seeds"], f"{path}: seeds")
    if not isinstance(result.get("pred_root", ""), str) or "\0" in result.get("pred_root", ""):
        raise InputError(f"{path}: pred_root must be a path, got {shown(result.get('pred_root'))}")
    base = f"results/{method}"
    for entry_id, row in rows.items():
        at = f"{path}: datasets.{entry_id}"
        if not isinstance(row, dict):
            raise InputError(f"{at} must be an object, got {shown(row)}")
        record = manifest["datasets"][entry_id]
        key = identity_key(record)
        if row.get(key) != record[key]:
            what = "ground-truth files hash" if key == "ground_truth_sha256" else "manifest hash"
            raise InputError(f"{path}: dataset {entry_id} was scored against a dataset whose {what} "
                             f"differs from {SUITE_MANIFEST}; evaluate again")
        _costs(row, at)
        if "runs" in row:
            runs = row["runs"]
            if not isinstance(runs, list) or not runs or not all(isinstance(run, dict) for run in runs):
                raise InputError(f"{at}.runs must be a non-empty list of runs, got {shown(runs)}")
            seeds = _seeds([run.get("seed") for run in runs], f"{at}.runs' seeds")
            if row.get("seeds") != seeds:
                raise InputError(f"{at}.seeds is {shown(row.get('seeds'))}, its runs' seeds are {seeds}")
            for run, seed in zip(runs, seeds):
                _expect(run.get("metrics"), f"{base}/{entry_id}/{seed_folder(seed)}/metrics.json", f"{at}.runs.metrics")
                _costs(run, f"{at}.runs[seed {seed}]")
                _renders(run, method, result.get("pred_root"), f"{at}.runs[seed {seed}]")
            _expect(row.get("metrics"), runs[0]["metrics"], f"{at}.metrics")
            _expect(row.get("aggregate"), f"{base}/{entry_id}/{AGGREGATE_FILE}", f"{at}.aggregate")
        else:
            _expect(row.get("metrics"), f"{base}/{entry_id}/metrics.json", f"{at}.metrics")
            _renders(row, method, result.get("pred_root"), at)
    return result


def _renders(row: dict, method: str, pred_root, where: str) -> None:
    """Where a row's renders are (read again by the protocol-sensitivity table): inside
    the suite folder's predictions/<method>/ (suite run), or inside the pred_root the user
    gave (suite evaluate); their layout one evaluate reads. Rows from before are without."""
    renders = row.get("renders")
    if renders is None:
        return
    if not isinstance(renders, str) or "\0" in renders or ".." in Path(renders).parts:
        raise InputError(f"{where}.renders must be a path inside the method's predictions, got {shown(renders)}")
    inside = (Path(renders).is_relative_to(pred_root) if Path(renders).is_absolute() and isinstance(pred_root, str)
              else not Path(renders).is_absolute() and Path(renders).parts[:2] == ("predictions", method))
    if not inside or row.get("pred_format") not in PRED_FORMATS:
        raise InputError(f"{where}.renders must lie in predictions/{method}/ or its pred_root and pred_format be one "
                         f"of {', '.join(PRED_FORMATS)}, got {shown(renders)}, {shown(row.get('pred_format'))}")


def _expect(value, expected: str, where: str) -> None:
    """A path a record holds must be the one its writer makes (a path relative to the suite
    folder: anything else could lead out of it)."""
    if value != expected:
        raise InputError(f"{where} must be {expected!r}, got {shown(value)}")


def _seeds(value, where: str) -> list:
    if not isinstance(value, list):
        raise InputError(f"{where} must be a list of seeds, got {shown(value)}")
    try:
        return arguments.check_seeds(value)
    except InputError as error:
        raise InputError(f"{where}: {error}") from None


def _costs(row: dict, where: str) -> None:
    """A row's cost figures finite numbers >= 0 or null, its geometry a table of them."""
    for name in COST_FIELDS:
        value = row.get(name)
        if value is not None and not (finite_number(value) and value >= 0):
            raise InputError(f"{where}.{name} must be a number >= 0 or null, got {shown(value)}")
    check_geometry(row.get("geometry"), f"{where}.geometry")


def check_geometry(value, where: str):
    """Our NeRF's geometry figures as a job or a result records them: null, {"n/a": reason},
    or {figure of eval.geometry.SUMMARY_NAMES: finite number or null}."""
    if value is None:
        return value
    if not isinstance(value, dict):
        raise InputError(f"{where} must be an object or null, got {shown(value)}")
    if "n/a" in value:
        if set(value) != {"n/a"} or not isinstance(value["n/a"], str):
            raise InputError(f"{where}: n/a must be alone, with its reason, got {shown(value)}")
        return value
    for name, figure in value.items():
        if name not in SUMMARY_NAMES or (figure is not None and not finite_number(figure)):
            raise InputError(f"{where}.{name} must be a geometry figure ({', '.join(SUMMARY_NAMES[:2])}, ...) "
                             f"holding a finite number or null, got {shown(figure)}")
    return value


JOB_RESULT = ("method", "seed", "train_seconds", "steps", "steps_per_second", "cpu_seconds", "peak_memory_bytes",
              "model_bytes", "budget_seconds", "threads", "geometry", "renders", "pred_format", "frames",
              "render_seconds")


def job_result(record: dict, recipe: dict, path) -> dict:
    """The result a finished job's record (OUT/jobs/<method>/[seed-<s>/]<id>.json,
    orchestrate.suite.jobs) holds, checked as the job wrote it: JOB_RESULT's keys; its
    method and seed the job's; costs finite numbers >= 0 or null (steps, model_bytes and
    threads integers); geometry null unless the suite scores it; its renders the folder the
    job renders into or inside it, in a layout evaluate reads. InputError naming the record
    otherwise: a record is data that flows into result.json and the leaderboard."""
    result = record.get("result")
    where = f"{path}: result"
    if not isinstance(result, dict):
        raise InputError(f"{where} must be an object, got {shown(result)}; delete the record to run the job again")
    _check_keys(result, set(JOB_RESULT), where)
    _costs(result, where)
    for name, low in (("model_bytes", 0), ("steps", 1), ("threads", 1), ("frames", 1)):
        value = result[name]
        if (value is not None or name == "frames") and (not isinstance(value, int) or isinstance(value, bool)
                                                        or value < low):
            raise InputError(f"{where}.{name} must be an integer >= {low}, got {shown(value)}")
    if result["method"] != recipe["method"]["name"]:
        raise InputError(f"{where}.method is {shown(result['method'])}, the job's is {recipe['method']['name']}")
    if result["seed"] != recipe["seed"] or isinstance(result["seed"], bool):
        raise InputError(f"{where}.seed is {shown(result['seed'])}, the job's seed is {recipe['seed']}")
    if recipe.get("geometry") is None and result["geometry"] is not None:
        raise InputError(f"{where}.geometry must be null: the suite scores no geometry")
    renders, target = result["renders"], recipe["renders"]
    if (not isinstance(renders, str) or ".." in Path(renders).parts or not Path(renders).is_relative_to(target)
            or result["pred_format"] not in PRED_FORMATS):
        raise InputError(f"{where}.renders must lie in {target} in a layout evaluate reads, got {shown(renders)}, "
                         f"{shown(result['pred_format'])}")
    return result


def suite_from_folder(out) -> Suite:
    """The suite a folder was made from, as its suite.json records it: the definition parsed
    as a suite file is (suite_from_definition), its sha256 recomputed from that (the one
    suite.json states covers itself, so proves nothing) and checked against the folder's
    marker and suite manifest by read_suite_folder, which every reader calls."""
    path = Path(out) / SUITE_FILE
    if not path.is_file():
        raise InputError(f"{out} is not a suite folder (no {SUITE_FILE}); make it with nerfgauge suite generate")
    recorded = read_json(path, finite=True)
    suite = suite_from_definition(recorded, str(path))
    check_same_suite(suite, recorded, str(path))
    return suite
