"""Study storage of the design search: open/create Optuna studies, store evaluated
generations, query every trial, claim a worker's lineage. Optuna's public API only.

Where trials live. A study with a *trial store* (the default beside a journal file:
``study.journal`` -> ``study.trials/<study name>/``; any folder with ``store=``/
``--trial-store``) keeps every evaluated trial there, in bulk, one HDF5 file per run of
a worker (:class:`TrialStore`); the study's user attribute ``tawarp_trials`` names the
folder. The study itself keeps, through ``study.add_trials``, copies of the trials
people ask Optuna for (system attribute ``tawarp:copy``): with one objective each
generation's best feasible trial where it improves on its lineage's generations before
(so ``study.best_trial`` is the best of all), with
several each trial that joins its lineage's feasible Pareto front when evaluated (so
``study.best_trials`` is the front of all). A study without a store (a database URL or
memory, unless a store folder is given: with several machines it must be a folder they
all see) keeps every trial itself, as before. Either way :func:`trials_table` returns
every trial, and the search, :func:`best_designs`, the summary and the figures read it.

A trial in the study is stored evaluated (``optuna.trial.create_trial``), with the
system attributes ``tawarp:worker`` (its lineage), ``tawarp:generation``,
``tawarp:index`` (its place in the generation as asked) and ``constraints``
(``[T_max - T_limit]``, feasible when <= 0, as Optuna's constrained samplers store it).
The metrics are user attributes. Asked but unevaluated generations are not stored: the
samplers are deterministic, so a resumed run asks them again.

Measured on the 2-core development machine (2000 trials, journal file, Optuna 5.0):
``add_trials`` 4.0e3 trials/s on an idle disk (2.7e3 with the open lock), ``study.ask``
+ 5 ``set_user_attr`` + ``study.tell`` 82 trials/s; so every trial in Optuna caps a
search at ~4e5 evaluations/min whatever the device does, and the trial store exists. A
journal path is opened on a :class:`JournalFile` (Optuna's public backend protocol, same
file format and lock) that takes the lock and syncs once per generation.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import time
import warnings
import weakref
from pathlib import Path
from urllib.parse import quote

import numpy as np
from optuna.storages.journal import BaseJournalBackend

from ..io import discard_hdf5, ensure_free_space, hdf5_writing, interrupts_deferred, io_failure
from .objectives import directions

ATTR = "tawarp:"
COPY = ATTR + "copy"  # system attribute: the trial is a copy of a trial-store row
STORE_ATTR = "tawarp_trials"  # study user attribute: the trial store's folder


class StudyConflict(ValueError):
    """The study cannot be continued as asked (a live worker of the same name, another
    seed or batch for a worker's lineage, another design space, other objectives)."""


class JournalFile(BaseJournalBackend):
    """Optuna's journal file (``JournalFileBackend``'s format and lock: one JSON log per
    line, appended under ``JournalFileSymlinkLock``) whose appends can be grouped: inside
    ``with journal.batch():`` the lock is taken once, each append is written and flushed
    at once (a killed process loses nothing it stored; readers see it), and the file is
    synced to disk once at the end, instead of a lock and an fsync per append."""

    def __init__(self, path: str):
        from optuna.storages.journal import JournalFileBackend, JournalFileSymlinkLock

        self.path = path
        self.reader = JournalFileBackend(path)
        self.lock = JournalFileSymlinkLock(path)
        self._file = None  # open for appending while a batch holds the lock

    def read_logs(self, log_number_from: int):
        return self.reader.read_logs(log_number_from)

    def append_logs(self, logs: list) -> None:
        text = "".join(json.dumps(log, separators=(",", ":")) + "\n" for log in logs).encode("utf-8")
        if self._file is not None:
            self._write(text)
            return
        with self.batch():
            self.append_logs(logs)

    def _write(self, text: bytes) -> None:
        """Append ``text`` whole or not at all: a write that fails (a full disk) is cut
        back to the file's size before it, since a half-written line would stop every
        later reader of the study."""
        fd = self._file.fileno()
        size = os.fstat(fd).st_size  # under the lock: nobody else appends
        view = memoryview(text)
        try:
            while view:
                view = view[os.write(fd, view) :]
        except OSError as e:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, size)
            raise OSError(
                e.errno,
                f"{self.path}: could not be written ({os.strerror(e.errno) if e.errno else e}); "
                f"the trials stored before are kept",
            ) from None

    @contextlib.contextmanager
    def batch(self):
        if self._file is not None:  # already in one
            yield
            return
        with interrupts_deferred():
            self.lock.acquire()
            try:
                with open(self.path, "ab", buffering=0) as f:  # unbuffered: each append reaches the file
                    self._file = f
                    try:
                        yield
                    finally:
                        self._file = None
                        os.fsync(f.fileno())
            finally:
                self.lock.release()


