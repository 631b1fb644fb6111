"""Output files written atomically: a temporary file in the target folder, then renamed,
so a reader never sees a half-written file and an interrupted run leaves no debris.

The temporary file is named after its target (``.NAME.XXXXXXXX.tmp`` beside ``NAME``),
gets the permissions a plain ``open()`` would give (``0666`` less the umask, not
``mkstemp``'s ``0600``), and is removed when writing fails or is interrupted.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path

import numpy as np


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | Path):
    """``with atomic_path(p) as tmp: write(tmp)``: on success ``tmp`` replaces ``p``;
    on any exception (Ctrl-C included) ``tmp`` is removed and ``p`` is untouched."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a directory; give a file name")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def write_json(path: str | Path, obj) -> Path:
    """Write ``obj`` as JSON atomically (NumPy arrays and scalars become lists and numbers)."""
    return write_text(path, json.dumps(obj, indent=2, default=_json_default) + "\n")


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    raise TypeError(f"not JSON serializable: {type(o)}")
