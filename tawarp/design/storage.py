"""Study storage of the design search: open/create Optuna studies, store evaluated
generations, find a worker's lineage. Optuna's public API only.

A trial is stored once, evaluated (``study.add_trials`` of
``optuna.trial.create_trial``: one journal append per trial), with the system attributes
``tawarp:worker`` (its lineage), ``tawarp:generation``, ``tawarp:index`` (its place in
the generation as asked) and ``constraints`` (``[T_max - T_limit]``, feasible when
<= 0, as Optuna's constrained samplers store it). The metrics are user attributes.
Asked but unevaluated generations are not stored: the samplers are deterministic, so a
resumed run asks them again.

Measured on the 2-core development machine (2000 trials, journal file, Optuna 5.0):
``add_trials`` 4.0e3 trials/s on an idle disk (2.7e3 with the open lock), ``study.ask``
+ 5 ``set_user_attr`` + ``study.tell`` 82 trials/s. ``add_trials`` appends (and fsyncs)
once per trial, which a busy disk slows to ~300 trials/s; so a journal path is opened
on a :class:`JournalFile` (Optuna's public backend protocol, same file format and lock)
that takes the lock and syncs once per generation, as the search did before.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
import weakref

import numpy as np
from optuna.storages.journal import BaseJournalBackend

from .objectives import directions

ATTR = "tawarp:"


class StudyConflict(ValueError):
    """The study cannot be continued as asked (a live worker of the same name, another
    batch, another design space, other objectives)."""


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
            self._file.write(text)
            self._file.flush()
            return
        with self.batch():
            self.append_logs(logs)

    @contextlib.contextmanager
    def batch(self):
        if self._file is not None:  # already in one
            yield
            return
        self.lock.acquire()
        try:
            with open(self.path, "ab") as f:
                self._file = f
                try:
                    yield
                finally:
                    self._file = None
                    f.flush()
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
        kw = {"connect_args": {"timeout": 60}} if s.startswith("sqlite") else {}
        for attempt in range(8):
            try:
                return optuna.storages.RDBStorage(s, engine_kwargs=kw)
            except Exception:  # workers creating a fresh database's schema at once race; retry
                if attempt == 7:
                    raise
                time.sleep(0.2 * (attempt + 1))
    os.makedirs(os.path.dirname(os.path.abspath(s)), exist_ok=True)
    backend = JournalFile(s)
    st = JournalStorage(backend)
    _JOURNALS[st] = backend
    return st


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
        raise StudyConflict(f"study {study_name!r} has directions {[d.name.lower() for d in study.directions]}, "
                            f"objectives {list(objectives)} need {dirs}")
    _bind(study, "tawarp_objectives", list(objectives), "objectives")
    if space_description is not None:
        _bind(study, "tawarp_space", space_description, "design space")
    return study


def _bind(study, key: str, value, what: str) -> None:
    prev = study.user_attrs.get(key)
    if prev is None:
        study.set_user_attr(key, value)
    elif prev != value:
        raise StudyConflict(f"study {study.study_name!r} was run with {what} {prev}, not {value}; "
                            f"a study is bound to its {what}: give another study name or output")


def lineage(study, worker: str) -> dict[int, dict[int, object]]:
    """The worker's stored trials: ``{generation: {index: FrozenTrial}}``."""
    gens: dict[int, dict[int, object]] = {}
    for tr in study.get_trials(deepcopy=False):
        if tr.system_attrs.get(ATTR + "worker") == worker and ATTR + "generation" in tr.system_attrs:
            gens.setdefault(int(tr.system_attrs[ATTR + "generation"]), {})[int(tr.system_attrs[ATTR + "index"])] = tr
    return gens


def add_evaluated(study, storage, points: list[dict], distributions: dict, values: np.ndarray, metrics: list[dict],
                  violation: np.ndarray | None, failed: np.ndarray, system_attrs: list[dict]) -> None:
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
        trials.append(create_trial(state=TrialState.COMPLETE if ok else TrialState.FAIL,
                                   values=[float(x) for x in values[j]] if ok else None,
                                   params=p, distributions={k: distributions[k] for k in p},
                                   user_attrs=metrics[j], system_attrs=sa))
    journal = _JOURNALS.get(storage)
    with journal.batch() if journal is not None else contextlib.nullcontext():
        study.add_trials(trials)


def best_designs(study, objectives, T_limit, k: int = 1) -> list[dict]:
    """Best feasible trials: the ``k`` best for one objective, the Pareto front for several.
    Each: ``number``, ``params``, ``values`` {objective: value}, ``metrics`` (user attrs),
    ``worker``."""
    from optuna.trial import TrialState

    from .objectives import signs
    from .samplers import pareto_mask

    trials = list(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)))
    if T_limit is not None:
        trials = [t for t in trials if t.system_attrs.get("constraints", [0.0])[0] <= 0]
    if not trials:
        return []
    F = np.array([t.values for t in trials]) * signs(objectives)
    if len(objectives) == 1:
        order = np.argsort(F[:, 0], kind="stable")[:k]
    else:
        order = np.flatnonzero(pareto_mask(F))
        order = order[np.argsort(F[order, 0], kind="stable")]
    out, seen = [], set()
    for i in order:
        t = trials[i]
        key = tuple(sorted((k2, str(v)) for k2, v in t.params.items()))
        if key in seen:
            continue
        seen.add(key)
        out.append({"number": t.number, "params": dict(t.params),
                    "values": {o: float(v) for o, v in zip(objectives, t.values)},
                    "metrics": dict(t.user_attrs), "worker": t.system_attrs.get(ATTR + "worker")})
    return out


def study_summary(study) -> dict:
    """Counts of trials by state and by worker, numbers unique (for checks and reports)."""
    from collections import Counter

    trials = study.get_trials(deepcopy=False)
    return {"trials": len(trials), "states": dict(Counter(t.state.name for t in trials)),
            "workers": dict(Counter(t.system_attrs.get(ATTR + "worker") for t in trials)),
            "unique_numbers": len({t.number for t in trials}) == len(trials)}


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
        self.claims.add_trial(create_trial(state=TrialState.RUNNING, user_attrs={"owner": self.owner,
                                                                                 "heartbeat": time.time()}))
        running = sorted(self.claims.get_trials(deepcopy=False, states=(TrialState.RUNNING,)), key=lambda t: t.number)
        mine = next(t for t in running if t.user_attrs.get("owner") == self.owner)
        self.number = mine.number
        self.trial_id = storage.get_trial_id_from_study_id_trial_number(
            storage.get_study_id_from_name(name), self.number)
        live = [t for t in running if t.number < self.number and self._alive(t)]
        if live:
            self.release(failed=True)
            raise StudyConflict(f"worker {worker!r} of study {study_name!r} is running in another live process "
                                f"({live[0].user_attrs.get('owner')}); give this run another worker name")

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
