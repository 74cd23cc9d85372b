"""`nerfgauge methods`: every method the harness can run (the built-in ones and the specs
nerfgauge ships for other tools' methods), with what it needs from a dataset, what its
renders hold and, for another tool's method, how its environment is installed;
`nerfgauge methods install METHOD [--env DIR]` builds that environment
(nerfgauge.methods.install)."""

from __future__ import annotations

import json

from nerfgauge.core.errors import InputError
from nerfgauge.methods.builtin import builtin_methods
from nerfgauge.methods.external import ExternalMethod
from nerfgauge.methods.install import install_environment, where_it_looks
from nerfgauge.methods.registry import resolve, shipped_specs

INSTALL = "install"  # the verb: `nerfgauge methods install METHOD`


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "methods", help="list the methods the harness runs, with what each needs and produces; install one's tool",
        description="The methods nerfgauge runs through one interface (train on a dataset into a run folder, "
                    "render a split): its own, and other tools' methods from the specs it ships (nerfacto, "
                    "splatfacto, gsplat, nerfbaselines). Name one in a suite's [[methods]] or on the command line; "
                    "a Python class of yours as module:Class, another tool's method as a spec .toml. "
                    "`nerfgauge methods install METHOD [--env DIR]` builds the environment another tool's method "
                    "runs in, from its spec's install lines.")
    parser.add_argument("specs", nargs="*", metavar="METHOD",
                        help="describe these (names, module:Class or spec files) instead of every method; "
                             "or `install METHOD`")
    parser.add_argument("--env", metavar="DIR",
                        help="with install: build the environment here (default: where the method looks for it, "
                             "$NERFGAUGE_ENV_<NAME> or ~/.local/share/nerfgauge/envs/<name>)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.set_defaults(func=_run)


def _run(args) -> int:
    if args.specs[:1] == [INSTALL]:
        return _install(args)
    if args.env is not None:
        raise InputError("--env is for `nerfgauge methods install METHOD --env DIR`")
    if args.specs:
        methods = [resolve(spec) for spec in args.specs]
    else:
        methods = [*builtin_methods().values(), *(resolve(name) for name in shipped_specs())]
    rows = [method.describe() for method in methods]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    width = max(len(row["name"]) for row in rows)
    for row in rows:
        needs = ", ".join(row["needs"]) or "-"
        kind = "trains" if row["learned"] else "no training"
        print(f"{row['name']:<{width}}  {row['summary']}")
        print(f"{'':<{width}}  {kind}; needs: {needs}; produces: {', '.join(row['produces'])}")
        if row.get("install"):
            print(f"{'':<{width}}  install: nerfgauge methods install {row['name']}   (environment: {row['environment']})")
            for line in row["install"]:
                print(f"{'':<{width}}    {line}")
    return 0


def _install(args) -> int:
    if len(args.specs) != 2:
        raise InputError("give one method: nerfgauge methods install METHOD [--env DIR]")
    method = resolve(args.specs[1])
    if not isinstance(method, ExternalMethod):
        raise InputError(f"method {method.name} is nerfgauge's own: it has no environment to install")
    folder, built = install_environment(method, args.env)
    print(f"{method.name}: environment {'installed' if built else 'already installed'}: {folder}")
    note = where_it_looks(method, folder)
    if note:
        print(note)
    return 0
