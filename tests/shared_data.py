"""Where the real measurements of the tests live: the copies bundled with the package.

The real-data tests call :func:`measured_folder`, the package's ``tawarp/data/measured/<sub>``
(each data set with its README, source and licence). A missing folder fails the test: a
real-data test never passes by skipping.
"""

from importlib import resources
from pathlib import Path

import pytest


def measured_folder(sub: str = "") -> Path:
    """``tawarp/data/measured/<sub>`` of the installed package (the test fails when absent)."""
    folder = Path(str(resources.files("tawarp") / "data" / "measured" / sub))
    if not folder.is_dir():
        pytest.fail(f"real measurements {folder} not found; reinstall the package (pip install -e .)")
    return folder
