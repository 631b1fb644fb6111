"""The cascade kernel's GPU code without a GPU: registers, spills and instruction counts.

Warp compiles the forward cascade (and the point kernel) ahead of time to PTX for an
architecture (default sm_90, the H100), ``ptxas`` assembles it under each register cap and
``nvdisasm`` lists the machine code, whose instructions are counted per function: all,
float64 arithmetic (DFMA, DMUL, DADD), local-memory loads and stores (LDL, STL: spills and
stack) and calls. Static counts, not Nsight Compute's executed ones: they show what the
compiler made of the code (a function called instead of inlined, a spill) on a machine
without a GPU. Writes JSON.

    python bench/kernel_code.py --caps 0,96,128,168 --out bench/results/kernel_code_sm90.json

Needs ``ptxas`` (CUDA toolkit) on the PATH and ``nvdisasm`` (the PyPI wheel
``nvidia-cuda-nvdisasm``, or the toolkit) on the PATH or in ``$NVDISASM``. NVRTC may write a
newer PTX version than the toolkit's ``ptxas`` reads: the ``.version`` line is lowered to
``--ptx-version``.
"""

from __future__ import annotations

import argparse
import collections
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import warp as wp

from _results import run, write_result

COUNTED = {"fp64": r" (DFMA|DMUL|DADD)\b", "ldl": r" LDL\b", "stl": r" STL\b", "call": r" CALL\b"}


def disassembly_counts(text: str) -> dict:
    """Instruction counts per function of the disassembly ``text`` (:data:`COUNTED` and ``total``)."""
    counts = collections.defaultdict(collections.Counter)
    name = None  # the sections before the first function hold data, not instructions
    for line in text.splitlines():
        if "@function" in line:
            name = re.sub(r".*_cu_[0-9a-f]{8}\d+", "", line.split()[1].split(",")[0])
            name = re.sub(r"make_\w+__locals__(\w+?)_[0-9a-f]{8}_cuda_kernel_forward", r"\1", name)
        elif name is not None and re.match(r"^\s+/\*[0-9a-f]+\*/", line):
            counts[name]["total"] += 1
            for key, pattern in COUNTED.items():
                if re.search(pattern, line):
                    counts[name][key] += 1
    return {k: dict(v) for k, v in counts.items()}


def loop_counts(text: str, kernel: str) -> list[dict]:
    """Instruction counts of each loop of function ``kernel`` in the disassembly ``text``: a
    backward branch and the instructions from its target to it (address range, ``total``,
    :data:`COUNTED`, ``ldg``: global loads). A cascade's cell loop is the loop of the most
    float64 instructions that holds no other such loop: the one executed once per Magnus
    cell (bench/README.md)."""
    name, labels, pending, body = None, {}, [], []
    for line in text.splitlines():
        if "@function" in line:
            name = line.split()[1].split(",")[0]
            continue
        label = re.match(r"^\.(L_x_\d+):", line)
        if label:
            pending.append(label.group(1))
            continue
        code = re.match(r"^\s+/\*([0-9a-f]+)\*/\s+(.*)", line)
        if code and name and kernel in name and not name.startswith("$"):
            address = int(code.group(1), 16)
            labels.update(dict.fromkeys(pending, address))
            body.append((address, code.group(2)))
        pending = [] if code else pending
    patterns = {**COUNTED, "ldg": r" LDG\b"}
    loops = []
    for address, text_ in body:
        branch = re.search(r"BRA .*\(\.(L_x_\d+)\)", text_)
        if branch and labels.get(branch.group(1), address) < address:
            start = labels[branch.group(1)]
            inside = [" " + t for a, t in body if start <= a <= address]
            counts = {k: sum(bool(re.search(p, t)) for t in inside) for k, p in patterns.items()}
            loops.append({"start": start, "end": address, "total": len(inside), **counts})
    return loops


def cell_loop(loops: list[dict]) -> dict | None:
    """The cell loop among :func:`loop_counts`' loops (None without one of 100 float64
    instructions); of the point kernel's, its loop over a Magnus cell's three Gauss points
    (executed once per point; None where the loop is unrolled)."""
    heavy = [lp for lp in loops if lp["fp64"] >= 100]
    inner = [
        lp
        for lp in heavy
        if not any(o is not lp and lp["start"] <= o["start"] and o["end"] <= lp["end"] for o in heavy)
    ]
    return max(inner, key=lambda lp: lp["fp64"], default=None)


