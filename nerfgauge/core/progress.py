"""Progress bars that read right where they end up: a tqdm bar on a terminal, a few plain
lines in a log.

tqdm redraws its bar with carriage returns several times a second; on a terminal that is one
line that moves, but in a log file (CI, `tox -e demo > log`, a batch job) each redraw stays,
and a demo's log held thousands of them. `progress()` is the one place every bar of the
project is made: when stderr is a terminal it returns tqdm's bar; otherwise a `PlainProgress`
that prints one whole line (tqdm's own text: count, rate, elapsed, postfix) each time
another `EVERY_FRACTION` of the total is done or `EVERY_SECONDS` have passed, and a last one
when it closes.
"""

from __future__ import annotations

import sys
import time

from tqdm import tqdm

EVERY_FRACTION = 0.1  # a log line each 10% of the total ...
EVERY_SECONDS = 30.0  # ... or each 30 s, whichever comes first (a total may be unknown)


def progress(iterable=None, *, total=None, desc: str = "", unit: str = "it", enabled=True, initial=0,
             bar_format=None, leave: bool = True, stream=None):
    """A progress bar over `iterable` (or advanced with `.update(n)` up to `total`).

    enabled: True shows it (a bar on a terminal, plain lines elsewhere); False hides it;
    None shows it on a terminal only (tqdm's `disable=None`). stream: where it writes
    (default stderr). `bar_format` applies to the terminal bar. The returned object has
    tqdm's `update`, `set_postfix`, `close`, `n`, `total`, iteration and `with`."""
    stream = sys.stderr if stream is None else stream
    terminal = _is_terminal(stream)
    if enabled is False or (enabled is None and not terminal):
        return tqdm(iterable, total=total, disable=True)
    if terminal:
        return tqdm(iterable, total=total, desc=desc, unit=unit, initial=initial, bar_format=bar_format,
                    leave=leave, file=stream, dynamic_ncols=True)
    return PlainProgress(iterable, total=total, desc=desc, unit=unit, initial=initial, stream=stream)


def note(message: str) -> None:
    """Print a line of the run's story without tearing a terminal bar (tqdm.write)."""
    tqdm.write(message)


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


class PlainProgress:
    """tqdm's interface, printing whole lines at most every EVERY_FRACTION or EVERY_SECONDS."""

    def __init__(self, iterable=None, *, total=None, desc="", unit="it", initial=0, stream=None,
                 every_fraction: float = EVERY_FRACTION, every_seconds: float = EVERY_SECONDS, clock=time.monotonic):
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        self.iterable, self.total, self.desc, self.unit = iterable, total, desc, unit
        self.n = initial
        self.stream = sys.stderr if stream is None else stream
        self.every_fraction, self.every_seconds, self.clock = every_fraction, every_seconds, clock
        self.postfix = ""
        self.start = self.last_time = clock()
        self.last_fraction = self._fraction()
        self.closed = False
        self.lines = 0  # printed so far
        self.printed_n = None  # the count the last line showed
        self._print()  # where it starts: a log shows the step began (and its total) before any is done

    def _fraction(self):
        return self.n / self.total if self.total else None

    def line(self) -> str:
        """tqdm's text for the current state, as one line without a bar."""
        # a time budget counts float seconds: a tenth is enough to read
        n, total = (round(value, 1) if isinstance(value, float) else value for value in (self.n, self.total))
        return tqdm.format_meter(n, total, self.clock() - self.start, prefix=self.desc, unit=self.unit,
                                 postfix=self.postfix or None, ncols=0)

    def _print(self) -> None:
        self.stream.write(self.line() + "\n")
        self.stream.flush()
        self.lines += 1
        self.printed_n = self.n
        self.last_time, self.last_fraction = self.clock(), self._fraction()

    def update(self, n=1) -> None:
        self.n += n
        fraction = self._fraction()
        if (fraction is not None and fraction - self.last_fraction >= self.every_fraction - 1e-12) \
                or self.clock() - self.last_time >= self.every_seconds:
            self._print()

    def set_postfix(self, ordered_dict=None, refresh: bool = True, **values) -> None:
        values = {**(ordered_dict or {}), **values}
        self.postfix = ", ".join(f"{key}={value}" for key, value in values.items())

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            if self.printed_n != self.n:
                self._print()  # the final state, once

    def __iter__(self):
        try:
            for item in self.iterable:
                yield item
                self.update(1)
        finally:
            self.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
