"""Finding a method by what a user writes: a built-in name (`compact`, `nearest`, ...), the
name of a spec nerfgauge ships (`nerfacto`, `splatfacto`, ...: nerfgauge/methods/specs/*.toml,
other tools' methods run from their own command lines, nerfgauge.methods.external), a Python
class of theirs as `module:Class`, or a method spec file of theirs (`path/to/spec.toml`).

Every method's name becomes a folder name (suites: results/<method>/), so names are checked
as on entry wherever they come from, and a name is one line of plain text.
"""

from __future__ import annotations

import importlib
import re
from pathlib import Path

from nerfgauge.core.errors import InputError
from nerfgauge.methods.builtin import builtin_methods
from nerfgauge.methods.interface import Method, check_name

CLASS_SPEC = re.compile(r"^[A-Za-z_][A-Za-z0-9_.]*:[A-Za-z_][A-Za-z0-9_]*$")
SPECS_FOLDER = Path(__file__).resolve().parent / "specs"  # package data: the specs nerfgauge ships


def shipped_specs() -> dict:
    """{name: path} of the method specs nerfgauge ships, a spec named by its file name."""
    return {path.stem: path for path in sorted(SPECS_FOLDER.glob("*.toml"))}


def load_class(spec: str, settings: dict | None = None) -> Method:
    """A user's Method subclass named `module:Class`, constructed with `settings` as keyword
    arguments. The module is imported as Python imports any module (it runs its code: name
    only modules you trust, as with any import)."""
    if not CLASS_SPEC.match(spec):
        raise InputError(f"{spec!r} is not a Python class as module:Class")
    module_name, class_name = spec.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        raise InputError(f"cannot import {module_name!r} for method {spec}: {error}") from None
    cls = getattr(module, class_name, None)
    if not isinstance(cls, type) or not issubclass(cls, Method):
        raise InputError(f"{spec} is not a subclass of nerfgauge.methods.Method")
    try:
        method = cls(**(settings or {}))
    except TypeError as error:
        raise InputError(f"{spec} does not take these settings: {error}") from None
    check_name(method.name, f"{spec}'s name")
    return method


def resolve(spec: str, settings: dict | None = None) -> Method:
    """The method `spec` names: a built-in name, a shipped spec's name, `module:Class`, or a
    spec file ending in .toml."""
    if not isinstance(spec, str) or not spec.strip():
        raise InputError(f"a method is a name, module:Class or a .toml spec file, got {spec!r}")
    if spec.endswith(".toml"):
        from nerfgauge.methods.external import load_spec  # only where specs are used

        return load_spec(spec, settings)
    if ":" in spec:
        return load_class(spec, settings)
    methods, shipped = builtin_methods(), shipped_specs()
    if spec not in methods and spec in shipped:
        from nerfgauge.methods.external import load_spec  # only where specs are used

        return load_spec(shipped[spec], settings)
    if spec not in methods:
        raise InputError(f"unknown method {spec!r}; known: {', '.join([*methods, *shipped])} "
                         "(or module:Class, or a method spec .toml)")
    method = methods[spec]
    if settings and not method.learned:
        raise InputError(f"method {spec} has no settings (it does not train)")
    return method