#: storage -> its JournalFile (storages made by make_storage from a path)
_JOURNALS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def make_storage(storage):
    """None -> in-memory; a URL (``sqlite:///x.db``, ``postgresql://...``) -> RDB; any other
    string/path -> a journal file (created when missing); a storage object passes."""
    import optuna
    from optuna.storages import JournalStorage

    if storage is None:
        return optuna.storages.InMemoryStorage()
    if not isinstance(storage, (str, os.PathLike)):
        return storage
    s = str(storage)
    if "://" in s:
        return _rdb_storage(s)
    os.makedirs(os.path.dirname(os.path.abspath(s)), exist_ok=True)
    backend = JournalFile(s)
    st = JournalStorage(backend)
    _JOURNALS[st] = backend
    return st


def _rdb_storage(url: str):
    """Optuna's RDB storage at ``url``; a database that cannot be opened raises ValueError
    naming the URL (password hidden) and what to do."""
    import optuna
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    try:
        parsed = make_url(url)
    except (ArgumentError, ValueError) as e:
        raise ValueError(
            f"storage {url!r}: not a database URL ({e}); give sqlite:///FILE.db, "
            "postgresql://USER@HOST/DB or a journal file path"
        ) from None
    shown = parsed.render_as_string(hide_password=True)
    sqlite = parsed.get_backend_name() == "sqlite"
    if sqlite and parsed.database and parsed.database != ":memory:":
        folder = Path(parsed.database).parent
        if not folder.is_dir():
            raise ValueError(
                f"storage {shown}: the folder {str(folder)!r} of the database does not exist; "
                "create it or give another path"
            )
    kw = {"connect_args": {"timeout": 60}} if sqlite else {}
    for attempt in range(8):
        try:
            return optuna.storages.RDBStorage(url, engine_kwargs=kw)
        except Exception as e:  # workers creating a fresh database's schema at once race; retry
            if attempt == 7:
                cause = str(getattr(e, "orig", None) or e).strip().splitlines()[0]
                raise ValueError(
                    f"storage {shown}: cannot open the database ({cause}); check the URL, "
                    "that the server runs and that you may write there"
                ) from e
            time.sleep(0.2 * (attempt + 1))


