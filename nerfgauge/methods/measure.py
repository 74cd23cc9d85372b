"""What a job cost: wall time, CPU time (user + system) and peak resident memory.

`measured()`: a block of work in this process (every thread of it); the peak is the
process's peak so far (ru_maxrss never decreases), so it bounds the block's from above.
`run_process()`: a command in a child process, measured from the child's own resource
usage (os.wait4), exact per command: other tools' methods (nerfgauge.methods.external),
the benches' measured children (orchestrate.bench.common.run_child).
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field


def maxrss_bytes(maxrss) -> int:
    """ru_maxrss in bytes: Linux reports kibibytes, macOS bytes."""
    return int(maxrss) * (1 if sys.platform == "darwin" else 1024)


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
        cost.peak_memory_bytes = maxrss_bytes(after.ru_maxrss)


@dataclass(frozen=True)
class Finished:
    seconds: float
    cpu_seconds: float
    peak_memory_bytes: int | None  # None: the launcher was stopped before it could report
    status: int  # exit status, or -N when the command died of signal N
    stopped: bool = False  # stopped for running past its timeout


POLL_SECONDS = 0.05
# The command is started by a small launcher (a fresh interpreter without site packages) that
# forks it and reports its os.wait4 usage through a pipe. A child forked (or vforked) straight
# from this process would carry this process's resident set into its own peak: Linux records
# the old image's high-water mark at exec, so a command started from a 2 GB harness would
# report at least 2 GB (387 MB for a 120 MB command started under pytest). The launcher's own
# peak (about 10 MB) is the floor of the figure.
LAUNCHER = """
import json, os, sys
pid = os.fork()
if pid == 0:
    try:
        os.execv(sys.argv[2], sys.argv[2:])
    finally:
        os._exit(127)
_, status, usage = os.wait4(pid, 0)
os.write(int(sys.argv[1]), json.dumps({"cpu_seconds": usage.ru_utime + usage.ru_stime, "maxrss": usage.ru_maxrss,
                                       "status": os.waitstatus_to_exitcode(status)}).encode())
os._exit(os.waitstatus_to_exitcode(status) % 256)
"""


def run_process(argv: list, *, cwd=None, env=None, stdout=None, timeout: float | None = None) -> Finished:
    """Run argv (an absolute program path first; no shell) in its own process group, stdout
    and stderr to `stdout` (a file object; None: ours), and stop the whole group once it runs
    past `timeout` seconds. OSError when it cannot start."""
    start = time.perf_counter()
    report, report_write = os.pipe()
    try:
        process = subprocess.Popen([sys.executable, "-I", "-S", "-c", LAUNCHER, str(report_write), *map(str, argv)],
                                   cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=stdout,
                                   stderr=None if stdout is None else subprocess.STDOUT, start_new_session=True,
                                   pass_fds=(report_write,))
    except OSError:
        os.close(report)
        raise
    finally:
        os.close(report_write)
    stopped = False
    try:
        while True:
            pid, status, usage = os.wait4(process.pid, os.WNOHANG)
            if pid:
                break
            if timeout is not None and time.perf_counter() - start > timeout and not stopped:
                stopped = True
                _stop_group(process.pid)
            time.sleep(POLL_SECONDS)
    except BaseException:  # interrupted: the command goes with us
        _stop_group(process.pid)
        raise
    process.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait again
    _stop_group(process.pid)  # anything the command left running in its group
    seconds = time.perf_counter() - start
    with os.fdopen(report, "rb") as pipe:
        measured = json.loads(pipe.read() or b"{}")
    peak = maxrss_bytes(measured["maxrss"]) if "maxrss" in measured else None
    return Finished(seconds, measured.get("cpu_seconds", usage.ru_utime + usage.ru_stime), peak,
                    measured.get("status", process.returncode), stopped)


def _stop_group(pid: int) -> None:
    try:
        os.killpg(pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
