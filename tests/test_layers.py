"""The import graph keeps the layers (docs/architecture.md): no cycles, and every import
points down.

    top:       nerfgauge.cli  >  nerfgauge.api  >  nerfgauge.run, nerfgauge.orchestrate  >  nerfgauge.methods
    stages:    nerfgauge.generate  >  nerfgauge.scenes;  nerfgauge.nerf;  nerfgauge.eval;  nerfgauge.splat
    bottom:    nerfgauge.core

`core` imports only `core`; `scenes` imports `core`; `generate` imports `scenes` and `core`;
`nerf`, `eval` and `splat` import `core` only, except the few edges in ALLOWED below (each with its
reason); no stage imports the top layer (the CLI, the API, `run`, orchestration).

The graph is read from the source with `ast`, with pyproject's folder mapping applied
(the folder eval/ is the package nerfgauge.eval, ...). Imports inside functions count as
edges like those at module level: a cycle hidden in a function is still a cycle. Imports
inside functions are kept for heavy or optional packages only (torch, mitsuba, drjit,
trimesh, matplotlib, dask, ...: `nerfgauge --help` and `import nerfgauge.api` stay fast),
and each says why in a comment on its line.
"""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parent.parent

STAGES = ("nerfgauge.scenes", "nerfgauge.generate", "nerfgauge.nerf", "nerfgauge.eval", "nerfgauge.splat")
CORE = ("nerfgauge.core",)
# What each group of modules may import besides itself (a module's group: the longest
# name here that it is or is inside of).
MAY_IMPORT = {
    "nerfgauge.core": (),
    "nerfgauge.scenes": CORE,
    "nerfgauge.generate": ("nerfgauge.scenes", *CORE),
    "nerfgauge.nerf": CORE,
    "nerfgauge.eval": CORE,
    "nerfgauge.splat": CORE,
    "nerfgauge.methods": (*STAGES, *CORE),  # methods run the stages (nerf and splat train, methods.baselines renders)
    "nerfgauge.orchestrate": ("nerfgauge.methods", *STAGES, *CORE),
    "nerfgauge.run": ("nerfgauge.methods", *STAGES, *CORE),
    "nerfgauge.api": ("nerfgauge.run", "nerfgauge.methods", *STAGES, *CORE),
    "nerfgauge.cli": ("nerfgauge.run", "nerfgauge.orchestrate", "nerfgauge.methods", *STAGES, *CORE),
    "nerfgauge": ("nerfgauge.api", *CORE),  # the package's lazy exports (nerfgauge/__init__.py)
}
TOP = ("nerfgauge.cli", "nerfgauge.api", "nerfgauge.run", "nerfgauge.orchestrate", "nerfgauge.methods")

# Edges against the layer order that are there by design: (importer, imported): reason.
ALLOWED = {
    ("nerfgauge.eval.normals", "nerfgauge.nerf.rendering"):
        "scoring a field's normals renders its depth through nerf's chunked renderer (a trained field is the input)",
    ("nerfgauge.eval.commands", "nerfgauge.nerf.checkpoint"):
        "`nerfgauge geometry --run RUN` loads the run's model to score its normals",
    ("nerfgauge.eval.commands", "nerfgauge.nerf.runs"):
        "`nerfgauge geometry --run RUN` reads the run with the dataset it was trained on, checked against its record",
    ("nerfgauge.eval.check", "nerfgauge.scenes.registry"):
        "the gate refuses a scene name no recipe has (the registry lists the recipes)",
    ("nerfgauge.nerf.commands", "nerfgauge.splat.commands"):
        "one `train` and one `render` command serve every model: `--model splat` and a splatting RUN go to "
        "splat's runners, whose flags are defined beside SplatConfig",
}


def module_files() -> dict[str, Path]:
    """{module name: file} over every package folder pyproject maps (nerfgauge.eval -> eval/)."""
    setuptools = tomllib.loads((REPOSITORY / "pyproject.toml").read_text())["tool"]["setuptools"]
    folders = {"nerfgauge": "nerfgauge", **setuptools.get("package-dir", {})}
    modules = {}
    for package, folder in folders.items():
        for path in sorted((REPOSITORY / folder).rglob("*.py")):
            parts = [p for p in path.relative_to(REPOSITORY / folder).with_suffix("").parts if p != "__init__"]
            name = ".".join([package, *parts])
            mapped_elsewhere = any(name == other or name.startswith(other + ".")
                                   for other, other_folder in folders.items()
                                   if other != package and other.startswith(package + ".")
                                   and Path(folder, *other[len(package) + 1:].split(".")) != Path(other_folder))
            if not mapped_elsewhere:
                modules[name] = path
    return modules