def open_study(storage, study_name: str, objectives, space_description: list | None = None):
    """Load or create the Optuna study ``study_name`` in ``storage`` (see :func:`make_storage`).

    A study is bound to its objectives and, when ``space_description`` is given
    (:meth:`DesignSpace.describe`), to its design space: reopening it with others raises
    :class:`StudyConflict` naming both."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    st = make_storage(storage)
    dirs = directions(objectives)
    study = optuna.create_study(storage=st, study_name=study_name, directions=dirs, load_if_exists=True)
    if [d.name.lower() for d in study.directions] != dirs:
        raise StudyConflict(
            f"study {study_name!r} has directions {[d.name.lower() for d in study.directions]}, "
            f"objectives {list(objectives)} need {dirs}"
        )
    _bind(study, "tawarp_objectives", list(objectives), "objectives")
    if space_description is not None:
        _bind(study, "tawarp_space", space_description, "design space")
    return study


def _bind(study, key: str, value, what: str) -> None:
    prev = study.user_attrs.get(key)
    if prev is None:
        study.set_user_attr(key, value)
    elif prev != value:
        raise StudyConflict(
            f"study {study.study_name!r} was run with {what} {prev}, not {value}; "
            f"a study is bound to its {what}: give another study name or output"
        )


def bind_worker(study, worker: str, resumed: bool, **given) -> None:
    """Bind ``worker``'s lineage to what the user gave for it (``seed``, ``batch``): the
    run that starts the lineage records them in the study's user attribute
    ``tawarp_worker:NAME``; a run that resumes it (``resumed``: generations are stored)
    with others is refused, naming them. A lineage whose first run died before storing
    anything may start again with any."""
    key = f"tawarp_worker:{worker}"
    prev = study.user_attrs.get(key)
    if resumed and prev is not None and prev != given:
        was = ", ".join(f"{k} {v}" for k, v in prev.items())
        now = ", ".join(f"{k} {v}" for k, v in given.items())
        raise StudyConflict(
            f"worker {worker!r} of study {study.study_name!r} was started with {was}, not {now}: "
            f"resume it with those, or give another worker name"
        )
    if prev != given:
        study.set_user_attr(key, given)


# -- the columnar trial store ------------------------------------------------------------------
class TrialStore:
    """The columnar trial store of one study: a folder of HDF5 files, each written by one
    run of one worker (a *segment*), every evaluated generation appended to it in bulk.

    A segment has one dataset per column (``generation``, ``index``, ``failed``,
    ``constraint``, ``time`` [s since the epoch], ``params/NAME``, ``metrics/NAME``; the
    material as an index into the ``choices`` attribute) and ``committed``, the number of
    rows of complete generations. Generations are appended as: columns resized and
    written; at a commit, file flushed, then ``committed`` advanced and flushed. Readers
    read ``committed`` rows only, so they never see a generation in part, nor rows
    written since the last commit. A flush hands the
    bytes to the kernel, which keeps them whatever becomes of the writer (a killed
    process loses no committed generation) and writes them to disk in its own time: the
    store does not wait for the disk (a sync per commit made islands writing on one disk
    wait for each other's syncs: bench/README.md, section Several GPUs), so a crash of
    the machine itself may lose the generations of its last seconds.

    Why HDF5 (h5py) and not netCDF: HDF5's single-writer/multiple-reader mode (SWMR)
    orders the file's metadata writes so that the file is consistent at every moment;
    a writer killed at any point leaves every committed generation readable (but for a
    chunk index torn by the kill, :func:`torn_rows`), and readers may read while it
    writes. A segment is never reopened for writing (HDF5 refuses to reopen a file whose
    SWMR writer died without closing it), so each run of a worker starts a segment of its
    own; the reader unions them. Two workers never write one
    file, and a worker name is held by one live process at a time
    (:class:`WorkerClaim`), so no lock is needed."""

    def __init__(self, path, study_name: str):
        self.path = Path(path)
        self.study_name = study_name
        #: {segment: committed rows it lost} of the last :meth:`read` (:func:`torn_rows`)
        self.torn: dict[Path, int] = {}

    def writer(self, worker: str, first_generation: int, choices: dict, rows_per_chunk: int) -> "StoreWriter":
        """A new segment of ``worker``, starting at ``first_generation``; ``choices``:
        ``{parameter: [category names]}`` of the categorical parameters."""
        return StoreWriter(self, worker, first_generation, choices, rows_per_chunk)

    def segments(self) -> list[Path]:
        return sorted(self.path.glob("*.h5")) if self.path.is_dir() else []

    def read(self) -> dict[str, np.ndarray]:
        """Every committed row of this study's segments: ``{column: (n,) array}`` with
        ``worker``, ``generation``, ``index``, ``failed``, ``constraint``, ``time``,
        ``param:NAME`` (material names as strings) and ``metric:NAME``. A segment whose
        writer was killed while it wrote a column's chunk index (:func:`torn_rows`) gives
        the whole generations before the damage, with a :class:`StoreWarning`; :attr:`torn`
        then names it with the committed rows it lost."""
        parts = []
        self.torn = {}
        for seg in self.segments():
            with open_segment(seg) as f:
                if f.attrs["study"] != self.study_name:
                    continue
                n = int(f["committed"][0])
                columns = {k: f[k] for k in _BASE}
                columns.update({"param:" + k: ds for k, ds in f["params"].items()})
                columns.update({"metric:" + k: ds for k, ds in f["metrics"].items()})
                try:
                    cols = {k: ds[:n] for k, ds in columns.items()}
                except OSError:
                    cols = torn_rows(seg, columns, n)
                    self.torn[seg] = n - len(cols["generation"])
                for k, ds in columns.items():
                    if "choices" in ds.attrs:
                        cols[k] = np.array([str(c) for c in ds.attrs["choices"]], dtype=object)[cols[k]]
                cols["worker"] = np.full(len(cols["generation"]), str(f.attrs["worker"]), dtype=object)
            parts.append(cols)
        return _concat(parts)


class StoreWarning(UserWarning):
    """A trial store segment could not be read whole (:func:`torn_rows`)."""


#: Metadata read attempts of a reader of a segment (HDF5's default for a SWMR reader is
#: 100, each after twice the previous wait, from 1 ns): a reader racing a live writer's
#: metadata write sees it whole within microseconds, but a block a killed writer left torn
#: never heals, and the 100th attempt would come after 2^99 ns. 27 attempts wait 0.13 s in all
#: (a reader beside a live writer that still saw a torn block after them would read the rows
#: before it, with the warning, and the whole at its next read).
READ_ATTEMPTS = 27


def open_segment(path: Path):
    """A segment opened for reading beside its writer (SWMR), a torn metadata block
    (:func:`torn_rows`) raising OSError after :data:`READ_ATTEMPTS` reads. h5py does not
    wrap ``H5Pset_metadata_read_attempts``: it is called in the HDF5 library h5py loaded
    (where it is not found, HDF5's default stands)."""
    import ctypes

    import h5py
    from h5py import h5f, h5p

    fapl = h5p.create(h5p.FILE_ACCESS)
    fapl.set_libver_bounds(h5f.LIBVER_LATEST, h5f.LIBVER_LATEST)
    fapl.set_file_locking(False, True)
    try:
        attempts = ctypes.CDLL(h5p.__file__).H5Pset_metadata_read_attempts
    except (OSError, AttributeError):
        pass
    else:
        attempts.argtypes, attempts.restype = [ctypes.c_int64, ctypes.c_uint], ctypes.c_int
        attempts(fapl.id, READ_ATTEMPTS)
    return h5py.File(h5f.open(os.fsencode(path), h5f.ACC_RDONLY | h5f.ACC_SWMR_READ, fapl=fapl))


#: (segment, committed rows, rows read) of the torn segments reported: a resumed search
#: reads its store several times (the search's start, its table, its plots), and the damage
#: is told once
_TORN_REPORTED: set = set()


def torn_rows(path: Path, columns: dict, n: int) -> dict[str, np.ndarray]:
    """The whole generations of the first ``n`` rows of a segment's ``columns`` ({name:
    dataset}) that every column can still give, with a :class:`StoreWarning` naming the
    segment and the rows lost. SWMR orders a writer's metadata writes, but a SIGKILL can
    stop the kernel's copy of one write between two memory pages: a chunk-index block
    rewritten in place is left half new (its checksum never matches again), and the chunks
    it indexes, committed ones among them, cannot be found. Each column is read a chunk at a
    time up to its first unreadable one. The warning comes once per process for a segment in
    a given state (:data:`_TORN_REPORTED`)."""
    readable = {}
    for k, ds in columns.items():
        readable[k] = n
        for start in range(0, n, ds.chunks[0]):
            try:
                ds[start : min(start + ds.chunks[0], n)]
            except OSError:
                readable[k] = start
                break
    good = min(readable.values())
    generation = columns["generation"][: min(readable["generation"], good + 1)]
    if good and (len(generation) == good or generation[good] == generation[good - 1]):
        # the last generation read continues in the rows lost, or may: only whole ones are kept
        good = int(np.searchsorted(generation[:good], generation[good - 1]))
    if (str(path), n, good) not in _TORN_REPORTED:
        _TORN_REPORTED.add((str(path), n, good))
        warnings.warn(
            f"{path}: {n - good} of its {n} committed rows cannot be read (a chunk index that its writer, "
            f"killed while writing it, left torn); the {good} rows before them, whole generations, are read",
            StoreWarning,
            stacklevel=3,
        )
    return {k: ds[:good] for k, ds in columns.items()}


_BASE = ("generation", "index", "failed", "constraint", "time")


class StoreWriter:
    """Appends one worker's generations to a new segment of a :class:`TrialStore` (see
    there). The file is made on the first append, when the columns are known."""

    def __init__(self, store: TrialStore, worker: str, first_generation: int, choices: dict, rows_per_chunk: int):
        import uuid

        self.store, self.worker, self.choices = store, worker, choices
        self.chunk = int(min(max(rows_per_chunk, 64), 1 << 16))
        self.name = f"{quote(worker, safe='')}-g{first_generation:07d}-{uuid.uuid4().hex[:8]}.h5"
        self._f = None
        self._columns = None  # the segment's open datasets
        self.rows = 0  # written, committed or not
        self.failure = None  # why a write failed: the segment was closed, nothing more is written

    def append(
        self, generation, index: np.ndarray, params: dict, metrics: dict, violation, failed, commit: bool = True
    ) -> None:
        """Rows of one generation, or of several whole ones at once (one resize and write
        for all: ``generation`` then is (k,), each row's): ``index`` (k,) members,
        ``params`` {name: (k,)} (a categorical one as indices into its choices), ``metrics``
        {name: (k,)}, ``violation`` (k,) or None, ``failed`` (k,); then, with ``commit``,
        :meth:`commit`."""
        if self.failure is not None:
            raise OSError(errno.EIO, self.failure)
        k = len(index)
        cols = {
            "generation": np.array(np.broadcast_to(np.asarray(generation, dtype=np.int64), (k,))),
            "index": np.asarray(index, dtype=np.int64),
            "failed": np.asarray(failed, dtype=bool),
            "constraint": np.full(k, np.nan) if violation is None else np.asarray(violation, dtype=np.float64),
            "time": np.full(k, time.time()),
        }
        cols.update({"params/" + n: np.asarray(v) for n, v in params.items()})
        cols.update({"metrics/" + n: np.asarray(v, dtype=np.float64) for n, v in metrics.items()})
        # a new chunk of every column may be allocated; checked first because HDF5 does not
        # survive a failed write to a SWMR file (its close, or its exit handler, ends the
        # process with SIGSEGV): the except below serves a disk filled by another process
        # between this check and the write, and may not be reached
        ensure_free_space(self.store.path / self.name, sum(self.chunk * v.dtype.itemsize for v in cols.values()))
        if self._f is None:
            self._open(cols)
        n0 = self.rows
        with self._failing():
            for name, v in cols.items():
                ds = self._columns[name]
                ds.resize((n0 + k,))
                ds[n0:] = v
        self.rows = n0 + k
        if commit:
            self.commit()

    def commit(self) -> None:
        """Every row appended so far made visible to readers."""
        if self.failure is not None:
            raise OSError(errno.EIO, self.failure)
        f = self._f
        with self._failing():
            f.flush()  # the rows reach the file before the count that makes them visible
            self._columns["committed"][0] = self.rows
            f.flush()

    @contextlib.contextmanager
    def _failing(self):
        """A write to the segment: a full disk closes it (the committed generations stay
        readable: SWMR) and is raised as an OSError naming the file; nothing more is
        written to it (opened again, it would be replaced by an empty one)."""
        try:
            yield
        except (OSError, RuntimeError) as e:
            reason = io_failure(e)
            if reason is None:
                raise
            self._columns = None
            discard_hdf5(self._f)
            self._f = None
            self.failure = (
                f"{self.store.path / self.name}: the trial store could not be written ({reason}); the "
                f"generations stored before are kept"
            )
            raise OSError(getattr(e, "errno", None) or errno.EIO, self.failure) from None

    def _open(self, cols: dict) -> None:
        """Create the segment under a temporary name, open it for SWMR writing, then rename
        it: a crash before leaves no half-made segment for readers, and a reader in this
        process that opens it the moment it appears shares the writer's open file (HDF5
        refuses to open for writing a file its process holds open for reading alone;
        tests/test_design_store.py::test_a_segment_read_the_moment_it_appears_is_still_written)."""
        import h5py

        self.store.path.mkdir(parents=True, exist_ok=True)
        for stale in self.store.path.glob(f"{quote(self.worker, safe='')}-*.h5.tmp"):
            stale.unlink()  # left by an earlier run of this worker, which the claim says is gone
        path = self.store.path / self.name
        tmp = path.with_name(path.name + ".tmp")
        with hdf5_writing(h5py.File(tmp, "w", libver="latest")) as f:
            f.attrs["study"], f.attrs["worker"] = self.store.study_name, self.worker
            for name, v in cols.items():
                ds = f.create_dataset(name, shape=(0,), maxshape=(None,), chunks=(self.chunk,), dtype=v.dtype)
                base = name.partition("/")[2]
                if name.startswith("params/") and base in self.choices:
                    ds.attrs["choices"] = list(self.choices[base])
            f.create_dataset("committed", data=np.zeros(1, dtype=np.int64))
        # no chunk cache: every write appends whole chunks but the last, so a cache only
        # adds a copy; and the datasets stay open, because closing one writes its chunks
        # and metadata out at every append: together these halved a writer's time
        # (bench/README.md, "The trial store written as rows gather")
        self._f = h5py.File(tmp, "a", libver="latest", locking=False, rdcc_nbytes=0)
        self._f.swmr_mode = True
        self._columns = {name: self._f[name] for name in [*cols, "committed"]}
        try:
            os.replace(tmp, path)
        except OSError:  # not left writing to a file no reader sees
            self._columns = None
            self._f.close()
            self._f = None
            raise

    def close(self) -> None:
        if self._f is not None:
            self._columns = None
            self._f.close()
            self._f = None


def _concat(parts: list[dict]) -> dict[str, np.ndarray]:
    """Columns of several parts joined; a column missing from a part is NaN (or None) there."""
    parts = [p for p in parts if p and len(p["generation"])]
    if not parts:
        return {}
    if len(parts) == 1:  # (a store of one segment: its columns, not copies of them)
        return dict(parts[0])
    keys = list(dict.fromkeys(k for p in parts for k in p))
    out = {}
    for k in keys:
        out[k] = np.concatenate(
            [
                p[k] if k in p else np.full(len(p["generation"]), np.nan if k.startswith("metric:") else None)
                for p in parts
            ]
        )
    return out


def bind_store(study, storage, store=None) -> TrialStore | None:
    """The trial store a search run of ``study`` writes to, the study bound to it (user
    attribute ``tawarp_trials``; another folder later is refused). ``store``: a folder;
    None: the study's own, else ``<journal>.trials/<study name>`` beside a journal file
    ``storage``, else none; False: none, every trial in the study (refused for a study
    that has a store)."""
    if store is False:
        if study.user_attrs.get(STORE_ATTR):
            raise StudyConflict(
                f"study {study.study_name!r} keeps its trials in the trial store "
                f"{study.user_attrs[STORE_ATTR]}; it cannot go without one"
            )
        return None
    if store is None:
        store = study.user_attrs.get(STORE_ATTR)
        if store is None and isinstance(storage, (str, os.PathLike)) and "://" not in str(storage):
            store = Path(storage).with_suffix(".trials") / quote(study.study_name, safe="")
    if store is None:
        return None
    path = str(Path(store).resolve())
    _bind(study, STORE_ATTR, path, "trial store")
    return TrialStore(path, study.study_name)


def store_of(study, store=None) -> TrialStore | None:
    """The trial store ``study`` points to (user attribute ``tawarp_trials``), or the one
    at ``store`` (a folder; for a study copied elsewhere), or None."""
    path = store if store is not None else study.user_attrs.get(STORE_ATTR)
    return TrialStore(path, study.study_name) if path else None


def _study_rows(study, copies_as_rows: bool = False) -> tuple[dict, dict]:
    """(rows of the study's own finished trials, {(worker, generation, index): number} of
    its copies of store rows); ``copies_as_rows``: the copies are rows too."""
    from optuna.trial import TrialState

    rows, copies = [], {}
    for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE, TrialState.FAIL)):
        sa = t.system_attrs
        key = (sa.get(ATTR + "worker"), int(sa.get(ATTR + "generation", -1)), int(sa.get(ATTR + "index", -1)))
        if sa.get(COPY):
            copies[key] = t.number
        if copies_as_rows or not sa.get(COPY):
            rows.append((key, t))
    if not rows:
        return {}, copies
    ts = [t for _, t in rows]
    cols = {
        "worker": np.array([k[0] for k, _ in rows], dtype=object),
        "generation": np.array([k[1] for k, _ in rows], dtype=np.int64),
        "index": np.array([k[2] for k, _ in rows], dtype=np.int64),
        "failed": np.array([t.state == TrialState.FAIL for t in ts]),
        "constraint": np.array([t.system_attrs.get("constraints", [np.nan])[0] for t in ts], dtype=np.float64),
        "time": np.array([t.datetime_complete.timestamp() if t.datetime_complete else np.nan for t in ts]),
        "number": np.array([t.number for t in ts], dtype=np.int64),
    }
    for name in dict.fromkeys(k for t in ts for k in t.params):
        vals = [t.params.get(name) for t in ts]
        cols["param:" + name] = np.array(vals, dtype=object if any(isinstance(v, str) for v in vals) else np.float64)
    for name in dict.fromkeys(k for t in ts for k in t.user_attrs):
        cols["metric:" + name] = np.array([t.user_attrs.get(name, np.nan) for t in ts], dtype=np.float64)
    return cols, copies


