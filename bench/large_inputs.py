"""Large inputs: the memory of reading a large T-matrix CSV and the
time of ``tawarp fit`` against the number of heat inputs. Writes JSON.

    python bench/large_inputs.py                                   # 100 MB CSV; 1k, 4k, 19k heat inputs
    python bench/large_inputs.py --csv-mb 10 --heat-inputs 250,1000 --out /tmp/l.json

*Reading.* A T-matrix CSV of about ``--csv-mb`` MB (18 columns, sigma included; the
synthetic ceramic rows at 12.345 W and 20 frequencies repeated over as many heat inputs as it takes)
is read by :func:`tawarp.measure.files.read_tmatrix_csv` in a fresh process; the peak
resident memory (``ru_maxrss``) is reported in total and above the process's memory
just before the read (Python, NumPy, tawarp imported), both also as a multiple of the
file size.

*Fitting.* ``tawarp fit DATA --core ceramic --device cpu`` (the two-step procedure,
default restarts, figures included) on synthetic ceramic data with ``--n-freqs``
frequencies at each of N heat inputs (Q = 0 and N - 1 values in 0.5-20 W), timed as a
subprocess, wall clock and peak memory; ``seconds_per_heat_input`` should stay flat if
the time is linear in N.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np
from _results import run, write_result

READ_SCRIPT = """
import sys, time, tracemalloc
from tawarp.measure.files import read_tmatrix_csv

def status(key):  # this process's own memory [bytes]: VmRSS now, VmHWM its peak
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith(key + ":"))

