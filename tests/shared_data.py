"""Where the real measurements live: ``shared/data/measured`` beside or inside the clone.

The real-data tests call :func:`measured_folder`: it walks up from this file to the first
directory holding ``shared/data/measured`` (``<repo>/../shared`` or ``<repo>/shared``).
Missing data FAIL the test when the environment variable ``CI`` is set (a CI run must not
pass by skipping them) and skip it with the paths tried otherwise.
"""

import os
from pathlib import Path

import pytest


def measured_folder(sub: str = "") -> Path:
    """``.../shared/data/measured/<sub>`` (fails in CI, skips elsewhere when absent)."""
    tried = []
    for parent in Path(__file__).resolve().parents:
        candidate = parent / "shared" / "data" / "measured" / sub
        if candidate.is_dir():
            return candidate
        tried.append(str(candidate))
    msg = f"real measurements shared/data/measured/{sub} not found; looked in {', '.join(tried)}"
    if os.environ.get("CI"):
        pytest.fail(msg + " (CI is set: real-data tests must run)")
    pytest.skip(msg)