def copies_in_study(study) -> dict[tuple, int]:
    """``{(worker, generation, index): Optuna number}`` of the study's copies of store rows."""
    return _study_rows(study)[1]


def _rows(study, store=None, copies: bool = False) -> dict[str, np.ndarray]:
    """Every evaluated trial of ``study`` as columns (see :func:`trials_table`); with
    ``copies``, the study's own trials and its copies of trial-store rows alone (the
    trial store is not read)."""
    own, numbers = _study_rows(study, copies_as_rows=copies)
    ts = None if copies else store_of(study, store)
    stored = ts.read() if ts is not None else {}
    if stored:
        stored["number"] = _copy_numbers(stored, numbers)
    cols = _concat([stored, own])
    if cols and not _in_evaluation_order(cols):
        order = np.lexsort((cols["index"], cols["generation"], cols["worker"].astype(str), cols["time"]))
        cols = {k: v[order] for k, v in cols.items()}
    return cols


def _in_evaluation_order(cols: dict) -> bool:
    """Whether the rows are in evaluation order (by time, then worker, generation and
    index: :func:`np.lexsort`'s order of those keys, the worker by name), as a lone
    worker's store is: checked between neighbours, whose workers are compared only where
    their times are equal (the sort's string keys took seconds per 1e7 rows)."""
    t, g, j = cols["time"], cols["generation"], cols["index"]
    if np.any(t[1:] < t[:-1]) or np.any(np.isnan(t)):
        return False
    tie = np.flatnonzero(t[1:] == t[:-1])
    w = cols["worker"]
    same = w[tie] == w[tie + 1]
    if not np.all(same):
        return False
    before = (g[tie] < g[tie + 1]) | ((g[tie] == g[tie + 1]) & (j[tie] <= j[tie + 1]))
    return bool(np.all(before))


