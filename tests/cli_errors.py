"""The one check every bad-input test makes: `nerfgauge ARGV` exits 2 with exactly one
stderr line, `nerfgauge <command>: error: ...`, and no traceback."""

from __future__ import annotations

from nerfgauge.cli import main


def one_line_exit_2(capsys, argv, *expected) -> str:
    """Run the command in-process; assert exit 2 and one error line holding every `expected`
    text. Returns the line."""
    code = main([str(arg) for arg in argv])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, (code, err)
    assert lines[0].startswith("nerfgauge ") and ": error: " in lines[0], err
    assert all(text in lines[0] for text in expected), err
    return lines[0]
