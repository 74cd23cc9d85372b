"""Pages written from the code at build time (mkdocs hook), so they cannot drift from it.

A page holds a marker where generated Markdown goes:

- `<!-- generated: cli -->`: every command and flag, walked from `nerfgauge.cli.build_parser()`
  (a renamed flag changes the page; tests/test_docs.py checks every flag the docs name
  against the same walk);
- `<!-- generated: exit-codes -->`: the exit-code contract, cli.py's docstring;
- `<!-- generated: layers -->`: which layer may import which, and the edges allowed against
  the order with their reasons, read from tests/test_layers.py (the test that enforces them).

And every page is checked as it is built: a `nerfgauge ...` command it shows (in a bash
block or inline code) must exist with every `--flag` beside it, and a `--flag` named alone
must exist on some command (or be another tool's, FOREIGN_FLAGS); else a warning, which
`mkdocs build --strict` turns into a failed build. tests/test_docs.py runs the same check.

mkdocs.yml names this file under `hooks:`; tests/test_docs.py imports it by path.
"""

from __future__ import annotations

import argparse
import html
import importlib.util
import logging
import os
import re
import shlex
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


# Flags of other tools that the docs name in passing (pip, dask, nerfstudio, NerfBaselines, evo ...).
FOREIGN_FLAGS = {"--no-deps", "--nthreads", "--nworkers", "--port", "--depth-unit-scale-factor", "--load-config",
                 "--output-path", "--split", "--data", "--method", "--output", "--checkpoint", "--durations",
                 "--dist", "--headless", "--remote-debugging-pipe", "--fuzz-seed", "--strict",
                 "--disable-pip-version-check", "--align", "--correct_scale",
                 # the method specs' pages (docs/how-to/methods/): pip, git, ns-train, simple_trainer.py
                 "--constraint", "--depth", "--branch", "--vis", "--test-every", "--no-normalize-world-space"}
FENCE = re.compile(r"(?P<marker><!--\s*test:\s*(?P<what>[^>]*?)\s*-->\s*\n)?```(?P<info>[^\n]*)\n(?P<body>.*?)\n```",
                   re.S)
INLINE = re.compile(r"(?<!`)`([^`\n]+)`(?!`)")


def command_lines(body: str) -> list[str]:
    """A shell block's logical lines (continuations joined), comments dropped."""
    lines, pending = [], ""
    for line in body.splitlines():
        line = pending + line.strip()
        if line.endswith("\\"):
            pending = line[:-1] + " "
            continue
        pending = ""
        if line and not line.startswith("#"):
            lines.append(line)
    return lines


def tokens_of(line: str) -> list[str]:
    line = line.split(" #", 1)[0]
    try:
        return shlex.split(line)
    except ValueError:
        return line.split()


def command_of(tokens: list[str], known: dict):
    """(command path, the tokens after it) of a `nerfgauge ...` token list; path None if unknown."""
    words = [t for t in tokens[1:] if not t.startswith("-")]
    for length in (2, 1):
        path = tuple(words[:length])
        if path in known:
            return path, tokens[1 + tokens[1:].index(path[-1]) + 1:]
    return None, tokens[1:]


def flags_named(tokens: list[str]) -> list[str]:
    found = []
    for token in tokens:
        for part in re.split(r"[\[\]|()]", token):
            if re.fullmatch(r"--[a-z][a-z0-9-]*(=.*)?", part):
                found.append(part.split("=", 1)[0])
    return found


def shown_commands(markdown: str) -> list[str]:
    """Every command line of the page's shell blocks and every inline code span."""
    shown = [line for match in FENCE.finditer(markdown) if match["info"].split()[:1] in (["bash"], ["sh"], ["console"])
             for line in command_lines(match["body"])]
    return shown + INLINE.findall(FENCE.sub("", markdown))


def stale(markdown: str, known: dict) -> tuple[list[str], int]:
    """(what the page names that the CLI does not have, how many nerfgauge commands it shows).
    known: {command path: its flags} (commands() and flags())."""
    every = set().union(*known.values())
    wrong, checked = [], 0
    for text in shown_commands(markdown):
        tokens = tokens_of(text)
        if tokens[:1] == ["nerfgauge"] and len(tokens) > 1:
            checked += 1
            path, rest = command_of(tokens, known)
            if path is None:
                if tokens[1] not in {"COMMAND", "--help", "-h"}:
                    wrong.append(f"`{text}`: no command `nerfgauge {' '.join(tokens[1:3])}`")
                continue
            wrong += [f"`{text}`: `nerfgauge {' '.join(path)}` has no {flag}"
                      for flag in flags_named(rest) if flag not in known[path]]
        else:
            wrong += [f"`{text}`: no command has {flag}" for flag in flags_named(tokens)
                      if flag not in every | FOREIGN_FLAGS]
    return wrong, checked


_KNOWN = {}


def known_commands() -> dict:
    """{command path: its flags}, from nerfgauge.cli.build_parser() (once a build)."""
    if not _KNOWN:
        from nerfgauge.cli import build_parser  # the package: only when the site is built or tested

        _KNOWN.update({path: flags(parser) for path, parser in commands(build_parser()).items()})
    return _KNOWN


def on_page_markdown(markdown: str, page, config, files) -> str:
    """mkdocs: warn about commands and flags the CLI does not have (the lab notebook, dated
    studies of earlier code, excepted), then replace each marker with its generated Markdown."""
    if not page.file.src_uri.startswith("log/"):
        for problem in stale(markdown, known_commands())[0]:
            logging.getLogger("mkdocs.plugins.nerfgauge").warning(f"{page.file.src_uri}: {problem}")
    return MARKER.sub(lambda match: GENERATORS[match.group(1)](), markdown)
