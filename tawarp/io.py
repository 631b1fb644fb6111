"""Output files written atomically (a temporary file in the target folder, then renamed,
so a reader never sees a half-written file and an interrupted run leaves no debris), and
Ctrl-C handled so that long runs stop cleanly (:func:`interrupts_deferred`,
:func:`interrupt_guard`).

The temporary file is named after its target and its writer (``.NAME.PID@HOST.XXXXXXXX.tmp``
beside ``NAME``), gets the permissions a plain ``open()`` would give (``0666`` less the
umask, not ``mkstemp``'s ``0600``), and is removed when writing fails or is interrupted.
A run killed outright (SIGKILL, a power cut) cannot remove it: the next run that writes
``NAME`` removes the temporaries of ``NAME`` whose writer, on this host, is gone
(:func:`remove_stale_temporaries`).

Files beside an output (a sweep's JSON summary, a fit's figures) are written only where
none is or where tawarp wrote the one there (:func:`claim_outputs`,
:func:`written_by_tawarp`): a user's own ``res.json`` is never replaced by a summary.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import json
import os
import re
import shutil
import signal
import socket
import tempfile
import threading
from pathlib import Path

import numpy as np


@contextlib.contextmanager
def interrupts_deferred():
    """Hold SIGINT and SIGTERM back until the block ends, then deliver them to the handlers
    in place before: a Ctrl-C inside a journal append could leave the lock taken or a
    half-written line, which every later reader of the study would trip over. The handlers
    are swapped rather than the signals masked: a process-directed signal that one thread
    masks goes to another thread (Warp's CPU threads, tqdm's monitor), and Python would still
    raise it in the main thread at once. Only the main thread may set handlers; elsewhere
    this does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = []
    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        if held:
            signal.raise_signal(held[0])


@contextlib.contextmanager
def interrupt_guard():
    """``with interrupt_guard() as interrupted:`` in a long loop, call ``interrupted()`` at
    safe points (between generations): it raises KeyboardInterrupt once Ctrl-C was pressed.
    Ctrl-C still raises at once as usual; the guard remembers it because Python swallows an
    exception raised inside a weakref callback or ``__del__`` ("Exception ignored in ..."),
    and a Ctrl-C that lands there (Warp frees arrays through such callbacks) was lost: a
    design search went on running (seen under load in tests/test_design.py). Main thread
    only, and not when SIGINT is ignored (a background job); elsewhere a no-op."""
    hit = []

    def interrupted() -> None:
        if hit:
            raise KeyboardInterrupt

    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or previous in (signal.SIG_IGN, None):
        yield interrupted
        return

    def handler(signum, frame):
        hit.append(signum)
        if callable(previous):  # Python's default raises KeyboardInterrupt; a custom one runs first
            return previous(signum, frame)
        raise KeyboardInterrupt  # SIG_DFL would end the process: the nearest Python equivalent

    signal.signal(signal.SIGINT, handler)
    try:
        yield interrupted
    finally:
        signal.signal(signal.SIGINT, previous)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


#: Marks tawarp's own outputs: the ``generator`` key of a JSON object, a netCDF file's
#: ``title`` or ``generator`` attribute, a CSV's ``# generator = ...`` line, a PNG's
#: ``Software`` text, a Markdown file's :func:`markdown_mark` line (:func:`written_by_tawarp`).
GENERATOR = "tawarp"


def markdown_mark(generator: str) -> str:
    """The line that marks a Markdown file as written by ``generator`` (``"tawarp loop"``):
    an HTML comment, which the rendered text does not show."""
    return f"<!-- generator = {generator} -->"


#: The help text of an output written beside a named one (:func:`claim_outputs`).
CLAIM_HELP = " (a file there that tawarp did not write is never replaced)"


class OutputConflict(FileExistsError):
    """A file beside an output would be replaced and tawarp did not write it."""


def written_by_tawarp(path: str | Path) -> bool:
    """True when the file ``path`` carries tawarp's mark (:data:`GENERATOR`); False for
    any other file, one that cannot be read, or a folder."""
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".json":
            obj = json.loads(path.read_text())
            return isinstance(obj, dict) and str(obj.get("generator", "")).startswith(GENERATOR)
        if suffix == ".png":
            from PIL import Image

            with Image.open(path) as im:
                return str(im.info.get("Software", "")).startswith(GENERATOR)
        if suffix in (".nc", ".h5"):
            import h5py

            with h5py.File(path, "r") as f:
                return any(str(f.attrs.get(k, "")).startswith(GENERATOR) for k in ("generator", "title"))
        if suffix in (".csv", ".md"):
            mark = "#generator=" if suffix == ".csv" else "<!--generator="
            with open(path, encoding="utf-8", errors="replace") as f:
                return any(line.replace(" ", "").startswith(mark + GENERATOR) for line in f.readlines(4096))
    except Exception:  # unreadable, not of its suffix's format: not ours
        return False
    return False