def imports_of(name: str, path: Path, modules: dict) -> list[tuple[str, int, bool]]:
    """(imported project module, line, inside a function) for every import in the file."""
    found = []

    def visit(node, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inside = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                targets = [alias.name for alias in child.names]
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                    package = package[:len(package) - (child.level - 1)]
                    base = ".".join(package + ([base] if base else []))
                targets = [base] + [f"{base}.{alias.name}" for alias in child.names]
            else:
                visit(child, inside)
                continue
            for target in targets:
                if target in modules and target != name:
                    found.append((target, child.lineno, inside))
    visit(ast.parse(path.read_text(), str(path)), False)
    return found


def graph() -> tuple[dict, dict]:
    """({module: {imported modules}}, {(module, imported): [(line, inside a function)]})."""
    modules = module_files()
    edges, where = {name: set() for name in modules}, {}
    for name, path in modules.items():
        for target, line, inside in imports_of(name, path, modules):
            if target.startswith(name + ".") or name.startswith(target + "."):
                continue  # a package and its own submodules
            edges[name].add(target)
            where.setdefault((name, target), []).append((line, inside))
    return edges, where


def group(module: str) -> str:
    return next(g for g in sorted(MAY_IMPORT, key=len, reverse=True) if module == g or module.startswith(g + "."))


def cycles(edges: dict) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), each as a cycle path."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def strong(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges[v]):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(cycle_path(sorted(component), edges))

    for v in sorted(edges):
        if v not in index:
            strong(v)
    return found


def cycle_path(component: list, edges: dict) -> list:
    """One cycle through the component's first module: a -> b -> ... -> a."""
    members, start = set(component), component[0]
    paths, seen = [[start]], {start}
    while paths:
        path = paths.pop(0)
        for w in sorted(edges[path[-1]] & members):
            if w == start:
                return path + [start]
            if w not in seen:
                seen.add(w)
                paths.append(path + [w])
    return component


def describe(edge, where) -> str:
    lines = ", ".join(f"line {line}{' (in a function)' if inside else ''}" for line, inside in where[edge])
    return f"{edge[0]} -> {edge[1]} ({lines})"


def test_the_import_graph_has_no_cycle():
    edges, where = graph()
    found = cycles(edges)
    assert not found, "import cycles (function-local imports count):\n" + "\n".join(
        " -> ".join(cycle) + "\n    " + "\n    ".join(describe((a, b), where) for a, b in zip(cycle, cycle[1:]))
        for cycle in found)


def test_every_import_points_down_the_layers():
    edges, where = graph()
    against = sorted(describe((name, target), where) for name, targets in edges.items() for target in targets
                     if group(target) not in (group(name), *MAY_IMPORT[group(name)]) and (name, target) not in ALLOWED)
    assert not against, ("imports against the layer order (move the name to the layer that owns it, or name the "
                         "edge in ALLOWED with its reason):\n" + "\n".join(against))


def test_the_allowed_edges_are_still_there():
    edges, _ = graph()
    stale = [f"{a} -> {b}" for a, b in ALLOWED if b not in edges.get(a, ())]
    assert not stale, f"ALLOWED names edges the code no longer has: {stale}"


def test_no_stage_imports_the_top_layer():
    edges, where = graph()
    up = sorted(describe((name, target), where) for name, targets in edges.items() for target in targets
                if group(name) in (*STAGES, *CORE) and group(target) in TOP)
    assert not up, "stages importing the CLI, the API, run or orchestration:\n" + "\n".join(up)


def function_local_imports(path: Path) -> list[tuple[int, str]]:
    """(line, text) of every import statement inside a function of the file (any package)."""
    lines, found = path.read_text().splitlines(), []

    def visit(node, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inside = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if inside and isinstance(child, (ast.Import, ast.ImportFrom)):
                found.append((child.lineno, lines[child.lineno - 1]))
            visit(child, inside)
    visit(ast.parse(path.read_text(), str(path)), False)
    return found


def test_function_local_imports_say_why():
    silent = sorted(f"{path.relative_to(REPOSITORY)}:{line}: {text.strip()}"
                    for path in module_files().values() for line, text in function_local_imports(path)
                    if "#" not in text)
    assert not silent, ("imports inside functions with no comment saying why (which heavy package they keep "
                        "off the import path, e.g. `# torch: only when ...`); else import at module level:\n"
                        + "\n".join(silent))
