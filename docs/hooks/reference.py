"""Pages written from the code at build time (mkdocs hook), so they cannot drift from it.

A page holds a marker where generated Markdown goes:

- `<!-- generated: cli -->`: every command and flag, walked from `nerfgauge.cli.build_parser()`
  (a renamed flag changes the page; tests/test_docs.py checks every flag the docs name
  against the same walk);
- `<!-- generated: exit-codes -->`: the exit-code contract, cli.py's docstring;
- `<!-- generated: layers -->`: which layer may import which, and the edges allowed against
  the order with their reasons, read from tests/test_layers.py (the test that enforces them).

mkdocs.yml names this file under `hooks:`; tests/test_docs.py imports it by path.
"""

from __future__ import annotations

import argparse
import html
import importlib.util
import os
import re
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[2]
MARKER = re.compile(r"<!-- generated: ([a-z-]+) -->")
USAGE_COLUMNS = "72"  # argparse wraps usage at the terminal width: one width for every build


def commands(parser: argparse.ArgumentParser, path: tuple = ()) -> dict:
    """{("generate",): its parser, ("bench", "train"): ..., ...} for every command that runs
    (a command with subcommands, such as `bench`, is listed through them only)."""
    found = {}
    subparsers = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if path and not subparsers:
        found[path] = parser
    for action in subparsers:
        for name, child in action.choices.items():
            found.update(commands(child, (*path, name)))
    return found


def flags(parser: argparse.ArgumentParser) -> set[str]:
    """Every option string of a command (`--out`, `-o`, `--help`, ...)."""
    return {option for action in parser._actions for option in action.option_strings}


def _help(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    if action.help is None or action.help == argparse.SUPPRESS:
        return ""
    text = parser._get_formatter()._expand_help(action)  # %(default)s and friends, as --help shows them
    return " ".join(text.split())


def _cell(text: str) -> str:
    return html.escape(text, quote=False).replace("|", "\\|")


def _subcommand_help(parser: argparse.ArgumentParser, path: tuple) -> str:
    """The one-line help the parent's listing gives a command."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                if choice.dest == path[0]:
                    return choice.help or ""
    return ""


def cli_markdown(parser: argparse.ArgumentParser | None = None) -> str:
    """The command reference: per command its summary, usage and a table of its arguments."""
    if parser is None:
        from nerfgauge.cli import build_parser  # the package: only when the page is built
        parser = build_parser()
    os.environ["COLUMNS"] = USAGE_COLUMNS
    out = []
    for path, command in commands(parser).items():
        parent = parser
        for part in path[:-1]:
            parent = commands_of(parent)[part]
        summary = _subcommand_help(parent, path[-1:]) or ""
        out += [f"## nerfgauge {' '.join(path)}", ""]
        if summary:
            out += [_cell(summary[:1].upper() + summary[1:]) + ".", ""]
        if command.description and command.description != summary:
            out += [_cell(" ".join(command.description.split())), ""]
        out += ["```text", command.format_usage().strip(), "```", ""]
        groups = [(group.title, group._group_actions) for group in command._action_groups if group._group_actions]
        for title, actions in groups:
            rows = [a for a in actions if not isinstance(a, argparse._HelpAction)]
            if not rows:
                continue
            out += [f"**{_cell(title)}**", "", "| argument | what it does |", "|---|---|"]
            for action in rows:
                choices = "{" + ",".join(map(str, action.choices)) + "}" if action.choices else None
                if action.option_strings:
                    metavar = "" if action.nargs == 0 else " " + str(action.metavar or choices or action.dest.upper())
                    names = ", ".join(f"`{option}{metavar}`" for option in action.option_strings)
                else:
                    names = f"`{action.metavar or action.dest}`" + (f" `{choices}`" if choices else "")
                out.append(f"| {names} | {_cell(_help(command, action))} |")
            out.append("")
    return "\n".join(out)


def commands_of(parser: argparse.ArgumentParser) -> dict:
    return {name: child for action in parser._actions if isinstance(action, argparse._SubParsersAction)
            for name, child in action.choices.items()}


def exit_codes_markdown() -> str:
    """cli.py's docstring from "Exit codes:" on: the contract, written once, in the code."""
    import nerfgauge.cli  # the package: only when the page is built

    doc = nerfgauge.cli.__doc__
    start = doc.index("Exit codes:")
    return doc[start:].strip()


def _test_layers():
    spec = importlib.util.spec_from_file_location("test_layers", REPOSITORY / "tests" / "test_layers.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def layers_markdown() -> str:
    """tests/test_layers.py's MAY_IMPORT and ALLOWED as two tables."""
    layers = _test_layers()
    out = ["| modules in | may import (besides themselves) |", "|---|---|"]
    for group, allowed in layers.MAY_IMPORT.items():
        out.append(f"| `{group}` | {', '.join(f'`{name}`' for name in allowed) or 'nothing of the project'} |")
    out += ["", "Edges against that order, each there by design:", "",
            "| importer | imports | why |", "|---|---|---|"]
    for (importer, imported), reason in layers.ALLOWED.items():
        out.append(f"| `{importer}` | `{imported}` | {_cell(reason)} |")
    return "\n".join(out)


GENERATORS = {"cli": cli_markdown, "exit-codes": exit_codes_markdown, "layers": layers_markdown}


def on_page_markdown(markdown: str, page, config, files) -> str:
    """mkdocs: replace each marker with its generated Markdown."""
    return MARKER.sub(lambda match: GENERATORS[match.group(1)](), markdown)
