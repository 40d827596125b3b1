"""Phase timestamps of a ``lidarcal`` process on stderr, for ``scripts/bench_trace.py``.

Off unless the environment variable ``LIDARCAL_TRACE`` is set (to anything but ""
or "0"); then every :func:`mark` prints one line

    lidarcal-trace PHASE pid=PID thread=NAME wall=T cpu=C tcpu=TC minflt=F [key=value ...]

to stderr: ``wall`` is :func:`time.perf_counter` (``CLOCK_MONOTONIC`` on Linux, the
same clock in every process, so the marks of the parent, its threads and its forked
workers line up with the caller's), ``cpu`` the process's CPU seconds so far (all its
threads), ``tcpu`` the calling thread's, ``minflt`` the process's minor page faults so far
(memory first touched, or copied after a fork). Off, :func:`mark` returns at once. Imports
nothing beyond the standard library's ``os``, ``sys`` and ``time``.
"""

from __future__ import annotations

import os
import sys
import time

ENABLED = os.environ.get("LIDARCAL_TRACE", "") not in ("", "0")
PREFIX = "lidarcal-trace"


def mark(phase: str, **info: object) -> None:
    """One line for ``phase`` (a short name without spaces) when tracing is on."""
    if not ENABLED:
        return
    import resource
    import threading  # already imported by the interpreter; looked up only when tracing

    info = {"minflt": resource.getrusage(resource.RUSAGE_SELF).ru_minflt, **info}
    extra = "".join(f" {k}={v}" for k, v in info.items())
    line = (f"{PREFIX} {phase} pid={os.getpid()} thread={threading.current_thread().name} "
            f"wall={time.perf_counter():.6f} cpu={time.process_time():.6f} "
            f"tcpu={time.thread_time():.6f}{extra}\n")
    sys.stderr.write(line)
    sys.stderr.flush()


def _at_exit() -> None:
    import resource

    ru = resource.getrusage(resource.RUSAGE_CHILDREN)  # the workers, reaped by now
    mark("atexit", children_cpu=f"{ru.ru_utime + ru.ru_stime:.6f}")


if ENABLED:
    import atexit

    # registered before multiprocessing's own exit handler (atexit runs them last-in,
    # first-out): this mark follows the pool's and the threads' shutdown
    atexit.register(_at_exit)
    mark("start")
