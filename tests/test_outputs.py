"""Outputs: a full disk or a lost permission is an ``error:`` line with the older output
intact; a file beside an output that tawarp did not write is never replaced; an
interrupted run's temporaries are removed by the next run that writes the same output."""

import subprocess
import sys
from collections import namedtuple

from tawarp.cli import main

SWEEP = ["sweep", "rvc_foam", "--var", "Q=1:18:3", "--device", "cpu", "--quiet"]
DESIGN = ["design", "rvc_foam", "--var", "Q=1:18", "--var", "stack.length=0.01:0.1", "--trials", "16", "--batch", "8",
          "--device", "cpu", "--quiet", "--no-plots"]

# the HDF5 writes of a sweep fail as on a full disk
_FULL_DISK = """
import errno, sys
import h5py
def full(self, *a, **k):
    raise OSError(errno.ENOSPC, "No space left on device")
h5py.Dataset.__setitem__ = full
from tawarp.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _debris(folder):
    return sorted(p.name for p in folder.rglob(".*") if p.name.endswith((".tmp", ".old")))


def test_a_full_disk_during_a_sweep_is_an_error_line_and_the_older_file_stays(tmp_path):
    """It printed an h5py traceback and ended with SIGSEGV (HDF5's exit handler flushed the
    failed file again). In a child process: a crash is an exit code there."""
    (tmp_path / "res.nc").write_text("older")
    run = subprocess.run([sys.executable, "-c", _FULL_DISK, *SWEEP, "-o", "res.nc"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 2, run.stderr
    assert run.stderr.strip().splitlines()[-1] == ("tawarp sweep: error: res.nc: could not be written (No space left "
                                                   "on device); the older file is kept")
    assert (tmp_path / "res.nc").read_text() == "older"
    assert not (tmp_path / "res.json").exists() and _debris(tmp_path) == []


def _little_space(monkeypatch, free):
    import shutil

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(free, 0, free))


def test_too_little_space_is_refused_before_writing(tmp_path, monkeypatch, capsys):
    """HDF5 cannot give up a file whose writing failed, so the space is checked first."""
    _little_space(monkeypatch, 1000)
    (tmp_path / "res.nc").write_text("older")
    assert main([*SWEEP, "-o", str(tmp_path / "res.nc")]) == 2
    err = capsys.readouterr().err
    assert "tawarp sweep: error: " in err and "res.nc: the disk has 0.001 MB free" in err and "nothing was written" in err
    assert (tmp_path / "res.nc").read_text() == "older" and _debris(tmp_path) == []
    assert main([*DESIGN, "-o", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert "tawarp design: error: " in err and ".h5: the disk has 0.001 MB free" in err
    assert _debris(tmp_path) == []


def test_a_permission_error_is_an_error_line(tmp_path, monkeypatch, capsys):
    """The rename into place refused (a folder made read-only meanwhile)."""
    import errno
    import os

    def refused(src, dst):
        raise PermissionError(errno.EACCES, "Permission denied")

    (tmp_path / "res.nc").write_text("older")
    monkeypatch.setattr(os, "replace", refused)
    assert main([*SWEEP, "-o", str(tmp_path / "res.nc")]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"tawarp sweep: error: {tmp_path / 'res.nc'}: could not be written (Permission denied); the older file is kept")
    assert (tmp_path / "res.nc").read_text() == "older" and _debris(tmp_path) == []