def _member_ids(g, index) -> np.ndarray:
    """Ids of members ``index`` of generation(s) ``g``, unique in a lineage: g 2^32 + index."""
    return (np.asarray(g, dtype=np.int64) << np.int64(32)) + np.asarray(index, dtype=np.int64)


def _copy_numbers(stored: dict, numbers: dict) -> np.ndarray:
    """The Optuna number of each trial-store row's copy in the study, -1 where it has
    none; ``numbers``: ``{(worker, generation, index): number}``. Matched by sorted keys,
    worker by worker: a store holds millions of rows and a study a few hundred copies, and
    a lookup per row took a second per 3e6 rows."""
    out = np.full(len(stored["generation"]), -1, dtype=np.int64)
    by_worker = {}
    for (w, g, j), number in numbers.items():
        by_worker.setdefault(w, []).append((_member_ids(g, j), number))
    for w, pairs in by_worker.items():
        rows = np.flatnonzero(stored["worker"] == w)
        if not rows.size:
            continue
        keys, nums = np.array(pairs, dtype=np.int64).T
        order = np.argsort(keys)
        keys, nums = keys[order], nums[order]
        row_keys = _member_ids(stored["generation"][rows], stored["index"][rows])
        at = np.minimum(np.searchsorted(keys, row_keys), len(keys) - 1)
        hit = keys[at] == row_keys
        out[rows[hit]] = nums[at[hit]]
    return out