def claim_outputs(*paths: str | Path, why: str = "") -> None:
    """Raise :class:`OutputConflict` for the first of ``paths`` (files a command writes
    beside its named output) that exists and that tawarp did not write; call it before
    writing anything. ``why`` says what the file would have held."""
    for p in map(Path, paths):
        if p.exists() and not written_by_tawarp(p):
            raise OutputConflict(
                errno.EEXIST,
                f"{p}: exists and tawarp did not write it; it would be replaced"
                f"{' by ' + why if why else ''}: move it away or give another -o",
            )


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Remove the temporaries (files or folders) of target ``path`` left by runs that were
    killed: those of a process of this host that no longer runs, and those named before
    the writer was part of the name. Returns what was removed."""
    path = Path(path)
    host = _host()
    removed = []
    pattern = f".{glob.escape(path.name)}.*"
    for tmp in (*path.parent.glob(pattern + ".tmp"), *path.parent.glob(pattern + ".old")):
        writer = tmp.name[len(path.name) + 2 :].split(".")[0]
        pid, at, where = writer.partition("@")
        if at and (where != host or not pid.isdigit() or _alive(int(pid))):
            continue
        if not at and len(writer) != 8:  # an older name: .NAME.XXXXXXXX.tmp (mkstemp's 8 characters)
            continue
        with contextlib.suppress(OSError):
            shutil.rmtree(tmp) if tmp.is_dir() and not tmp.is_symlink() else tmp.unlink()
            removed.append(tmp)
    return removed


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:32] or "host"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _temporary_prefix(path: Path) -> str:
    return f".{path.name}.{os.getpid()}@{_host()}."


@contextlib.contextmanager
def atomic_path(path: str | Path):
    """``with atomic_path(p) as tmp: write(tmp)``: on success ``tmp`` replaces ``p``;
    on any exception (Ctrl-C included) ``tmp`` is removed and ``p`` is untouched."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a directory; give a file name")
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=_temporary_prefix(path), suffix=".tmp")
    os.close(fd)
    # mkstemp only picks a free name; the writer creates the file: opening an existing one
    # with O_TRUNC (mode "w") makes ext4 write all its data out when it is closed
    # (auto_da_alloc): 1.6 s of a 3.1 GB sweep on the H200; a new file's data are written
    # back in the background
    os.remove(tmp)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except (OSError, RuntimeError) as e:
        reason = io_failure(e)
        if reason is None:
            raise
        kept = "the older file is kept" if path.exists() else "nothing was written"
        raise OSError(
            getattr(e, "errno", None) or errno.EIO, f"{path}: could not be written ({reason}); {kept}"
        ) from None
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


#: Room [bytes] left for a file's metadata beside its data (:func:`ensure_free_space`).
METADATA_SLACK = 1 << 20


def ensure_free_space(path: str | Path, nbytes: int) -> None:
    """Raise OSError(ENOSPC) naming ``path`` when its folder's file system has fewer than
    ``nbytes`` + :data:`METADATA_SLACK` bytes free. Called before an HDF5 write: the library
    cannot give up a file whose writing failed for want of space (its close and its exit
    handler flush again, and the process ended with SIGSEGV after the error)."""
    path = Path(path)
    folder = next(p for p in (path.parent, *path.parents) if p.exists())
    free = shutil.disk_usage(folder).free
    need = int(nbytes) + METADATA_SLACK
    if free < need:
        raise OSError(
            errno.ENOSPC,
            f"{path}: the disk has {free / 1e6:.3g} MB free and this write needs about "
            f"{need / 1e6:.3g} MB; nothing was written: free some space or write elsewhere",
        )


#: The errors that say a file cannot be written where it is (:func:`io_failure`).
WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO, errno.EFBIG}


def io_failure(e: BaseException) -> str | None:
    """The operating system's reason when ``e`` is a failed write (an OSError of
    :data:`WRITE_ERRNOS`, or h5py's RuntimeError around one: HDF5 reports a full disk as
    "... errno = 28, error message = 'No space left on device' ..."), else None (another
    error inside a writing block, a missing input file say, is not blamed on the output)."""
    code = e.errno if isinstance(e, OSError) else None
    if code is None:
        m = re.search(r"errno = (\d+)", str(e))
        code = int(m.group(1)) if m else None
    return os.strerror(code) if code in WRITE_ERRNOS else None


@contextlib.contextmanager
def atomic_dir(path: str | Path):
    """``with atomic_dir(d) as tmp: fill(tmp)``: a new folder ``tmp`` beside ``d`` that
    replaces ``d`` (and whatever it held) on success; removed on any exception, ``d``
    untouched. The swap is two renames (a folder cannot replace a non-empty one in one)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(f"{path}: exists and is not a folder")
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=_temporary_prefix(path), suffix=".tmp"))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())
        old = None
        if path.exists():
            old = Path(tempfile.mkdtemp(dir=path.parent, prefix=_temporary_prefix(path), suffix=".old"))
            os.replace(path, old / "d")
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


@contextlib.contextmanager
def hdf5_writing(f):
    """``with hdf5_writing(h5py.File(...)) as f:`` (an ``h5netcdf.File`` too): flushed and
    closed at the end; when the writing or the flush fails (a full disk, a lost
    permission), the file is discarded (:func:`discard_hdf5`) and the error raised.
    HDF5 keeps a file whose close failed open, and its exit handler, flushing it once
    more, ended the process with SIGSEGV after the error message."""
    try:
        yield f
        f.flush()
    except BaseException:
        discard_hdf5(f)
        raise
    f.close()


def discard_hdf5(f) -> None:
    """Close an open ``h5py.File`` (or ``h5netcdf.File``) without writing anything more to
    it: its file descriptor is pointed at the null device first, so that the close, which
    flushes the file's metadata, succeeds. What reached the file before stays; a SWMR
    file keeps its last flushed state."""
    h5 = getattr(f, "_h5file", f)  # h5netcdf keeps its h5py file there
    if not h5.id.valid:
        return
    fd = h5.id.get_vfd_handle()
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, fd)
    finally:
        os.close(null)
    with contextlib.suppress(Exception):
        f.close()


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
