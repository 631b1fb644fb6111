"""How fast worker processes write their results into one shared-memory file
(tawarp.distributed.SharedColumns): P processes each write a region of R MB into a fresh
file of /dev/shm at once, by each of the ways below; the rate is the bytes of all
regions over the wall time from the start to the last process done (the best of
``--repeats``), and a writer's own cost, GB per CPU second (on a host busy with other
work the wall times say little).

* ``pwrite``: ``os.pwrite`` of the region (tmpfs's write call holds the file's inode
  lock while it copies: one writer at a time per file);
* ``mapped``: a mapping of the region, its pages faulted in one at a time by the copy;
* ``populated``: a mapping of the region, its pages made present at once
  (``madvise(MADV_POPULATE_WRITE)``), then the copy: no inode lock, no page faults;
* ``files``: ``os.pwrite`` of each region into a file of its own (the lock not shared).

and into a file of its own per process whose pages are there already (written before
the start, as the pooled chunk files of ``ClusterEvaluator.evaluate_sobol`` that a
later call writes again: tawarp.distributed.ChunkFiles):

* ``rewrite``: ``os.pwrite`` of the region (no allocation, tmpfs's per-page write path);
* ``remap``: a mapping made and populated (page tables only), the copy, the unmapping:
  a worker's first write of a pooled file;
* ``kept``: the copy into a populated mapping made before the start: a worker's later
  writes of that file (tawarp.distributed._written_mapping).

    python bench/shared_write.py --processes 1,2 --mb 512 [--out bench/results/NAME.json]
"""

from __future__ import annotations

import argparse
import json
import mmap
import multiprocessing as mp
import os
import sys
import tempfile
import time

import numpy as np

from tawarp.distributed import MADV_POPULATE_WRITE
from _results import run, write_result

WAYS = ("pwrite", "mapped", "populated", "files", "rewrite", "remap", "kept")
#: The ways that write a file of each process's own.
OWN_FILE = ("files", "rewrite", "remap", "kept")
#: The ways that write a file whose pages are there before the start.
WRITTEN_BEFORE = ("rewrite", "remap", "kept")


def pwrite(fd: int, src: np.ndarray, at: int) -> None:
    view = memoryview(src)
    while view:
        n = os.pwrite(fd, view, at)
        view, at = view[n:], at + n


def write(way: str, path: str, i: int, size: int, go, done) -> None:
    src = np.full(size, i + 1, dtype=np.uint8)  # (this process's own pages, touched before the start)
    at = 0 if way in OWN_FILE else i * size
    path += f".{i}" if way in OWN_FILE else ""
    kept = None
    if way in WRITTEN_BEFORE:
        fd = os.open(path, os.O_RDWR | os.O_CREAT)
        pwrite(fd, np.zeros(size, dtype=np.uint8), 0)
        if way == "kept":
            kept = mmap.mmap(fd, size)
            kept.madvise(MADV_POPULATE_WRITE)
        os.close(fd)
    go.wait()
    c0 = time.process_time()
    fd = os.open(path, os.O_RDWR | os.O_CREAT)
    try:
        if way in ("pwrite", "files", "rewrite"):
            pwrite(fd, src, at)
        else:
            m = kept if kept is not None else mmap.mmap(fd, size, offset=at)
            if way in ("populated", "remap"):
                m.madvise(MADV_POPULATE_WRITE)
            dst = np.frombuffer(m, dtype=np.uint8)
            dst[:] = src
            del dst
            if kept is None:
                m.close()
    finally:
        os.close(fd)
    done.put((time.perf_counter(), time.process_time() - c0))


def rate(way: str, processes: int, size: int) -> tuple[float, float]:
    """(GB/s of ``processes`` writers of ``size`` bytes each into a fresh file, GB per
    CPU second of one writer: its own cost, whatever else runs on the host)."""
    with tempfile.TemporaryDirectory(dir="/dev/shm") as folder:
        path = os.path.join(folder, "columns")
        with open(path, "wb") as f:
            f.truncate(0 if way in OWN_FILE else processes * size)
        ctx = mp.get_context("fork")
        go, done = ctx.Event(), ctx.Queue()
        procs = [ctx.Process(target=write, args=(way, path, i, size, go, done)) for i in range(processes)]
        for p in procs:
            p.start()
        time.sleep(0.5 + (3 if way in WRITTEN_BEFORE else 1) * size / 1e9)  # (each fills its source first)
        t0 = time.perf_counter()
        go.set()
        ends = [done.get() for _ in procs]
        for p in procs:
            p.join()
        wall = max(t for t, _ in ends) - t0
        return processes * size / wall / 1e9, size / max(c for _, c in ends) / 1e9


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--processes", default="1,2", help="writer counts, comma separated (default 1,2)")
    ap.add_argument("--mb", type=int, default=512, help="MB per process (default 512)")
    ap.add_argument("--repeats", type=int, default=3, help="runs per case, the best kept (default 3)")
    ap.add_argument("--out", default=None, help="JSON output (default: print it only)")
    args = ap.parse_args(argv)
    size = args.mb << 20
    out = {
        "mb_per_process": args.mb,
        "cpu_count": os.cpu_count(),
        "kernel": os.uname().release,
        "gb_per_s": {},
        "gb_per_cpu_s": {},
    }
    for k in (int(p) for p in args.processes.split(",")):
        runs = {w: [rate(w, k, size) for _ in range(args.repeats)] for w in WAYS}
        out["gb_per_s"][k] = {w: max(r for r, _ in v) for w, v in runs.items()}
        out["gb_per_cpu_s"][k] = {w: max(c for _, c in v) for w, v in runs.items()}
        print(k, json.dumps(out["gb_per_s"][k]), json.dumps(out["gb_per_cpu_s"][k]), flush=True)
    print(json.dumps(out, indent=1))
    if args.out:
        write_result(dict(out, command="python bench/shared_write.py " + " ".join(sys.argv[1:])), "", args.out)
    return 0


if __name__ == "__main__":
    run(main)
