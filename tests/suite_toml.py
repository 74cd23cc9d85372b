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
    return repr(value)


def _table(values: dict) -> str:
    return "".join(f"{key} = {_value(value)}\n" for key, value in values.items())


def suite_toml(name: str, dataset: dict, train: dict, scenes=TWO_SCENES, *, version: int = 1,
               description: str | None = None, protocol: dict | None = None) -> str:
    """The TOML of a suite: top-level name, version (and description), then [dataset],
    [train], [protocol] (PROTOCOL updated by `protocol`) and one [[scenes]] table per entry."""
    head = {"name": name, "version": version} | ({"description": description} if description else {})
    text = _table(head)
    text += "\n[dataset]\n" + _table(dataset)
    text += "\n[train]\n" + _table(train)
    text += "\n[protocol]\n" + _table(PROTOCOL | (protocol or {}))
    for entry in scenes:
        text += "\n[[scenes]]\n" + _table(entry)
    return text
