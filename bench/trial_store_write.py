"""How fast islands append their generations to their trial stores at once
(tawarp.design.storage.StoreWriter, a segment of its own per island): P processes each
append G generations of B rows, C generations per commit (an island's ``commit_seconds``
grouping), into a folder (by default a temporary one on the disk that holds the
temporary files, where the islands' study lies unless told), by each of the ways below;
a process's time is that of its appends and its close, and the rate the rows of all
processes over the wall time from the start to the last one done (the best of
``--repeats``).

* ``flush``: the store's append as it is (the generations flushed to the kernel);
* ``sync``: the append followed by ``os.fsync`` of the segment, as the store did at every
  commit before: each writer waits for the disk, and writers on one disk for each other;
* ``sync_at_close``: no sync per append, one at the close: the same bytes to the disk,
  all at the end.

The rows have the columns of the bench's islands (five design values, four metrics, one
objective): about 100 bytes a row, so 512 generations of 8192 are 0.4 GB a process.

    python bench/trial_store_write.py --processes 1,2 [--ways flush] [--folder DIR] [--out bench/results/NAME.json]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import sys
import tempfile
import time

import numpy as np

from tawarp.design.storage import TrialStore
from _results import run, write_result

WAYS = ("flush", "sync", "sync_at_close")


def append_all(way: str, folder: str, i: int, gens: int, batch: int, per_commit: int, go, done) -> None:
    rows = batch * per_commit
    rng = np.random.default_rng(i)
    params = {k: rng.random(rows) for k in ("stack.length", "heat_input", "hot_hx.length", "stack.porosity")}
    params["material"] = rng.integers(0, 4, rows)
    metrics = {k: rng.random(rows) for k in ("gradient", "T_max", "heat_leak", "T_hot")}
    index, failed = np.tile(np.arange(batch), per_commit), np.zeros(rows, dtype=bool)
    w = TrialStore(folder, "study").writer(f"island{i}", 0, {"material": ["a", "b", "c", "d"]}, batch)
    go.wait()
    t0 = time.perf_counter()
    for c in range(gens // per_commit):
        g = np.repeat(np.arange(c * per_commit, (c + 1) * per_commit), batch)
        w.append(g, index, params, metrics, params["heat_input"] - 5.0, failed)
        if way == "sync":
            os.fsync(w._f.id.get_vfd_handle())
    if way == "sync_at_close":
        os.fsync(w._f.id.get_vfd_handle())
    w.close()
    done.put((time.perf_counter(), time.perf_counter() - t0))


def rate(way: str, processes: int, parent: str | None, gens: int, batch: int, per_commit: int) -> tuple:
    """(rows per second of all ``processes``, each process's seconds)."""
    folder = tempfile.mkdtemp(prefix="tawarp_store_", dir=parent)
    try:
        ctx = mp.get_context("fork")
        go, done = ctx.Event(), ctx.Queue()
        procs = [
            ctx.Process(target=append_all, args=(way, folder, i, gens, batch, per_commit, go, done))
            for i in range(processes)
        ]
        for p in procs:
            p.start()
        time.sleep(1.0)  # (each makes its rows first)
        t0 = time.perf_counter()
        go.set()
        ends = [done.get() for _ in procs]
        for p in procs:
            p.join()
        wall = max(t for t, _ in ends) - t0
        return processes * gens * batch / wall, sorted(s for _, s in ends)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--processes", default="1,2", help="writer counts, comma separated (default 1,2)")
    ap.add_argument("--folder", default=None, help="where the segments go (default: the temporary files' folder)")
    ap.add_argument("--generations", type=int, default=512, help="generations per process (default 512)")
    ap.add_argument("--batch", type=int, default=8192, help="rows per generation (default 8192)")
    ap.add_argument("--per-commit", type=int, default=128, help="generations per append (default 128)")
    ap.add_argument("--repeats", type=int, default=3, help="runs per case, the best kept (default 3)")
    ap.add_argument("--ways", default=",".join(WAYS), help=f"comma list of {', '.join(WAYS)} (default all)")
    ap.add_argument("--out", default=None, help="JSON output (default: print it only)")
    args = ap.parse_args(argv)
    unknown = set(args.ways.split(",")) - set(WAYS)
    if unknown:
        ap.error(f"--ways: unknown {', '.join(sorted(unknown))} (known: {', '.join(WAYS)})")
    out = {
        "folder": args.folder or tempfile.gettempdir(),
        "generations": args.generations,
        "batch": args.batch,
        "per_commit": args.per_commit,
        "cpu_count": os.cpu_count(),
        "load_average": os.getloadavg(),
        "rows_per_s": {},
        "process_seconds": {},
    }
    for k in (int(p) for p in args.processes.split(",")):
        runs = {
            w: [rate(w, k, args.folder, args.generations, args.batch, args.per_commit) for _ in range(args.repeats)]
            for w in args.ways.split(",")
        }
        best = {w: max(v, key=lambda r: r[0]) for w, v in runs.items()}
        out["rows_per_s"][k] = {w: r for w, (r, _) in best.items()}
        out["process_seconds"][k] = {w: s for w, (_, s) in best.items()}
        print(k, json.dumps(out["process_seconds"][k]), flush=True)
    print(json.dumps(out, indent=1))
    if args.out:
        write_result(dict(out, command="python bench/trial_store_write.py " + " ".join(sys.argv[1:])), "", args.out)
    return 0


if __name__ == "__main__":
    run(main)
