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

from _results import write_result

COUNTED = {"fp64": r" (DFMA|DMUL|DADD)\b", "ldl": r" LDL\b", "stl": r" STL\b", "call": r" CALL\b"}


def disassembly_counts(cubin: Path, nvdisasm: str) -> dict:
    """Instruction counts per function of ``cubin`` (:data:`COUNTED` and ``total``)."""
    text = subprocess.run([nvdisasm, str(cubin)], capture_output=True, text=True, check=True).stdout
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
    return {
        "registers": int(re.search(r"Used (\d+) registers", entry).group(1)),
        "stack_frame_bytes": int(spills.group(1)),
        "spill_store_bytes": int(spills.group(2)),
        "spill_load_bytes": int(spills.group(3)),
        "functions": disassembly_counts(cubin, nvdisasm),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", type=int, default=90)
    ap.add_argument("--caps", default="128", help="register caps of the cascade (comma list; 0: none)")
    ap.add_argument("--ptx-version", default="9.0", help="the .version the local ptxas reads")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    nvdisasm = os.environ.get("NVDISASM") or shutil.which("nvdisasm")
    if not nvdisasm or not shutil.which("ptxas"):
        ap.error("needs ptxas and nvdisasm on the PATH (or $NVDISASM): pip install nvidia-cuda-nvdisasm")
    wp.init()
    from tawarp.model import forward

    kernels = {}
    for c in args.caps.split(","):
        # the cascade of a core with plain parts alone (circular pores, rigid frames, no shape
        # factor: the bench's and the bundled cores'), and of any core
        kernels[f"cascade plain/cap {c}"] = forward._transfer_kernel(int(c) or None, 0, True)
        kernels[f"cascade/cap {c}"] = forward._transfer_kernel(int(c) or None)
    kernels["points"] = forward._point_kernel(False)
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
            print(
                f"{label}: {r['registers']} registers, stack {r['stack_frame_bytes']} B, spills "
                f"{r['spill_store_bytes']}/{r['spill_load_bytes']} B; functions "
                + ", ".join(
                    f"{k[:40]} {v.get('total', 0)}" for k, v in r["functions"].items() if v.get("total", 0) > 300
                ),
                flush=True,
            )
    if args.out:
        write_result(result, "", args.out)


if __name__ == "__main__":
    main()