before = status("VmRSS")
tracemalloc.start()
t0 = time.perf_counter()
data = read_tmatrix_csv(sys.argv[1])
dt = time.perf_counter() - t0
traced = tracemalloc.get_traced_memory()[1]
tracemalloc.stop()
print(before, status("VmHWM"), traced, dt, len(data))
"""


def write_big_csv(path: str, megabytes: float) -> dict:
    """A valid T-matrix CSV of about ``megabytes`` MB: synthetic ceramic rows at 12.345 W and 20
    frequencies, repeated over distinct heat inputs."""
    from tawarp.measure.files import TMatrixData, write_tmatrix_csv
    from tawarp.measure.synthetic import make_paper_data

    one = make_paper_data("ceramic", n_freqs=20, heat_inputs=[12.345], device="cpu")
    tmp = path + ".one"
    write_tmatrix_csv(tmp, one)
    row_bytes = os.path.getsize(tmp) / len(one)
    os.unlink(tmp)
    nQ = max(1, int(megabytes * 1e6 / row_bytes / len(one)))
    m = len(one)
    Q = np.arange(nQ) * 0.001
    data = TMatrixData(
        np.repeat(Q, m),
        np.tile(one.freq, nQ),
        np.tile(one.T, (nQ, 1, 1)),
        np.tile(one.sigma, (nQ, 1, 1, 1)),
        one.metadata,
    )
    write_tmatrix_csv(path, data)
    return {"rows": len(data), "heat_inputs": nQ, "columns": 18, "bytes": os.path.getsize(path)}


def read_memory(path: str) -> dict:
    """Peak memory of reading ``path`` in a fresh process (Linux): ``peak_rss`` (``VmHWM``,
    the process's own peak; ``ru_maxrss`` would carry over the parent's from before the
    exec), ``rss_before_read`` (resident memory once tawarp is imported; the
    imports' own transient peak can exceed it) and ``peak_allocated`` (tracemalloc's peak
    of what the read itself allocated, Python objects and NumPy arrays; timed separately,
    as tracing slows Python down)."""
    out = subprocess.run([sys.executable, "-c", READ_SCRIPT, path], capture_output=True, text=True, check=True)
    before, peak, traced, _, rows = out.stdout.split()
    plain = subprocess.run(
        [sys.executable, "-c", READ_SCRIPT.replace("tracemalloc.start()", ""), path],
        capture_output=True,
        text=True,
        check=True,
    )
    size = os.path.getsize(path)
    before, peak, traced = int(before), int(plain.stdout.split()[1]), int(traced)
    return {
        "file_bytes": size,
        "rows": int(rows),
        "seconds": float(plain.stdout.split()[3]),
        "peak_rss_bytes": peak,
        "rss_before_read_bytes": before,
        "peak_allocated_bytes": traced,
        "peak_rss_increase_over_file_size": (peak - before) / size,
        "peak_allocated_over_file_size": traced / size,
    }


def fit_time(n_heat: int, n_freqs: int, folder: str) -> dict:
    from tawarp.measure.files import write_tmatrix_csv
    from tawarp.measure.synthetic import make_paper_data, paper_frequencies

    Q = np.concatenate([[0.0], np.linspace(0.5, 20.0, n_heat - 1)])
    freqs = paper_frequencies("ceramic", n_freqs)
    path = os.path.join(folder, f"heat_{n_heat}.csv")
    write_tmatrix_csv(path, make_paper_data("ceramic", heat_inputs=Q, freqs=freqs, device="cpu"))
    cmd = [
        os.path.join(os.path.dirname(sys.executable), "tawarp"),
        "fit",
        path,
        "--core",
        "ceramic",
        "--device",
        "cpu",
        "--quiet",
        "-o",
        os.path.join(folder, f"fit_{n_heat}.json"),
    ]
    t0 = time.perf_counter()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(cmd, check=True)
    dt = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {
        "heat_inputs": n_heat,
        "frequencies": n_freqs,
        "file_bytes": os.path.getsize(path),
        "seconds": dt,
        "cpu_seconds": (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime),
        "seconds_per_heat_input": dt / n_heat,
        "command": "tawarp " + " ".join(cmd[1:]),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--csv-mb", type=float, default=100.0, help="size of the CSV to read [MB] (0 skips)")
    ap.add_argument("--heat-inputs", default="1000,4000,19000", help="comma list of heat-input counts ('' skips)")
    ap.add_argument("--n-freqs", type=int, default=3, help="frequencies per heat input in the fit files")
    ap.add_argument("--out", default=None, help="JSON output (default: bench/results/large_inputs_cpu.json)")
    args = ap.parse_args(argv)
    result = {
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": sys.version.split()[0],
        "load_average": os.getloadavg(),
    }
    with tempfile.TemporaryDirectory() as folder:
        if args.csv_mb > 0:
            path = os.path.join(folder, "big.csv")
            result["csv"] = write_big_csv(path, args.csv_mb)
            result["read"] = read_memory(path)
            r = result["read"]
            print(
                f"read {r['file_bytes'] / 1e6:.1f} MB ({r['rows']} rows) in {r['seconds']:.2f} s: peak RSS "
                f"{r['peak_rss_bytes'] / 1e6:.0f} MB ({r['peak_rss_increase_over_file_size']:.2f} x the file above "
                f"the {r['rss_before_read_bytes'] / 1e6:.0f} MB before reading); allocated by the read at its peak "
                f"{r['peak_allocated_bytes'] / 1e6:.0f} MB = {r['peak_allocated_over_file_size']:.2f} x the file",
                flush=True,
            )
            os.unlink(path)
        result["fit"] = []
        for n in [int(float(s)) for s in args.heat_inputs.split(",") if s.strip()]:
            row = fit_time(n, args.n_freqs, folder)
            result["fit"].append(row)
            print(
                f"tawarp fit: {n:6d} heat inputs x {args.n_freqs} frequencies: {row['seconds']:.1f} s "
                f"({1e3 * row['seconds_per_heat_input']:.2f} ms per heat input)",
                flush=True,
            )
    result["load_average_after"] = os.getloadavg()
    write_result(result, "large_inputs_cpu.json", args.out)
    return 0


if __name__ == "__main__":
    run(main)
