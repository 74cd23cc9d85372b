"""Suite definitions for the suite tests, written from data: one TOML writer instead of a
copy of the same file in every test module (docs/conventions.md: a suite's tables)."""

from __future__ import annotations

# What every tiny test suite scores with, unless a test says otherwise.
PROTOCOL = {"split": "test", "background": "white", "depth_kind": "distance", "baselines": ["nearest"]}
# Two 16x16 datasets: the procedural scene and a random one.
TWO_SCENES = ({"scene": "primitives", "seed": 0}, {"id": "random-3", "scene": "random", "seed": 3})


def _value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_value(item) for item in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{key} = {_value(item)}" for key, item in value.items()) + " }"
    return repr(value)


def _table(values: dict) -> str:
    return "".join(f"{key} = {_value(value)}\n" for key, value in values.items())


LENGTH = ("steps", "budget_seconds", "threads")  # [train]'s keys beside [[methods]]


def suite_toml(name: str, dataset: dict, train: dict, scenes=TWO_SCENES, *, version: int = 1,
               description: str | None = None, protocol: dict | None = None, methods=None) -> str:
    """The TOML of a suite: top-level name, version (and description), then [dataset],
    [train] (the jobs' length: train's steps, budget_seconds, threads), [scoring] (PROTOCOL
    updated by `protocol`, without its baselines) and [[methods]]: `methods` (a list of
    tables) or else our compact NeRF named compact-nerf with train's other keys as its
    settings and each of the protocol's baselines; one [[scenes]] table per entry."""
    head = {"name": name, "version": version} | ({"description": description} if description else {})
    scoring = PROTOCOL | (protocol or {})
    if methods is None:
        settings = {key: value for key, value in train.items() if key not in LENGTH and key != "model"}
        methods = [{"name": "compact-nerf", "method": train.get("model", "compact")}
                   | ({"settings": settings} if settings else {})]
        methods += [{"method": baseline} for baseline in scoring.get("baselines", [])]
    text = _table(head)
    text += "\n[dataset]\n" + _table(dataset)
    text += "\n[train]\n" + _table({key: value for key, value in train.items() if key in LENGTH})
    text += "\n[scoring]\n" + _table({key: value for key, value in scoring.items() if key != "baselines"})
    for method in methods:
        text += "\n[[methods]]\n" + _table(method)
    for entry in scenes:
        text += "\n[[scenes]]\n" + _table(entry)
    return text


def one_scene_suite(root):
    """(suite TOML, a generated one-dataset 16 px suite folder root/S, predictions: the
    dataset's own test PNGs under root/pred/primitives) for the state and link tests."""
    import shutil

    from nerfgauge.cli import main

    toml = root / "one.toml"
    toml.write_text(suite_toml("one", {"width": 16, "height": 16, "views": 4, "val_views": 0, "test_views": 2,
                                       "spp": 2}, {"steps": 4}, scenes=({"scene": "primitives", "seed": 0},)))
    out = root / "S"
    assert main(["suite", "generate", str(toml), "--out", str(out)]) == 0
    pred = root / "pred" / "primitives"
    pred.mkdir(parents=True)
    for png in sorted((out / "datasets" / "primitives" / "test").glob("r_???.png")):
        shutil.copy(png, pred / png.name)
    return toml, out, pred.parent
