"""`nerfgauge methods`: every method the harness can run, with what it needs from a dataset
and what its renders hold."""

from __future__ import annotations

import json

from nerfgauge.methods.builtin import builtin_methods
from nerfgauge.methods.registry import resolve


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "methods", help="list the methods the harness runs, with what each needs and produces",
        description="The methods nerfgauge runs through one interface (train on a dataset into a run folder, "
                    "render a split). Name one in a suite's [[methods]] or on the command line; a Python class "
                    "of yours as module:Class, another tool's method as a spec .toml.")
    parser.add_argument("specs", nargs="*", metavar="METHOD",
                        help="describe these (names, module:Class or spec files) instead of the built-in ones")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.set_defaults(func=_run)


def _run(args) -> int:
    methods = [resolve(spec) for spec in args.specs] if args.specs else list(builtin_methods().values())
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
    return 0
