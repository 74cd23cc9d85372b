"""Docs that cannot rot (issue 51): what README.md and docs/ show still runs and still exists.

- Every `nerfgauge ...` command the docs show (in bash blocks and in inline code) names a
  command that exists, and every `--flag` beside it exists on that command; a `--flag` named
  alone must exist on some command (or be another tool's: FOREIGN_FLAGS in the hook). The
  flags come from the same walk of `nerfgauge.cli.build_parser()` that writes the site's
  command reference (docs/hooks/reference.py), so a renamed flag fails here and changes
  that page.
- Every bash block of README.md and docs/tutorials/ is marked, on the line before it:
  `<!-- test: run -->` runs it here, `<!-- test: skip (REASON) -->` says why it cannot
  (another tool, a GPU, the test suite itself). The run blocks of a page run in order, in one
  fresh folder (a tutorial's later steps use its earlier outputs), at small sizes: each
  `nerfgauge` line gets SMALL's values for the size flags its command has (a time budget
  becomes SMALL's step count); `<!-- test: run --flag VALUE -->` overrides SMALL for that
  block, `<!-- test: run, setup: COMMAND -->` runs COMMAND first (what the reader is assumed
  to have, e.g. their own method's renders). A `nerfgauge` line must exit 0 (`check`: 0, 1
  or 4, its verdicts); any other line 0. `<!-- test: same as PAGE -->`: every line of the
  block is a line of PAGE's run blocks (checked), so PAGE's run covers it and it does not
  run twice (README's suite commands are the suite tutorial's, each a minute of CI).
- Every relative link in README.md and docs/ points at a file that exists (mkdocs
  --strict checks the site's own links and anchors too: `tox -e docs`).
- The architecture page's layer table is generated from tests/test_layers.py (checked here:
  the marker is there, and the generator reproduces the test's edges).
"""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPOSITORY = Path(__file__).resolve().parent.parent
DOCS = REPOSITORY / "docs"
LOG = DOCS / "log"  # the lab notebook: dated studies of earlier code, kept as written
RUN_PAGES = [REPOSITORY / "README.md", *sorted((DOCS / "tutorials").glob("*.md"))]

# Small sizes for the run blocks: (flag, value); a command gets those it has.
SMALL = {"--res": "24", "--views": "6", "--val-views": "1", "--test-views": "2", "--spp": "4",
         "--steps": "20", "--seeds": "2"}
SIZE_REPLACED = {"--budget-seconds": "--steps"}  # a time budget becomes a step count
VERDICTS = {("check",): {0, 1, 4}}  # exit codes that are answers, not failures

LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _reference():
    spec = importlib.util.spec_from_file_location("docs_reference", DOCS / "hooks" / "reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


REFERENCE = _reference()
FENCE = REFERENCE.FENCE


def _commands() -> dict:
    from nerfgauge.cli import build_parser

    return {path: REFERENCE.flags(parser) for path, parser in REFERENCE.commands(build_parser()).items()}


COMMANDS = _commands()


def doc_pages(include_log: bool = False) -> list[Path]:
    pages = [REPOSITORY / "README.md", REPOSITORY / "BENCHMARKS.md", *sorted(DOCS.rglob("*.md"))]
    return [p for p in pages if include_log or LOG not in p.parents]


def blocks(page: Path) -> list[dict]:
    """Fenced code blocks: info string, body, and the test marker before it (or None)."""
    return [{"info": m["info"].strip(), "body": m["body"], "marker": m["what"],
             "line": page.read_text()[:m.start("body")].count("\n")}
            for m in FENCE.finditer(page.read_text())]


command_lines = REFERENCE.command_lines
_tokens = REFERENCE.tokens_of
flags_named = REFERENCE.flags_named


def command_of(tokens: list[str]):
    return REFERENCE.command_of(tokens, COMMANDS)


def test_every_command_and_flag_the_docs_name_exists():
    wrong, checked = [], 0
    for page in doc_pages():
        problems, count = REFERENCE.stale(page.read_text(), COMMANDS)
        wrong += [f"{page.relative_to(REPOSITORY)}: {problem}" for problem in problems]
        checked += count
    assert not wrong, "the docs name commands or flags the CLI does not have:\n" + "\n".join(sorted(set(wrong)))
    assert checked >= 100  # the docs' commands were found (README and docs/ show well over 100)


def test_the_flag_check_can_fail():
    page = "Train: `nerfgauge train data --steps 5 --no-such-flag 3`; alone: `--frobnicate`.\n"
    assert REFERENCE.stale(page, COMMANDS) == (["`nerfgauge train data --steps 5 --no-such-flag 3`: `nerfgauge train` "
                                                "has no --no-such-flag", "`--frobnicate`: no command has --frobnicate"], 1)
    tokens = _tokens("nerfgauge train data/prim --out runs/prim --budget-seconds 120 --no-such-flag 3")
    path, rest = command_of(tokens)
    assert path == ("train",) and [f for f in flags_named(rest) if f not in COMMANDS[path]] == ["--no-such-flag"]
    assert command_of(_tokens("nerfgauge suite run smoke --seeds 3"))[0] == ("suite", "run")
    assert command_of(_tokens("nerfgauge frobnicate data"))[0] is None


def test_every_bash_block_of_the_readme_and_tutorials_is_run_or_says_why_not():
    unmarked = [f"{page.relative_to(REPOSITORY)}:{block['line']}" for page in RUN_PAGES for block in blocks(page)
                if block["info"].split()[:1] == ["bash"]
                and not (block["marker"] and re.match(r"run\b|skip \(.+\)$|same as \S+$", block["marker"]))]
    assert not unmarked, ("bash blocks without `<!-- test: run -->`, `<!-- test: skip (REASON) -->` or "
                          "`<!-- test: same as PAGE -->` on the line before:\n" + "\n".join(unmarked))
    assert sum(1 for page in RUN_PAGES for b in blocks(page) if (b["marker"] or "").startswith("run")) >= 10


def small(line: str, overrides: dict) -> str:
    """A `nerfgauge` line at small sizes: SMALL's value for every size flag its command has
    (`--seeds` only where the line gives it; a train's or run's time budget becomes `--steps`),
    then the block's overrides."""
    tokens = _tokens(line)
    path, _ = command_of(tokens)
    if tokens[:1] != ["nerfgauge"] or path is None:
        return line
    have = COMMANDS[path]
    given = {t.split("=", 1)[0] for t in tokens}
    sizes = {flag: value for flag, value in SMALL.items() if flag in have
             and (flag != "--seeds" or flag in given) and (flag != "--steps" or path in {("train",), ("run",)})}
    sizes.update({flag: value for flag, value in overrides.items() if flag in have})
    out, skip = [], False
    for token in tokens:
        flag = token.split("=", 1)[0]
        if skip:
            skip = False
        elif flag in sizes or flag in SIZE_REPLACED:
            skip = "=" not in token  # drop the flag and its value
        else:
            out.append(token)
    for flag, value in sizes.items():
        out += [flag, value]
    return " ".join(t if re.fullmatch(r"[\w@%+=:,./*?-]+", t) else shlex.quote(t) for t in out)


def test_small_sizes_rewrite_only_what_the_command_has():
    assert small("nerfgauge generate primitives --out data/prim --views 24", {}) == \
        "nerfgauge generate primitives --out data/prim --res 24 --views 6 --val-views 1 --test-views 2 --spp 4"
    assert small("nerfgauge train data/prim --out runs/prim --budget-seconds 120", {}) == \
        "nerfgauge train data/prim --out runs/prim --steps 20"
    assert small("nerfgauge run primitives --out ci --res 64 --steps 400 --seeds 10", {"--seeds": "3"}) == \
        "nerfgauge run primitives --out ci --res 24 --views 6 --val-views 1 --test-views 2 --spp 4 --steps 20 --seeds 3"
    assert small("nerfgauge check ci/eval/compact/seed-*/metrics.json --thresholds t.toml", {}) == \
        "nerfgauge check ci/eval/compact/seed-*/metrics.json --thresholds t.toml"


def not_run_elsewhere(block: dict, page_named: str) -> list[str]:
    """The lines of `block` (marked `same as page_named`) that no run block of that page has;
    a page that is not one the run test runs leaves every line uncovered."""
    page = REPOSITORY / page_named
    if page not in RUN_PAGES:
        return command_lines(block["body"])
    covered = {line for other in blocks(page) if (other["marker"] or "").startswith("run")
               for line in command_lines(other["body"])}
    return [line for line in command_lines(block["body"]) if line not in covered]


def test_a_block_the_same_as_another_pages_is_run_there():
    same = [(page, block, block["marker"][len("same as "):]) for page in RUN_PAGES for block in blocks(page)
            if (block["marker"] or "").startswith("same as ")]
    missing = [f"{page.relative_to(REPOSITORY)}:{block['line']}: `{line}` is in no run block of {named}"
               for page, block, named in same for line in not_run_elsewhere(block, named)]
    assert not missing, "\n".join(missing)
    # and the check can fail: a line the named page does not run, a page the test does not run
    assert not_run_elsewhere({"body": "nerfgauge suite run smoke --seeds 4"}, "docs/tutorials/suite-on-dask.md")
    assert not_run_elsewhere({"body": "nerfgauge suite list"}, "BENCHMARKS.md") == ["nerfgauge suite list"]


def _marker_options(marker: str) -> tuple[dict, list[str]]:
    """(size overrides, setup commands) of `run --flag V ..., setup: CMD`."""
    head, *setups = re.split(r",\s*setup:\s*", marker[len("run"):])
    tokens = _tokens(head.strip(" ,"))
    return dict(zip(tokens[::2], tokens[1::2])), setups


@pytest.mark.slow
@pytest.mark.parametrize("page", RUN_PAGES, ids=[p.stem for p in RUN_PAGES])
def test_the_run_blocks_run_at_small_sizes(page, tmp_path):
    runs = [b for b in blocks(page) if (b["marker"] or "").startswith("run")]
    if not runs:
        pytest.skip(f"{page.name} has no run blocks")
    if any("--scheduler" in b["body"] for b in runs) and importlib.util.find_spec("distributed") is None:
        pytest.skip("a block uses --scheduler: needs the dask extra (pip install 'nerfgauge[dask]')")
    if "nerfgauge sfm" in page.read_text() and importlib.util.find_spec("pycolmap") is None:
        pytest.skip("nerfgauge sfm needs pycolmap (pip install 'nerfgauge[colmap]')")
    shutil.copy(REPOSITORY / "thresholds.toml", tmp_path)  # the reader is in a clone
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    for block in runs:
        overrides, setups = _marker_options(block["marker"])
        for line in [*setups, *command_lines(block["body"])]:
            command = small(line.split(" #", 1)[0].strip(), overrides)
            done = subprocess.run(["bash", "-c", command], cwd=tmp_path, env=env, capture_output=True, text=True,
                                  timeout=900)
            path = command_of(_tokens(command))[0] if command.startswith("nerfgauge") else None
            allowed = VERDICTS.get(path, {0})
            assert done.returncode in allowed, (f"{page.name}:{block['line']}: `{command}` exited {done.returncode}:\n"
                                                f"{done.stderr[-2000:]}")


def test_relative_links_point_at_files_that_exist():
    broken = []
    for page in doc_pages(include_log=True):
        for target in LINK.findall(FENCE.sub("", page.read_text())):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            path = (page.parent / target.split("#", 1)[0]).resolve()
            if not path.exists():
                broken.append(f"{page.relative_to(REPOSITORY)}: {target}")
    assert not broken, "links to files that do not exist:\n" + "\n".join(broken)


def test_readme_is_a_front_door():
    text = (REPOSITORY / "README.md").read_text()
    assert len(text.encode()) <= 12 * 1024
    first_screen = "\n".join(text.splitlines()[:40])
    assert "tox -e demo" in first_screen and "![" in text
    image = re.search(r"!\[[^\]]*\]\(([^)]+)\)", text).group(1)
    assert (REPOSITORY / image).stat().st_size < 300 * 1024
    assert len((REPOSITORY / "BENCHMARKS.md").read_bytes()) <= 15 * 1024


def test_the_architecture_page_shows_the_layer_test_s_own_table():
    assert "<!-- generated: layers -->" in (DOCS / "architecture.md").read_text()
    table = REFERENCE.layers_markdown()
    spec = importlib.util.spec_from_file_location("test_layers_for_docs", REPOSITORY / "tests" / "test_layers.py")
    layers = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(layers)
    for (importer, imported) in layers.ALLOWED:
        assert f"| `{importer}` | `{imported}` |" in table
    for group in layers.MAY_IMPORT:
        assert f"| `{group}` |" in table


def test_the_cli_reference_lists_every_command_and_flag():
    from nerfgauge.cli import build_parser

    page = REFERENCE.cli_markdown(build_parser())
    for path, flags in COMMANDS.items():
        assert f"## nerfgauge {' '.join(path)}\n" in page
        for flag in flags - {"-h", "--help"}:
            assert f"`{flag}" in page, (path, flag)


@pytest.mark.slow  # generates a 32-px dataset and trains 20 steps
def test_the_readme_python_block_runs(tmp_path, monkeypatch, capsys):
    (block,) = [b for b in blocks(REPOSITORY / "README.md") if b["info"] == "python"]
    monkeypatch.chdir(tmp_path)
    exec(compile(block["body"], str(REPOSITORY / "README.md"), "exec"), {"__name__": "__main__"})
    assert re.fullmatch(r"PSNR -?\d+\.\d dB\n", capsys.readouterr().out)
