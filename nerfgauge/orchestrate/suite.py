"""Benchmark suites: versioned sets of datasets, and results tied to them.

A suite is a TOML file (suites/*.toml, installed as the package nerfgauge.suites; or any
path ending in .toml):

    name = "smoke"                 # required
    version = 1                    # required, a positive integer: bump it on any change
    description = "..."            # optional
    [dataset]                      # required: nerfgauge generate settings (GenerateConfig
    width = 16 ...                 #   fields but scene and seed, the train-view degradations
                                   #   too); width, height, views, test_views and spp are required
    [train]                        # required: our NeRF (TrainConfig fields but dataset and
    steps = 80 ...                 #   seed); steps is required (reproducible)
    [protocol]                     # required: split, background, depth_kind; optional
    split = "test" ...             #   baselines (eval.baselines.METHODS; the lightfield ones
                                   #   run on lightfield layouts only) and geometry
                                   #   {resolution, samples} (our NeRF's mesh scored)
    [[scenes]]                     # at least one: scene (a registered recipe) and seed are
    scene = "primitives"           #   required; id (default: the scene) names its folder;
    seed = 0                       #   any [dataset] key overrides the default for it
    [[scenes]]                     # or ground truth nerfgauge did not write: folder (relative
    id = "lego"                    #   to the .toml's folder) is a NeRF-synthetic, nerfstudio
    folder = "nerf_synthetic/lego" #   or COLMAP text-model folder (core.foreign_dataset); id
                                   #   defaults to its name; no other key

A missing or unknown field, a wrong type, an unknown scene, or two entries with one id is an
InputError naming the file and the field. The suite's identity is its version and the
sha256 of its canonical JSON (`Suite.sha256`): editing a suite without bumping its
version still changes the hash, and results are refused either way.

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
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.resources
import math
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from nerfgauge.core import bounded, dataset, owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import json_bytes, read_json, sha256_file, write_json
from nerfgauge.core.folders import claim_folder, folder_lock
from nerfgauge.eval.baselines import METHODS
from nerfgauge.eval.evaluate import BACKGROUNDS, evaluate
from nerfgauge.eval.metrics import METRIC_NAMES
from nerfgauge.eval.uncertainty import aggregate_runs
from nerfgauge.eval.predictions import DEPTH_SUFFIXES
from nerfgauge.generate.distributed import check_reachable
from nerfgauge.generate.pipeline import GenerateConfig, generate
from nerfgauge.scenes.registry import RECIPES

SUITE_FILE = "suite.json"
SUITE_MANIFEST = "suite-manifest.json"
RESULT_FILE = "result.json"
AGGREGATE_FILE = "aggregate.json"  # results/<method>/<id>/aggregate.json: a method's runs over seeds
SCHEMA = 1
OURS = "compact-nerf"  # our NeRF's name on the leaderboard (suite run)
REQUIRED = {"dataset": ("width", "height", "views", "test_views", "spp"), "train": ("steps",),
            "protocol": ("split", "background", "depth_kind")}
PROTOCOL_KEYS = {"split": str, "background": str, "depth_kind": str, "baselines": list, "geometry": dict}
GEOMETRY_KEYS = ("resolution", "samples")


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
    train: dict  # TrainConfig fields
    protocol: dict
    scenes: tuple  # SceneEntry
    source: str  # where it was read from (named in errors)

    def definition(self) -> dict:
        """Everything that makes results comparable (not where the file lives)."""
        return {"name": self.name, "version": self.version, "description": self.description,
                "train": self.train, "protocol": self.protocol,
                "scenes": [entry.definition() for entry in self.scenes]}

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
    folder = importlib.resources.files("nerfgauge.orchestrate.suites")
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


def parse_suite(data: dict, source: str, base=None) -> Suite:
    """base: the folder relative `folder` entries are resolved against (the .toml's)."""
    from nerfgauge.nerf.config import TrainConfig  # torch: kept off `nerfgauge --help`'s import path

    _check_fields(data, {"name", "version", "description", "dataset", "train", "protocol", "scenes"}, source)
    for field in ("name", "version"):
        if field not in data:
            raise InputError(f"{source}: missing field {field}")
    name, version = data["name"], data["version"]
    if not isinstance(name, str) or not name.strip() or "/" in name:
        raise InputError(f"{source}: name must be a non-empty string without '/', got {name!r}")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise InputError(f"{source}: version must be a positive integer, got {version!r}")
    description = data.get("description", "")
    if not isinstance(description, str):
        raise InputError(f"{source}: description must be a string, got {description!r}")
    dataset_defaults = _table(data, "dataset", source)
    generate_fields = {f.name for f in dataclasses.fields(GenerateConfig)} - {"scene", "seed"}
    _check_fields(dataset_defaults, generate_fields, f"{source} [dataset]")
    train = _table(data, "train", source)
    _check_fields(train, {f.name for f in dataclasses.fields(TrainConfig)} - {"dataset", "seed", "budget_seconds"},
                  f"{source} [train]")
    protocol = _table(data, "protocol", source)
    _check_fields(protocol, set(PROTOCOL_KEYS), f"{source} [protocol]")
    for key, kind in PROTOCOL_KEYS.items():
        if key in protocol and not isinstance(protocol[key], kind):
            raise InputError(f"{source}: protocol.{key} must be a {kind.__name__}, got {protocol[key]!r}")
    if protocol["background"] not in BACKGROUNDS or protocol["depth_kind"] not in DEPTH_SUFFIXES:
        raise InputError(f"{source}: protocol.background must be one of {', '.join(BACKGROUNDS)} and "
                         f"protocol.depth_kind one of {', '.join(DEPTH_SUFFIXES)}")
    if protocol["split"] not in dataset.SPLITS:
        raise InputError(f"{source}: protocol.split must be one of {', '.join(dataset.SPLITS)}, got {protocol['split']!r}")
    protocol.setdefault("baselines", [])
    for method in protocol["baselines"]:
        if method not in METHODS:
            raise InputError(f"{source}: protocol.baselines: unknown baseline {method!r}; known: {', '.join(METHODS)}")
    if "geometry" in protocol:
        geometry = protocol["geometry"]
        _check_fields(geometry, set(GEOMETRY_KEYS), f"{source} protocol.geometry")
        for key in GEOMETRY_KEYS:
            if not isinstance(geometry.get(key), int) or isinstance(geometry.get(key), bool) or geometry[key] < 2:
                raise InputError(f"{source}: protocol.geometry.{key} must be an integer >= 2, got {geometry.get(key)!r}")
    scenes = data.get("scenes")
    if scenes is None:
        raise InputError(f"{source}: missing field [[scenes]]")
    if not isinstance(scenes, list) or not scenes or not all(isinstance(s, dict) for s in scenes):
        raise InputError(f"{source}: [[scenes]] must be a non-empty list of tables")
    entries, ids = [], set()
    for k, raw in enumerate(scenes):
        where = f"{source} scenes[{k}]"
        if "folder" in raw:
            entry = _folder_entry(raw, where, base)
            if entry.id in ids:
                raise InputError(f"{where}: id {entry.id!r} is used twice; give each entry its own id")
            ids.add(entry.id)
            entries.append(entry)
            continue
        _check_fields(raw, generate_fields | {"id", "scene", "seed"}, where)
        for field in ("scene", "seed"):
            if field not in raw:
                raise InputError(f"{where}: missing field {field}")
        if raw["scene"] not in RECIPES:
            raise InputError(f"{where}: unknown scene {raw['scene']!r}; known: {', '.join(RECIPES)}")
        if not isinstance(raw["seed"], int) or isinstance(raw["seed"], bool) or raw["seed"] < 0:
            raise InputError(f"{where}: seed must be a non-negative integer, got {raw['seed']!r}")
        entry_id = raw.get("id", raw["scene"])
        if not isinstance(entry_id, str) or not entry_id or "/" in entry_id or entry_id.startswith("."):
            raise InputError(f"{where}: id must be a folder name, got {entry_id!r}")
        if entry_id in ids:
            raise InputError(f"{where}: id {entry_id!r} is used twice; give each entry its own id")
        ids.add(entry_id)
        settings = {**dataset_defaults, **{key: value for key, value in raw.items() if key in generate_fields}}
        if isinstance(settings.get("elevation"), list):
            settings["elevation"] = tuple(settings["elevation"])
        entry = SceneEntry(entry_id, raw["scene"], raw["seed"], settings)
        try:
            config = GenerateConfig(scene=entry.scene, seed=entry.seed, **settings)
            config.validate()
            TrainConfig(dataset=".", seed=entry.seed, **train).validate()
        except (TypeError, ValueError) as error:
            raise InputError(f"{where}: {error}") from None
        except InputError as error:
            raise InputError(f"{where}: {error}") from None
        entries.append(entry)
    return Suite(name, version, description, train, protocol, tuple(entries), source)


def _folder_entry(raw: dict, where: str, base) -> SceneEntry:
    """A [[scenes]] entry naming a ground-truth folder nerfgauge did not write."""
    _check_fields(raw, {"id", "folder"}, f"{where} (a folder entry)")
    folder = raw["folder"]
    if not isinstance(folder, str) or not folder.strip():
        raise InputError(f"{where}: folder must be a path, got {folder!r}")
    path = Path(folder).expanduser()
    if not path.is_absolute():
        path = Path(base if base is not None else ".") / path
    path = path.resolve()
    if not path.is_dir():
        raise InputError(f"{where}: folder {folder!r} not found (looked for {path})")
    if (path / dataset.MANIFEST).is_file() or (path / dataset.MARKER).exists():
        raise InputError(f"{where}: folder {path} is a nerfgauge dataset; folder entries are for ground truth "
                         f"nerfgauge did not write (list our scenes by recipe: scene and seed)")
    entry_id = raw.get("id", path.name)
    if not isinstance(entry_id, str) or not entry_id or "/" in entry_id or entry_id.startswith("."):
        raise InputError(f"{where}: id must be a folder name, got {entry_id!r}")
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
        previous = read_json(manifest_path) if manifest_path.is_file() else {"datasets": {}}
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
    """The suite manifest of a complete suite folder made from `suite`; InputError otherwise,
    also when a dataset's manifest.json no longer has the hash the suite manifest recorded."""
    out = Path(out)
    if not (out / SUITE_FILE).is_file():
        raise InputError(f"{out} is not a suite folder (no {SUITE_FILE}); make it with nerfgauge suite generate")
    check_same_suite(suite, read_json(out / SUITE_FILE), str(out / SUITE_FILE))
    if not (out / SUITE_MANIFEST).is_file():
        raise InputError(f"suite folder {out} is incomplete (no {SUITE_MANIFEST}); finish it with nerfgauge suite generate")
    manifest = read_json(out / SUITE_MANIFEST, finite=True)
    check_same_suite(suite, manifest, str(out / SUITE_MANIFEST))
    for entry in suite.scenes:
        record = manifest.get("datasets", {}).get(entry.id)
        path = dataset_dir(out, entry) / dataset.MANIFEST
        if record is None:
            raise InputError(f"{out / SUITE_MANIFEST} lists no dataset {entry.id!r}")
        if entry.foreign or "ground_truth_sha256" in record:
            if not (entry.foreign and "ground_truth_sha256" in record):
                raise InputError(f"{out / SUITE_MANIFEST}: dataset {entry.id!r} was recorded as "
                                 f"{'a folder' if 'ground_truth_sha256' in record else 'a recipe'}; regenerate with "
                                 "nerfgauge suite generate --overwrite")
            check_folder(entry, record, str(out / SUITE_MANIFEST))
            continue
        if not path.is_file() or sha256_file(path) != record.get("manifest_sha256"):
            raise InputError(f"dataset {dataset_dir(out, entry)}: its manifest hash differs from the one in "
                             f"{out / SUITE_MANIFEST}; regenerate with nerfgauge suite generate --overwrite")
    return manifest


# --- results ----------------------------------------------------------------------------


def evaluate_suite(suite: Suite, out, method: str, pred_root, *, pred_format: str = "auto",
                   extras: dict | None = None, log=print, entries=None, skipped: dict | None = None,
                   seeds=None) -> dict:
    """Score PRED_ROOT/<id>/ against every dataset of the suite (eval.evaluate, the same
    function as `nerfgauge evaluate`) into out/results/<method>/; result.json last.

    extras: {id: {"train_seconds", "model_bytes", "geometry"}} known to the caller (suite run).
    PRED_ROOT/<id>/train.json ({"seconds", "model_bytes"}), when present, gives the same for
    another tool's runs. A PRED_ROOT/suite.json naming another suite or version is refused.
    entries: the suite's SceneEntry to score (default all; `suite run` passes the light-field
    datasets only for the light-field baselines). skipped: {id: why the method does not apply},
    kept in result.json for the leaderboard.

    seeds: training seeds (suite run --seeds): PRED_ROOT/seed-<s>/<id>/ holds each seed's
    renders; each is scored into results/<method>/<id>/seed-<s>/metrics.json, and
    results/<method>/<id>/aggregate.json (eval.uncertainty.aggregate_runs) holds every run's
    means, the two-level bootstrap interval over seeds and views, the per-seed spread and
    the variance split. extras may then be {id: {seed: {...}}}."""
    out, pred_root = Path(out), Path(pred_root)
    if not method or "/" in method or method.startswith("."):
        raise InputError(f"--method must be a folder name, got {method!r}")
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
    extras = extras or {}
    results_dir = out / "results" / method
    with folder_lock(out):
        owned.remove_file(results_dir / RESULT_FILE)  # no stale result.json beside new metrics
        rows = {}
        for index, entry in enumerate(entries, 1):
            log(f"[{index}/{len(entries)}] evaluate {method} on {entry.id}"
                + ("" if seeds is None else f" ({len(seeds)} seeds)"))
            record = manifest["datasets"][entry.id]
            key = identity_key(record)
            if seeds is None:
                rows[entry.id] = _score_one(suite, out, entry, record, pred_root / entry.id,
                                            results_dir / entry.id / "metrics.json", pred_format,
                                            extras.get(entry.id, {}))[0]
                continue
            runs, documents = [], []
            for seed in seeds:
                row, document = _score_one(suite, out, entry, record, pred_root / seed_folder(seed) / entry.id,
                                           results_dir / entry.id / seed_folder(seed) / "metrics.json",
                                           pred_format, extras.get(entry.id, {}).get(seed, {}))
                runs.append({"seed": seed, **{k: v for k, v in row.items() if k != key}})
                documents.append(document)
            aggregate = aggregate_runs(documents, list(seeds), [m for m in METRIC_NAMES if m in documents[0]["mean"]])
            aggregate_path = results_dir / entry.id / AGGREGATE_FILE
            write_json(aggregate_path, {"method": method, "scene": entry.id, **aggregate})
            first = runs[0]
            rows[entry.id] = {key: record[key], "metrics": first["metrics"],
                              "aggregate": aggregate_path.relative_to(out).as_posix(), "seeds": list(seeds),
                              "runs": runs, **{name: _mean_of(runs, name) for name in
                                               ("ms_per_frame", "train_seconds", "model_bytes", "steps")},
                              "geometry": _mean_geometry(runs)}
        result = {**suite.identity(), "schema": SCHEMA, "method": method, "pred_root": str(pred_root),
                  "datasets": rows, **({"skipped": dict(skipped)} if skipped else {}),
                  **({"seeds": list(seeds)} if seeds is not None else {})}
        write_json(results_dir / RESULT_FILE, result)
    return result


def seed_folder(seed: int) -> str:
    """The folder of one training seed's run, renders and metrics: seed-<s>."""
    return f"seed-{seed}"


def _score_one(suite: Suite, out: Path, entry, record: dict, pred_dir: Path, metrics_path: Path, pred_format: str,
               extras: dict) -> tuple[dict, dict]:
    """eval.evaluate of one folder of renders into metrics_path: (result.json row, document)."""
    document = evaluate(dataset_dir(out, entry), pred_dir, split=suite.protocol["split"],
                        out=metrics_path, background=suite.protocol["background"],
                        depth_kind=suite.protocol["depth_kind"], pred_format=pred_format)
    key = identity_key(record)
    if key == "ground_truth_sha256":  # the files this scoring read are the ones recorded
        read = document.get("ground_truth", {}).get("files", {})
        changed = sorted(rel for rel, digest in read.items() if record["files"].get(rel) != digest)
        if changed:
            owned.remove_file(metrics_path)
            raise InputError(f"ground-truth folder {dataset_dir(out, entry)} ({entry.id}): {changed[0]} "
                             f"changed while it was scored ({len(changed)} files differ from {SUITE_MANIFEST})")
    row = {key: record[key],
           "metrics": metrics_path.relative_to(out).as_posix(),
           "ms_per_frame": document["timing"].get("ms_per_frame"),
           "train_seconds": None, "model_bytes": None, "geometry": None}
    train_file = pred_dir / "train.json"
    if train_file.is_file():
        info = read_json(train_file, finite=True)
        row["train_seconds"], row["model_bytes"] = info.get("seconds"), info.get("model_bytes")
    row.update(extras)
    if isinstance(extras.get("steps"), int):  # our NeRF's training beside its scores (check prints it)
        document["training"] = {"steps": extras["steps"], "seconds": extras.get("train_seconds"),
                                "steps_per_second": extras.get("steps_per_second"), "budget_seconds": None,
                                **({"seed": extras["seed"]} if isinstance(extras.get("seed"), int) else {})}
        write_json(metrics_path, document)
    return row, document


def _mean_of(runs: list, name: str):
    """The mean of a cost figure over the runs that have it (None when none has)."""
    values = [run[name] for run in runs if isinstance(run.get(name), (int, float)) and not isinstance(run.get(name), bool)]
    return math.fsum(values) / len(values) if values else None


def _mean_geometry(runs: list):
    """The runs' geometry figures averaged (those defined in some run); None when no run has any."""
    tables = [run["geometry"] for run in runs if isinstance(run.get("geometry"), dict) and "n/a" not in run["geometry"]]
    if not tables:
        return next((run["geometry"] for run in runs if isinstance(run.get("geometry"), dict)), None)
    return {name: _mean_of(tables, name) for name in sorted({k for table in tables for k in table})}


def read_results(suite: Suite, out) -> dict:
    """{method: result.json} of every method in out/results/, each checked against the suite
    folder: another suite version, definition or dataset manifest hash is refused. A method
    may lack some datasets (shown as not applicable)."""
    out = Path(out)
    manifest = read_suite_folder(suite, out)
    results = {}
    folder = out / "results"
    for path in sorted(folder.glob(f"*/{RESULT_FILE}")) if folder.is_dir() else []:
        result = read_json(path, finite=True)
        check_same_suite(suite, result, str(path))
        for entry in suite.scenes:
            row = result.get("datasets", {}).get(entry.id)
            if row is None:  # a method that does not apply to this dataset (light-field baselines)
                continue
            key = identity_key(manifest["datasets"][entry.id])
            if row.get(key) != manifest["datasets"][entry.id][key]:
                what = "ground-truth files hash" if key == "ground_truth_sha256" else "manifest hash"
                raise InputError(f"{path}: dataset {entry.id} was scored against a dataset whose {what} "
                                 f"differs from {out / SUITE_MANIFEST}; evaluate again")
        results[result["method"]] = result
    if not results:
        raise InputError(f"{out} holds no results yet (no results/<method>/{RESULT_FILE}); "
                         "run nerfgauge suite evaluate or suite run")
    return results


def suite_from_folder(out) -> Suite:
    """The suite a folder was made from, as recorded in its suite.json."""
    path = Path(out) / SUITE_FILE
    if not path.is_file():
        raise InputError(f"{out} is not a suite folder (no {SUITE_FILE}); make it with nerfgauge suite generate")
    recorded = read_json(path, finite=True)
    definition = recorded.get("definition")
    if not isinstance(definition, dict):
        raise InputError(f"{path}: no suite definition")
    scenes = definition.get("scenes", [])
    try:
        folders = recorded.get("folders", {})
        entries = tuple(SceneEntry(s["id"], None, 0, {}, folder=s["folder"], path=folders[s["id"]]) if "folder" in s
                        else SceneEntry(s["id"], s["scene"], s["seed"], s["dataset"]) for s in scenes)
        suite = Suite(definition["name"], definition["version"], definition.get("description", ""),
                      definition["train"], definition["protocol"], entries, str(path))
    except (KeyError, TypeError) as error:
        raise InputError(f"{path}: malformed suite definition ({error!r})") from None
    check_same_suite(suite, recorded, str(path))
    return suite
