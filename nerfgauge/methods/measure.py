"""What a job cost, measured the same way for every method run in this process: wall time,
CPU time (user + system, every thread of the process) and the process's peak resident set.

A method run as a subprocess (nerfgauge.methods.external) is measured from the child's own
resource usage instead (os.wait4), which is exact per job; in this process the peak is the
process's peak so far (ru_maxrss never decreases), so it bounds the job's from above.
"""

from __future__ import annotations

import contextlib
import resource
import sys
import time
from dataclasses import dataclass, field


def maxrss_bytes(usage) -> int:
    """ru_maxrss in bytes: Linux reports kibibytes, macOS bytes."""
    return int(usage.ru_maxrss) * (1 if sys.platform == "darwin" else 1024)


@dataclass
class Cost:
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    peak_memory_bytes: int = 0
    _start: tuple = field(default=(), repr=False)


@contextlib.contextmanager
def measured():
    """Yield a Cost filled in when the block ends (also when it raises)."""
    cost = Cost()
    before = resource.getrusage(resource.RUSAGE_SELF)
    start = time.perf_counter()
    try:
        yield cost
    finally:
        after = resource.getrusage(resource.RUSAGE_SELF)
        cost.seconds = time.perf_counter() - start
        cost.cpu_seconds = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        cost.peak_memory_bytes = maxrss_bytes(after)
