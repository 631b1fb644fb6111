"""The GPUs' clocks, power and temperature sampled while a benchmark runs (``nvidia-smi``):
whether GPUs busy together run at the clocks of one GPU busy alone, and what held a clock
back (``nvidia-smi``'s clock event reasons: power cap, thermal or power-brake slowdown).

    with GpuClocks() as clocks:
        t0 = time.time(); run(); t1 = time.time()
        summary = clocks.between(t0, t1)
"""

from __future__ import annotations

import shutil
import subprocess
import threading
import time

import numpy as np

FIELDS = ("index", "clocks.sm", "clocks.max.sm", "power.draw", "temperature.gpu", "utilization.gpu")
#: The clock event reasons' field: its newer name, then the older one that drivers before
#: 535 know.
REASON_FIELDS = ("clocks_event_reasons.active", "clocks_throttle_reasons.active")
#: nvidia-smi's clock event reason bits (``nvidia-smi --help-query-gpu``), idle left out.
REASONS = {
    0x2: "applications_clocks",
    0x4: "sw_power_cap",
    0x8: "hw_slowdown",
    0x10: "sync_boost",
    0x20: "sw_thermal_slowdown",
    0x40: "hw_thermal_slowdown",
    0x80: "hw_power_brake_slowdown",
}
#: A sample counts as busy when a kernel ran this share [%] of its period: idle GPUs drop
#: their clocks, so only busy samples say what a computing GPU ran at.
BUSY_PERCENT = 50


class GpuClocks:
    """Samples every ``period_ms`` from a background ``nvidia-smi``, each stamped with
    ``time.time()`` on arrival; no samples where there is no ``nvidia-smi``."""

    def __init__(self, period_ms: int = 50):
        self.samples: list[tuple[float, list[str]]] = []
        self.fields: tuple[str, ...] = ()
        self._proc = None
        smi = shutil.which("nvidia-smi")
        if smi is None:
            return
        for reason in REASON_FIELDS + (None,):
            fields = FIELDS + ((reason,) if reason else ())
            query = [smi, f"--query-gpu={','.join(fields)}", "--format=csv,noheader,nounits"]
            try:
                ok = subprocess.run(query, capture_output=True, timeout=20).returncode == 0
            except (OSError, subprocess.SubprocessError):
                return
            if ok:
                break
        else:
            return
        self.fields = fields
        self._proc = subprocess.Popen(
            query + [f"-lms={period_ms}"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self._proc.stdout:
            values = [v.strip() for v in line.split(",")]
            if len(values) == len(self.fields):
                self.samples.append((time.time(), values))

    def between(self, t0: float, t1: float) -> dict:
        """Per GPU (``nvidia-smi``'s index) over the samples between ``time.time()`` stamps
        t0 and t1: ``samples``, ``busy`` (those of utilization >= :data:`BUSY_PERCENT`),
        the busy samples' median and lowest SM clock [MHz] and the GPU's top SM clock,
        the highest power [W] and temperature [C], and how many busy samples each clock
        event reason held (:data:`REASONS`)."""
        out: dict[str, dict] = {}
        at = {f: i for i, f in enumerate(self.fields)}
        for gpu in sorted({v[0] for t, v in self.samples if t0 <= t <= t1}, key=int):
            rows = [v for t, v in self.samples if t0 <= t <= t1 and v[0] == gpu]
            busy = [v for v in rows if _number(v[at["utilization.gpu"]]) >= BUSY_PERCENT]
            clocks = np.array([_number(v[at["clocks.sm"]]) for v in busy])
            entry = {
                "samples": len(rows),
                "busy": len(busy),
                "sm_clock_mhz_median": float(np.median(clocks)) if busy else None,
                "sm_clock_mhz_min": float(clocks.min()) if busy else None,
                "sm_clock_mhz_max_allowed": _number(rows[-1][at["clocks.max.sm"]]),
                "power_w_max": max(_number(v[at["power.draw"]]) for v in rows),
                "temperature_c_max": max(_number(v[at["temperature.gpu"]]) for v in rows),
            }
            if len(self.fields) > len(FIELDS):
                bits = [_bits(v[-1]) for v in busy]
                entry["reasons"] = {name: sum(1 for b in bits if b & bit) for bit, name in REASONS.items()}
            out[gpu] = entry
        return out

    def close(self) -> None:
        if self._proc is not None:
            self._proc.terminate()
            self._proc.wait(timeout=10)
            self._proc = None

    def __enter__(self) -> GpuClocks:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:  # "[N/A]", "[Not Supported]"
        return float("nan")


def _bits(text: str) -> int:
    try:
        return int(text, 16)
    except ValueError:
        return 0
