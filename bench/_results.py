"""Where the benchmarks write: one JSON per run, atomically (:func:`tawarp.io.write_json`),
under ``bench/results/`` unless ``--out`` names another file, or a folder to write it
into; and how they run as commands (:func:`run`)."""

from __future__ import annotations

import sys
from pathlib import Path

from tawarp.io import write_json

RESULTS = Path(__file__).resolve().parent / "results"


def write_result(result: dict, name: str, out: str | None = None) -> Path:
    """Write ``result`` to ``out`` (default ``bench/results/NAME``; an existing folder:
    ``out/NAME``) and say where."""
    path = Path(out) if out else RESULTS / name
    path = write_json(path / name if path.is_dir() else path, result)
    print(f"wrote {path}")
    return path


def run(main) -> None:
    """Exit with ``main()``'s status (0 for None), or after Ctrl-C with 130 and one line: a
    result is written whole or not at all (:func:`write_result`), so an interrupted
    benchmark leaves those it finished and nothing half-written."""
    try:
        status = main()
    except KeyboardInterrupt:
        print(
            f"{Path(sys.argv[0]).name}: interrupted; results written before are whole, none is half-written",
            file=sys.stderr,
        )
        status = 130
    sys.exit(status or 0)