def trials_table(study, store=None):
    """Every evaluated (COMPLETE or FAIL) trial of a design study, as an
    ``xarray.Dataset`` along the dimension ``trial`` in evaluation order: the rows of its
    trial store (:class:`TrialStore`, the folder the study's user attribute
    ``tawarp_trials`` names, or ``store``) and the trials the study holds itself (those
    of a study without a store: a database URL or memory, or Optuna's own samplers).

    Variables: ``worker``, ``generation``, ``index`` (place in the generation as asked;
    -1 for Optuna's samplers), ``number`` (the Optuna trial number of the trial, or of
    its copy in the study; -1 for a row without one), ``state`` (COMPLETE or FAIL),
    ``constraint`` (``T_max - T_limit`` [K], feasible when <= 0; NaN without a limit),
    ``time`` [s since the epoch, UTC], one variable per design parameter (attribute
    ``role = "parameter"``) and per metric (``role = "metric"``, objective values
    included: the objective's name is a metric). ``attrs``: ``objectives``,
    ``parameters``, ``metrics``, ``store``."""
    import xarray as xr

    cols = _rows(study, store)
    ts = store_of(study, store)
    ds = xr.Dataset(
        attrs={
            "study": study.study_name,
            "objectives": list(study.user_attrs.get("tawarp_objectives", [])),
            "store": str(ts.path) if ts is not None else "",
        }
    )
    if not cols:
        cols = {
            "worker": np.zeros(0, object),
            "generation": np.zeros(0, np.int64),
            "index": np.zeros(0, np.int64),
            "number": np.zeros(0, np.int64),
            "failed": np.zeros(0, bool),
            "constraint": np.zeros(0),
            "time": np.zeros(0),
        }
    ds["worker"] = ("trial", np.array(cols["worker"], dtype=str))
    for k in ("generation", "index", "number"):
        ds[k] = ("trial", cols[k])
    ds["state"] = ("trial", np.where(cols["failed"].astype(bool), "FAIL", "COMPLETE"))
    for k in ("constraint", "time"):
        ds[k] = ("trial", cols[k].astype(np.float64))
    params, metrics = [], []
    for k, v in cols.items():
        role, _, name = k.partition(":")
        if role not in ("param", "metric"):
            continue
        if name in ds:
            raise ValueError(f"trials_table: {role} {name!r} has the name of another column")
        ds[name] = ("trial", np.array(v, dtype=str) if v.dtype == object else v)
        ds[name].attrs["role"] = "parameter" if role == "param" else "metric"
        (params if role == "param" else metrics).append(name)
    ds.attrs["parameters"], ds.attrs["metrics"] = params, metrics
    return ds


