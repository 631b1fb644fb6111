"""Where the benchmarks write: one JSON per run, atomically (:func:`tawarp.io.write_json`),
under ``bench/results/`` unless ``--out`` names another file."""

from __future__ import annotations

from pathlib import Path

from tawarp.io import write_json

RESULTS = Path(__file__).resolve().parent / "results"


def write_result(result: dict, name: str, out: str | None = None) -> Path:
    """Write ``result`` to ``out`` (default ``bench/results/NAME``) and say where."""
    path = write_json(Path(out) if out else RESULTS / name, result)
    print(f"wrote {path}")
    return path