def assemble(ptx: Path, arch: int, ptx_version: str, nvdisasm: str) -> dict:
    """ptxas -v of ``ptx`` (registers, stack, spills of the kernel) and its disassembly counts."""
    src = re.sub(r"\.version \d+\.\d+", f".version {ptx_version}", ptx.read_text()).rstrip("\0")
    ptx.write_text(src)
    cubin = ptx.with_suffix(".cubin")
    log = subprocess.run(
        ["ptxas", f"-arch=sm_{arch}", "-v", str(ptx), "-o", str(cubin)], capture_output=True, text=True, check=True
    ).stderr
    entry = log[log.index("Compiling entry function") :]
    spills = re.search(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads", entry)
    text = subprocess.run([nvdisasm, str(cubin)], capture_output=True, text=True, check=True).stdout
    return {
        "registers": int(re.search(r"Used (\d+) registers", entry).group(1)),
        "stack_frame_bytes": int(spills.group(1)),
        "spill_store_bytes": int(spills.group(2)),
        "spill_load_bytes": int(spills.group(3)),
        "functions": disassembly_counts(text),
        "cell_loop": cell_loop(loop_counts(text, "transfer_kernel")),
        "gauss_loop": cell_loop(loop_counts(text, "point_kernel")),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", type=int, default=90)
    ap.add_argument("--caps", default="128", help="register caps of the kernels (comma list; 0: none)")
    ap.add_argument("--ptx-version", default="9.0", help="the .version the local ptxas reads")
    ap.add_argument(
        "--kernels",
        default="plain,general,points",
        help="comma list of plain (the plain cascade), general (the general cascade), points (the point kernel)",
    )
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    nvdisasm = os.environ.get("NVDISASM") or shutil.which("nvdisasm")
    if not nvdisasm or not shutil.which("ptxas"):
        ap.error("needs ptxas and nvdisasm on the PATH (or $NVDISASM): pip install nvidia-cuda-nvdisasm")
    wp.init()
    from tawarp.model import forward

    chosen = set(args.kernels.split(","))
    if chosen - {"plain", "general", "points"}:
        ap.error(f"--kernels: unknown {sorted(chosen - {'plain', 'general', 'points'})}")
    kernels = {}
    for c in args.caps.split(","):
        # the cascade of a core with plain parts alone (circular pores, rigid frames, no shape
        # factor: the bench's and the bundled cores'), and of any core
        if "plain" in chosen:
            kernels[f"cascade plain/cap {c}"] = forward._transfer_kernel(int(c) or None, 0, True)
        if "general" in chosen:
            kernels[f"cascade/cap {c}"] = forward._transfer_kernel(int(c) or None)
        if "points" in chosen:  # the point kernel of the linear heat model
            kernels[f"points/cap {c}"] = forward._point_kernel(False, int(c) or None)
    result = {"arch": f"sm_{args.arch}", "warp": wp.config.version, "kernels": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for label, kernel in kernels.items():
            paths = wp.compile_aot_module(
                kernel.module,
                arch=args.arch,
                module_dir=Path(tmp, label.replace("/", "_").replace(" ", "")),
                use_ptx=True,
            )
            ptx = next(Path(p) for p in paths if str(p).endswith(".ptx"))
            result["kernels"][label] = r = assemble(ptx, args.arch, args.ptx_version, nvdisasm)
            loop = r["cell_loop"] or r["gauss_loop"]
            print(
                f"{label}: {r['registers']} registers, stack {r['stack_frame_bytes']} B, spills "
                f"{r['spill_store_bytes']}/{r['spill_load_bytes']} B; "
                + (
                    f"{'cell' if r['cell_loop'] else 'Gauss point'} loop {loop['total']} / {loop['fp64']} float64, "
                    f"{loop['ldg']} loads, {loop['ldl']}/{loop['stl']} local loads/stores; "
                    if loop
                    else ""
                )
                + "functions "
                + ", ".join(
                    f"{k[:40]} {v.get('total', 0)}" for k, v in r["functions"].items() if v.get("total", 0) > 300
                ),
                flush=True,
            )
    if args.out:
        write_result(result, "", args.out)


if __name__ == "__main__":
    run(main)