def lineage(study, worker: str, store=None) -> dict[int, dict[str, np.ndarray]]:
    """The worker's evaluated trials by generation: ``{generation: {column: (k,) array}}``
    (the columns of :func:`trials_table`'s internal rows: ``index``, ``failed``,
    ``constraint``, ``param:NAME``, ``metric:NAME``, ...), members in index order."""
    cols = _rows(study, store)
    if not cols:
        return {}
    sel = np.flatnonzero((cols["worker"] == worker) & (cols["generation"] >= 0))
    sel = sel[np.lexsort((cols["index"][sel], cols["generation"][sel]))]
    gens, starts = np.unique(cols["generation"][sel], return_index=True)
    bounds = list(starts) + [len(sel)]
    return {int(g): {k: v[sel[bounds[i] : bounds[i + 1]]] for k, v in cols.items()} for i, g in enumerate(gens)}


def add_evaluated(
    study,
    storage,
    points: list[dict],
    distributions: dict,
    values: np.ndarray,
    metrics: list[dict],
    violation: np.ndarray | None,
    failed: np.ndarray,
    system_attrs: list[dict],
) -> None:
    """Store evaluated design points as finished trials of ``study`` in ``storage``:
    COMPLETE with ``values`` (n, m) (FAIL where ``failed``), metrics as user attributes,
    ``constraints`` = [violation]. A journal made by :func:`make_storage` is locked and
    synced to disk once for all."""
    from optuna.trial import TrialState, create_trial

    trials = []
    for j, p in enumerate(points):
        sa = dict(system_attrs[j])
        if violation is not None:
            sa["constraints"] = [float(violation[j])]
        ok = not failed[j]
        trials.append(
            create_trial(
                state=TrialState.COMPLETE if ok else TrialState.FAIL,
                values=[float(x) for x in values[j]] if ok else None,
                params=p,
                distributions={k: distributions[k] for k in p},
                user_attrs=metrics[j],
                system_attrs=sa,
            )
        )
    with journal_batch(storage):
        study.add_trials(trials)


def journal_batch(storage):
    """A context in which a journal made by :func:`make_storage` is locked and synced to
    disk once for all appends (a no-op for other storages)."""
    journal = _JOURNALS.get(storage)
    return journal.batch() if journal is not None else contextlib.nullcontext()


