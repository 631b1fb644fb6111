"""Processes and threads that tests start end with the test, pass or fail: a failing
assertion must fail the test, not leave a worker asked for a million trials running or a
thread that keeps pytest from exiting."""

from __future__ import annotations

import contextlib
import subprocess
import threading


@contextlib.contextmanager
def reaped(*procs: subprocess.Popen, timeout: float = 30.0):
    """``with reaped(p, q):``: on leaving, each process still running is killed (SIGKILL)
    and every one is reaped within ``timeout`` [s] (a zombie keeps its pid, and a design
    worker's claim lives while its pid does)."""
    try:
        yield procs
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.communicate(timeout=timeout)


@contextlib.contextmanager
def released(stop: threading.Event, *threads: threading.Thread, timeout: float = 30.0):
    """``with released(stop, t):``: on leaving, ``stop`` is set and each thread joined
    within ``timeout`` [s]; one still alive then fails the test."""
    try:
        yield
    finally:
        stop.set()
        for t in threads:
            t.join(timeout)
        alive = [t.name for t in threads if t.is_alive()]
        assert not alive, f"threads {alive} still running {timeout} s after being released"
