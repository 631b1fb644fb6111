"""Where a loop process's wall time goes besides its own work (``bench/loop.py --read-waits``).

A process that runs loops on a GPU waits for it at every read of a result (the heat solve's
count of sets still iterating, the fits' normal equations, the T-matrices a host step
needs) and at every array it makes from host data; with blocking waits
(:func:`tawarp.distributed.wait_by_blocking`) those waits take no CPU, so ``--host-time``
does not see them. :func:`read_waits` times each of them by the wall clock, by call site (the
function and line that asked), and counts the process's context switches: voluntary ones
(it waited: on the GPU, for its turn among loops run together) and involuntary ones (it
was preempted: a study's processes wanted more cores than the host has).
"""

from __future__ import annotations

import contextlib
import os
import resource
import sys
import time

import numpy as np
import warp as wp


@contextlib.contextmanager
def read_waits(on_cuda_only: bool = True):
    """Inside, every :meth:`warp.array.numpy` (a read, on a GPU a copy that waits for the work
    queued before it) and every :class:`warp.array` made from a NumPy array (an upload) is
    timed by the wall clock, those of arrays on a CUDA device alone unless ``on_cuda_only`` is
    False. Yields {"sites": {"read file:function:line" or "upload ...": [calls, seconds]},
    "switches": (voluntary, involuntary)}, the switches filled on leaving."""
    totals: dict = {"sites": {}, "switches": (0, 0)}
    sites = totals["sites"]
    read, make = wp.array.numpy, wp.array.__init__

    def site(kind: str) -> list:
        caller = sys._getframe(2)
        key = f"{kind} {os.path.basename(caller.f_code.co_filename)}:{caller.f_code.co_name}:{caller.f_lineno}"
        return sites.setdefault(key, [0, 0.0])

    def timed_read(self):
        if on_cuda_only and not self.device.is_cuda:
            return read(self)
        t = time.perf_counter()
        out = read(self)
        entry = site("read")
        entry[0] += 1
        entry[1] += time.perf_counter() - t
        return out

    def timed_make(self, *args, **kwargs):
        t = time.perf_counter()
        make(self, *args, **kwargs)
        data = args[0] if args else kwargs.get("data")
        if isinstance(data, np.ndarray) and self.device is not None and (self.device.is_cuda or not on_cuda_only):
            entry = site("upload")
            entry[0] += 1
            entry[1] += time.perf_counter() - t

    before = resource.getrusage(resource.RUSAGE_SELF)
    wp.array.numpy, wp.array.__init__ = timed_read, timed_make
    try:
        yield totals
    finally:
        wp.array.numpy, wp.array.__init__ = read, make
        after = resource.getrusage(resource.RUSAGE_SELF)
        totals["switches"] = (after.ru_nvcsw - before.ru_nvcsw, after.ru_nivcsw - before.ru_nivcsw)


def summary(totals: dict, cases: int, top: int = 12) -> dict:
    """The JSON of :func:`read_waits`' ``totals`` over ``cases`` loop cases: the waits'
    seconds and count in all and a case, the context switches, and the ``top`` call sites by
    their seconds."""
    seconds = sum(s for _, s in totals["sites"].values())
    calls = sum(n for n, _ in totals["sites"].values())
    ranked = sorted(totals["sites"].items(), key=lambda kv: -kv[1][1])[:top]
    return {
        "seconds": seconds,
        "calls": calls,
        "ms_per_case": 1e3 * seconds / max(cases, 1),
        "voluntary_switches": totals["switches"][0],
        "involuntary_switches": totals["switches"][1],
        "by_site": [{"site": k, "calls": n, "seconds": s} for k, (n, s) in ranked],
    }