def best_designs(
    study,
    objectives,
    T_limit,
    k: int = 1,
    store=None,
    per: str | None = None,
    copies: bool = False,
    worker: str | None = None,
) -> list[dict]:
    """Best feasible trials of all (:func:`trials_table`): the ``k`` best for one
    objective (``per``: the best of each value of that parameter, e.g. ``"material"``),
    the Pareto front for several. Each: ``number`` (Optuna's, None for a trial with no
    copy in the study), ``params``, ``values`` {objective: value}, ``metrics``,
    ``worker``, ``generation``, ``index``. ``copies``: among the study's trials and its
    copies alone, without reading the trial store: the same best (``k = 1``, no ``per``)
    and front for a study of batched searches with ``T_limit`` theirs, whose copies are
    the best feasible member of every generation that improved its lineage's best
    (several objectives: the members that joined their lineage's front), so every other
    trial is beaten by one of them. ``worker``:
    among that worker's trials alone (its lineage)."""
    from .objectives import signs
    from .samplers import pareto_mask

    cols = _rows(study, store, copies)
    if not cols:
        return []
    ok = ~cols["failed"].astype(bool)
    if worker is not None:
        ok &= cols["worker"] == worker
    if T_limit is not None:
        ok &= np.nan_to_num(cols["constraint"].astype(np.float64), nan=0.0) <= 0
    sel = np.flatnonzero(ok)
    if not sel.size:
        return []
    F = np.stack([cols["metric:" + o][sel].astype(np.float64) for o in objectives], axis=1) * signs(objectives)
    if len(objectives) == 1:
        order = np.argsort(F[:, 0], kind="stable")
        if per is not None:
            first = np.unique(cols["param:" + per][sel][order].astype(str), return_index=True)[1]
            order = order[np.sort(first)]
    else:
        order = np.flatnonzero(pareto_mask(F))
        order = order[np.argsort(F[order, 0], kind="stable")]
    pnames = [c for c in cols if c.startswith("param:")]
    mnames = [c for c in cols if c.startswith("metric:")]
    out, seen = [], set()
    for i in sel[order]:
        params = {c[6:]: (v if isinstance(v, str) else float(v)) for c in pnames if (v := cols[c][i]) is not None}
        key = tuple(sorted((k2, str(v)) for k2, v in params.items()))
        if key in seen:
            continue
        seen.add(key)
        num = int(cols["number"][i])
        out.append(
            {
                "number": num if num >= 0 else None,
                "params": params,
                "values": {o: float(cols["metric:" + o][i]) for o in objectives},
                "metrics": {c[7:]: float(cols[c][i]) for c in mnames},
                "worker": cols["worker"][i],
                "generation": int(cols["generation"][i]),
                "index": int(cols["index"][i]),
            }
        )
        if len(objectives) == 1 and len(out) >= k:
            break
    return out


def study_summary(study, store=None) -> dict:
    """Counts of all evaluated trials (:func:`trials_table`) by state and by worker;
    ``unique``: no (worker, generation, index) twice; ``in_study``: trials Optuna holds
    (copies included); ``store``: the trial store's folder or None."""
    from collections import Counter

    cols = _rows(study, store)
    n = len(cols.get("generation", ()))
    keys = list(zip(cols["worker"], cols["generation"].tolist(), cols["index"].tolist())) if n else []
    lineage_keys = [k for k in keys if k[1] >= 0]
    ts = store_of(study, store)
    return {
        "trials": n,
        "states": dict(Counter(np.where(cols["failed"].astype(bool), "FAIL", "COMPLETE").tolist())) if n else {},
        "workers": dict(Counter(cols["worker"].tolist())) if n else {},
        "unique": len(set(lineage_keys)) == len(lineage_keys),
        "in_study": len(study.get_trials(deepcopy=False)),
        "store": str(ts.path) if ts is not None else None,
    }


class WorkerClaim:
    """This process's claim on the lineage ``worker`` of ``study_name``: a RUNNING trial in
    the companion study ``"{study_name}#worker={worker}"``. The storage orders trials
    atomically, so of several processes claiming one name the earliest claim whose owner
    lives wins and the others are refused (:class:`StudyConflict`), whatever the timing.
    An owner lives while its process runs (same host) or while its heartbeat, renewed
    every generation, is younger than ``stale_after`` [s] (other hosts)."""

    def __init__(self, storage, study_name: str, worker: str, stale_after: float = 3600.0):
        import optuna
        import socket
        import uuid
        from optuna.trial import TrialState, create_trial

        self.storage, self.stale_after = storage, stale_after
        self.host = socket.gethostname()
        self.owner = f"{self.host}:{os.getpid()}:{uuid.uuid4().hex[:12]}"
        name = f"{study_name}#worker={worker}"
        self.claims = optuna.create_study(storage=storage, study_name=name, load_if_exists=True)
        self.claims.add_trial(
            create_trial(state=TrialState.RUNNING, user_attrs={"owner": self.owner, "heartbeat": time.time()})
        )
        running = sorted(self.claims.get_trials(deepcopy=False, states=(TrialState.RUNNING,)), key=lambda t: t.number)
        mine = next(t for t in running if t.user_attrs.get("owner") == self.owner)
        self.number = mine.number
        self.trial_id = storage.get_trial_id_from_study_id_trial_number(
            storage.get_study_id_from_name(name), self.number
        )
        live = [t for t in running if t.number < self.number and self._alive(t)]
        if live:
            self.release(failed=True)
            raise StudyConflict(
                f"worker {worker!r} of study {study_name!r} is running in another live process "
                f"({live[0].user_attrs.get('owner')}); give this run another worker name"
            )

    def _alive(self, t) -> bool:
        owner = t.user_attrs.get("owner")
        if owner is None:  # attributes not visible yet: a claim being written is a live one
            return True
        host, _, rest = owner.partition(":")
        pid = rest.partition(":")[0]
        if host == self.host and pid.isdigit():
            try:
                os.kill(int(pid), 0)
            except ProcessLookupError:
                return False
            except PermissionError:
                return True
            return True
        return time.time() - float(t.user_attrs.get("heartbeat", 0.0)) < self.stale_after

    def heartbeat(self) -> None:
        self.storage.set_trial_user_attr(self.trial_id, "heartbeat", time.time())

    def release(self, failed: bool = False) -> None:
        from optuna.trial import TrialState

        self.claims.tell(self.number, state=TrialState.FAIL) if failed else self.claims.tell(self.number, 0.0)
