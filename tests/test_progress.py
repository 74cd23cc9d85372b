"""core.progress: a bar on a terminal, a few whole lines in a log (issue 51)."""

import io

from nerfgauge.core.progress import EVERY_FRACTION, PlainProgress, progress
from tqdm import tqdm


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_a_log_gets_one_whole_line_each_tenth_and_no_carriage_return():
    log = io.StringIO()
    bar = progress(total=1000, desc="generate", unit="view", stream=log)
    assert isinstance(bar, PlainProgress)
    for _ in range(1000):
        bar.update(1)
    bar.close()
    text = log.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert len(lines) == 1 + round(1 / EVERY_FRACTION)  # 0%, 10%, 20%, ..., 100%; close adds nothing new
    assert lines[0].startswith("generate:   0%") and "0/1000" in lines[0]
    assert lines[-1].startswith("generate: 100%") and "1000/1000" in lines[-1]
    assert all(line.startswith("generate:") for line in lines)


def test_a_log_line_also_comes_after_the_time_step_when_progress_is_slow():
    now = [0.0]
    log = io.StringIO()
    bar = PlainProgress(total=10_000, desc="train", unit="step", stream=log, every_seconds=30, clock=lambda: now[0])
    for _ in range(5):  # 5 steps (0.05%), 31 s apart: a line each time, after the first
        now[0] += 31
        bar.update(1)
    assert len(log.getvalue().splitlines()) == 1 + 5
    bar.close()  # nothing new to say
    assert len(log.getvalue().splitlines()) == 1 + 5


def test_an_unknown_total_and_an_iterable_and_the_postfix():
    log = io.StringIO()
    items = list(progress(iter(range(3)), desc="evaluate", unit="frame", stream=log))
    assert items == [0, 1, 2]
    first, last = log.getvalue().splitlines()  # unknown total: where it starts, then where it ends
    assert first.startswith("evaluate: 0frame") and last.startswith("evaluate: 3frame")
    log = io.StringIO()
    bar = progress(total=4, desc="train", stream=log)
    bar.set_postfix(psnr="31.20", refresh=False)
    bar.update(4)
    bar.close()
    assert "psnr=31.20" in log.getvalue()


def test_a_terminal_gets_tqdm_and_disabled_prints_nothing():
    terminal = Terminal()
    bar = progress(total=3, desc="render", stream=terminal)
    assert isinstance(bar, tqdm) and not isinstance(bar, PlainProgress)
    bar.update(3)
    bar.close()
    assert "\r" in terminal.getvalue()  # tqdm redraws in place on a terminal
    log = io.StringIO()
    for enabled in (False, None):  # None: on a terminal only
        bar = progress(total=3, stream=log, enabled=enabled)
        bar.update(3)
        bar.close()
    assert log.getvalue() == ""
