"""The columnar trial store of design studies (tawarp.design.storage.TrialStore,
trials_table): every evaluated trial queryable with the values a direct evaluation
gives, crash safety of the appends, resume without duplicates."""

from __future__ import annotations

import functools
import math
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import optuna
import pytest
from processes import reaped, released
from study_copies import improving_generations

from tawarp.design.evaluate import Evaluator
from tawarp.design.search import search
from tawarp.design.space import DesignSpace
from tawarp.design.storage import StoreWarning, TrialStore, open_study, study_summary, trials_table
from tawarp.model.core import load_core

ROOT = Path(__file__).resolve().parents[1]
VARS = ["material=ceramic,rvc_foam", "stack.length=0.005:0.1", "heat_input=1:30", "hot_hx.length=0.005:0.03"]


def _space():
    return DesignSpace(load_core("rvc_foam"), VARS)


def _keys(ds) -> list[tuple]:
    return list(zip(ds.worker.values.tolist(), ds.generation.values.tolist(), ds["index"].values.tolist()))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_trial_is_queryable_with_the_values_of_a_direct_evaluation(tmp_path, seed):
    """N trials of a search with the temperature limit active: the table returns N rows,
    each (worker, generation, index) once, and every metric equals a fresh evaluation
    of the table's design points to 1e-12 (relative); the gradient and T_hot of a few
    rows equal the exact piecewise heat solution of the reference (1e-9). The study
    holds a copy of each generation's best feasible trial that beats the generations
    before, so Optuna's best trial is the best of all."""
    from tawarp.reference import heat_profile_exact

    space = _space()
    res = search(space, n_trials=96, batch=16, storage=str(tmp_path / "s.journal"), seed=seed, T_limit=420.0)
    ds = trials_table(res.study)
    assert ds.sizes["trial"] == 96 and len(set(_keys(ds))) == 96
    assert sorted(ds.attrs["parameters"]) == sorted(["material", "stack.length", "heat_input", "hot_hx.length"])
    assert np.any(ds.constraint.values > 0) and np.any(ds.constraint.values <= 0)  # the limit is active
    values = {k: ds[k].values for k in ds.attrs["parameters"]}
    direct = Evaluator(space, extra=("gradient",)).evaluate(values)
    for k in ds.attrs["metrics"]:
        np.testing.assert_allclose(ds[k].values, direct[k], rtol=1e-12, atol=0, err_msg=k)
    np.testing.assert_allclose(ds.constraint.values, direct["T_max"] - 420.0, rtol=1e-12, atol=1e-12)
    i = space.stack_index
    for j in np.random.default_rng(seed).choice(96, 3, replace=False):
        core, q = space.core_for({k: ds[k].values[j].item() for k in ds.attrs["parameters"]})
        x = core.positions()
        sol = heat_profile_exact(core, q)
        g = (sol.theta_in(i, x[i + 1]) - sol.theta_in(i, x[i])) / (x[i + 1] - x[i])
        assert ds.gradient.values[j] == pytest.approx(float(g), rel=1e-9)
        assert ds.T_hot.values[j] - core.gas.T_cold == pytest.approx(float(sol.theta_in(i, x[i + 1])), rel=1e-9)
    feasible = ds.constraint.values <= 0
    best = np.max(ds.gradient.values[feasible])
    assert res.study.best_trial.values[0] == best == res.best[0]["values"]["gradient"]
    assert study_summary(res.study)["in_study"] == len(res.study.trials) == len(improving_generations(ds))


@pytest.mark.parametrize("seed", [3, 4])
def test_several_objectives_the_study_holds_the_pareto_front(tmp_path, seed):
    """Two objectives: every trial of the table is in the store, and the study's copies
    contain the feasible Pareto front of all trials (Optuna's best_trials is that
    front), while holding fewer trials than were evaluated."""
    from tawarp.design.samplers import pareto_mask

    res = search(
        _space(),
        ("gradient", "heat_leak"),
        n_trials=256,
        batch=32,
        storage=str(tmp_path / "m.journal"),
        seed=seed,
        T_limit=450.0,
    )
    ds = trials_table(res.study)
    assert ds.sizes["trial"] == 256 and len(set(_keys(ds))) == 256
    ok = (ds.constraint.values <= 0) & (ds.state.values == "COMPLETE")
    F = np.stack([-ds.gradient.values[ok], ds.heat_leak.values[ok]], axis=1)
    front = {tuple(f) for f in F[pareto_mask(F)]}
    held = {(-t.values[0], t.values[1]) for t in res.study.best_trials}
    assert held == front
    assert len(front) <= len(res.study.trials) < 256
    assert {(-b["values"]["gradient"], b["values"]["heat_leak"]) for b in res.best} == front


_CRASH = """
import os, sys
import h5py
from tawarp.model.core import load_core
from tawarp.design.space import DesignSpace
from tawarp.design import search as S
from tawarp.design.storage import StoreWriter
journal, where, gen = sys.argv[1], sys.argv[2], int(sys.argv[3])
if where == "store":  # die (no close, no flush) after the first column of generation `gen` is written
    append = StoreWriter.append
    def dying_append(self, g, *a, **k):
        if g == gen:
            setitem = h5py.Dataset.__setitem__
            def die(ds, key, value):
                setitem(ds, key, value)
                os._exit(3)
            h5py.Dataset.__setitem__ = die
        return append(self, g, *a, **k)
    StoreWriter.append = dying_append
else:  # die at the run's end, every generation in the store, before copy number `gen` reaches the study
    copy, copied = S._Run.copy_to_study, []
    def dying_copy(self, g, *a, **k):
        if len(copied) == gen:
            os._exit(3)
        copied.append(g)
        return copy(self, g, *a, **k)
    S._Run.copy_to_study = dying_copy
space = DesignSpace(load_core("rvc_foam"), %r)
S.search(space, n_trials=64, batch=8, storage=journal, seed=7)
""" % (VARS,)


@pytest.mark.parametrize("where,gen", [("store", 1), ("store", 3), ("study", 2)])
@pytest.mark.filterwarnings("ignore:The value of `grace_period` might be too small:UserWarning")  # (1 s on purpose)
def test_a_crash_mid_generation_loses_only_that_generation(tmp_path, monkeypatch, where, gen):
    """A process dies inside the write of generation ``gen`` (after its first column
    reached the file, the file never closed) or, at the run's end, while copying the
    generations' best into the study (before its copy number ``gen``): the generations
    stored are readable, exactly as an uninterrupted run makes them, the one being written
    is invisible; the resumed run completes the lineage with every (generation, index)
    once and the study with one copy per generation that improved on those before."""
    journal = str(tmp_path / "c.journal")
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run(
        [sys.executable, "-c", _CRASH, journal, where, str(gen)], env=env, capture_output=True, text=True, timeout=180
    )
    assert p.returncode == 3, p.stdout + p.stderr
    # a death inside a commit leaves the journal's lock behind: the resumed run breaks it
    # after Optuna's grace period, here 1 s instead of 30 (the same path, shorter)
    lock = optuna.storages.journal.JournalFileSymlinkLock
    monkeypatch.setattr(optuna.storages.journal, "JournalFileSymlinkLock", functools.partial(lock, grace_period=1))
    ref = trials_table(search(_space(), n_trials=64, batch=8, seed=7).study)  # in memory, never interrupted
    names = ["material", "stack.length", "heat_input", "hot_hx.length", "gradient", "T_max", "heat_leak"]

    def same_as_ref(ds):
        k, kr = _keys(ds), _keys(ref)
        assert len(set(k)) == len(k) and set(k) <= set(kr)
        at = {key: j for j, key in enumerate(kr)}
        rows = [at[key] for key in k]
        for n in names:
            if ds[n].dtype.kind in "US":
                assert (ds[n].values == ref[n].values[rows]).all()
            else:
                np.testing.assert_allclose(ds[n].values, ref[n].values[rows], rtol=1e-12, atol=0, err_msg=n)

    study = open_study(journal, "tawarp-design", ["gradient"])
    after = trials_table(study)
    committed = gen if where == "store" else 8  # "study": every generation stored before the copies
    assert sorted(set(after.generation.values.tolist())) == list(range(committed))
    assert after.sizes["trial"] == 8 * committed
    same_as_ref(after)
    # the copies come at a run's end, generation by generation: those before the death
    assert len(study.trials) == (0 if where == "store" else gen)
    res = search(_space(), n_trials=64, batch=8, storage=journal, seed=7)
    assert res.resumed == 0
    ds = trials_table(res.study)
    assert ds.sizes["trial"] == 64 and len(set(_keys(ds))) == 64
    same_as_ref(ds)
    copies = [(t.system_attrs["tawarp:generation"], t.system_attrs["tawarp:index"]) for t in res.study.trials]
    assert len(improving_generations(ref)) > 2  # (the death at copy 2 above happened before the last copy)
    assert sorted(g for g, _ in copies) == improving_generations(ref)
    # one file per run that stored trials (a resume with nothing to evaluate stores none)
    assert len(list((tmp_path / "c.trials" / "tawarp-design").glob("*.h5"))) == (2 if where == "store" else 1)


_WRITER = """
import sys
import numpy as np
from tawarp.design.storage import TrialStore
store, start, per_commit = TrialStore(sys.argv[1], "s"), int(sys.argv[2]), int(sys.argv[3])
w = store.writer("w", start, {"material": ["a", "b"]}, 512)
for g in range(start, start + 10**6):
    k = np.arange(512)
    commit = (g - start + 1) % per_commit == 0
    w.append(g, k, {"x": g + k / 512.0, "material": k % 2}, {"y": np.full(512, float(g))}, -k / 1.0, k == 7, commit)
    if commit:
        print(g, flush=True)
"""


@pytest.mark.parametrize("delay,per_commit", [(0.3, 1), (0.7, 1), (1.3, 1), (0.7, 3)])
def test_a_store_killed_at_any_moment_keeps_whole_generations(tmp_path, delay, per_commit):
    """SIGKILL at an arbitrary moment of a writer appending generations of known content
    as fast as it can (most of its time inside HDF5 writes), committing every
    ``per_commit``-th: what readers see, while it writes and after, is whole generations
    0..G-1 up to the last commit, every value exact, every generation whose commit had
    returned among them (the store does not sync to disk: what it flushed is the
    kernel's) and none appended since; a second run of the worker continues in a new
    file from G; the union has each (generation, index) once."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))

    def run(start, wait):
        with reaped(
            subprocess.Popen(
                [sys.executable, "-c", _WRITER, str(tmp_path), str(start), str(per_commit)],
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
        ) as (p,):
            first = p.stdout.readline()  # the first commit returned: the writer is under way
            assert first.strip() == str(start + per_commit - 1), first
            time.sleep(wait)
            while_writing = check()  # a reader beside the live writer
            p.send_signal(signal.SIGKILL)
            p.wait()
            committed = int(([first] + p.stdout.read().split())[-1])  # the last commit that returned
        assert while_writing >= start + per_commit
        assert check() >= committed + 1

    def check():
        store = TrialStore(tmp_path, "s")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", StoreWarning)  # (told once; store.torn says it each read)
            cols = store.read()
        torn = store.torn
        g = cols["generation"]
        gens = np.unique(g)
        assert np.array_equal(gens, np.arange(len(gens))) and len(g) == 512 * len(gens)
        k = cols["index"]
        assert len(set(zip(g.tolist(), k.tolist()))) == len(g)
        np.testing.assert_array_equal(cols["param:x"], g + k / 512.0)
        np.testing.assert_array_equal(cols["param:material"], np.where(k % 2, "b", "a"))
        np.testing.assert_array_equal(cols["metric:y"], g.astype(float))
        np.testing.assert_array_equal(cols["constraint"], -k / 1.0)
        np.testing.assert_array_equal(cols["failed"], k == 7)
        assert len(gens) % per_commit == 0 or torn  # (each run starts at a commit)
        # a chunk index the kill tore (test_a_torn_chunk_index_gives_the_whole_generations_before_it)
        # loses the generations after it: reported, and counted as if none were committed
        return len(gens) if not torn else math.inf

    run(0, delay)
    n1 = check()
    if n1 == math.inf:  # torn: the second run would start inside the first one's lost rows
        return
    run(n1, delay / 2)
    n2 = check()
    assert n2 > n1 >= 1


def test_a_torn_chunk_index_gives_the_whole_generations_before_it(tmp_path):
    """A writer killed while the kernel copied a chunk-index block left it half written
    (its checksum wrong for good): the reader waited on HDF5's doubling retries for ever.
    Here the last index block of the file is torn by hand: the read takes well under a
    second and gives every whole generation before the damage, exact, naming the file and
    the rows lost in a StoreWarning, once however often the store is read."""
    import re

    store = TrialStore(tmp_path, "s")
    w = store.writer("w", 0, {"material": ["a", "b"]}, 64)
    for g in range(300):
        k = np.arange(64)
        w.append(g, k, {"x": g + k / 64.0, "material": k % 2}, {"y": np.full(64, float(g))}, -k / 1.0, k == 7)
    w.close()
    (seg,) = store.segments()
    image = bytearray(seg.read_bytes())
    block = [m.start() for m in re.finditer(b"EADB", image)][-1]  # an extensible array's data block
    image[block + 20] ^= 0xFF
    seg.write_bytes(bytes(image))
    start = time.monotonic()
    with pytest.warns(StoreWarning, match=re.escape(str(seg))) as caught:
        cols = store.read()
    assert time.monotonic() - start < 10.0
    g, k = cols["generation"], cols["index"]
    n = len(np.unique(g))
    assert 1 <= n < 300 and np.array_equal(np.unique(g), np.arange(n)) and len(g) == 64 * n
    np.testing.assert_array_equal(cols["param:x"], g + k / 64.0)
    np.testing.assert_array_equal(cols["param:material"], np.where(k % 2, "b", "a"))
    np.testing.assert_array_equal(cols["metric:y"], g.astype(float))
    assert f"{64 * (300 - n)} of its 19200 committed rows" in str(caught[0].message)
    # a resumed search reads its store again (its table, its plots): the same rows, told once
    with warnings.catch_warnings(record=True) as again:
        warnings.simplefilter("always")
        cols2 = store.read()
    assert not [w for w in again if issubclass(w.category, StoreWarning)]
    assert store.torn == {seg: 64 * (300 - n)}
    for k in cols:
        np.testing.assert_array_equal(cols2[k], cols[k])


def test_rows_written_between_commits_are_invisible_until_the_commit(tmp_path, monkeypatch):
    """A search whose trial store is written as rows are gathered (every two generations
    here) and committed once, at its end: each append leaves the committed count where the
    last commit put it, so readers see none of those rows until the commit; the store then
    holds the trials of a search that stores every generation as it goes, bit for bit."""
    import tawarp.design.search as S
    from tawarp.design.storage import StoreWriter

    append, seen = StoreWriter.append, []

    def recorded(self, *a, commit=True, **k):
        append(self, *a, commit=commit, **k)
        seen.append((len(a[1]), commit, int(self._f["committed"][0])))

    monkeypatch.setattr(S, "WRITE_ROWS", 16)
    monkeypatch.setattr(StoreWriter, "append", recorded)
    kw = dict(n_trials=12 * 8, batch=8, seed=5)
    res = search(_space(), storage=str(tmp_path / "a.journal"), commit_seconds=1e9, **kw)
    assert seen == [(16, False, 0)] * 6
    seen.clear()
    ref = search(_space(), storage=str(tmp_path / "b.journal"), commit_seconds=0, **kw)
    assert seen == [(8, True, 8 * (g + 1)) for g in range(12)]
    a, b = trials_table(res.study), trials_table(ref.study)
    assert a.sizes["trial"] == 96
    for k in a.data_vars:
        if k != "time":
            np.testing.assert_array_equal(a[k].values, b[k].values, err_msg=k)


def test_a_segment_whose_write_failed_is_closed_and_keeps_its_commits(tmp_path, monkeypatch):
    """A full disk during an append: the error names the segment, the generations
    committed before stay readable, and the writer refuses every later append or commit
    (opened again, the segment would be replaced by an empty one)."""
    import errno

    import h5py

    w = TrialStore(tmp_path, "s").writer("w", 0, {}, 64)
    k = np.arange(64)
    w.append(0, k, {"x": k / 64.0}, {"y": k * 2.0}, None, k == 3)
    setitem = h5py.Dataset.__setitem__

    def full(self, *a):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(h5py.Dataset, "__setitem__", full)
    with pytest.raises(OSError, match=r"w-g0000000-\w+\.h5: the trial store could not be written \(No space"):
        w.append(1, k, {"x": k / 64.0}, {"y": k * 2.0}, None, k == 3, commit=False)
    monkeypatch.setattr(h5py.Dataset, "__setitem__", setitem)
    for later in (lambda: w.append(2, k, {"x": k / 64.0}, {"y": k * 2.0}, None, k == 3), w.commit):
        with pytest.raises(OSError, match="could not be written"):
            later()
    w.close()
    cols = TrialStore(tmp_path, "s").read()
    np.testing.assert_array_equal(cols["generation"], np.zeros(64))
    np.testing.assert_array_equal(cols["metric:y"], k * 2.0)


def test_interrupt_inside_a_journal_append_is_delivered_after_it(tmp_path):
    """A SIGINT that arrives while a journal batch holds the lock is held back until the
    batch has written, synced and released the lock: the journal stays whole and unlocked,
    and the KeyboardInterrupt comes right after the block."""
    import os
    import signal
    import threading

    import pytest

    from tawarp.design.storage import JournalFile

    path = str(tmp_path / "j.journal")
    journal = JournalFile(path)
    # another thread alive, as Warp's CPU threads and tqdm's monitor are in a search: the
    # kernel may hand the signal to it, and it must still wait for the batch
    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    other.start()
    with released(stop, other), pytest.raises(KeyboardInterrupt):
        with journal.batch():
            journal.append_logs([{"op_code": 0, "a": 1}])
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C in the middle of the batch
            journal.append_logs([{"op_code": 0, "a": 2}])
        raise AssertionError("the interrupt must arrive as soon as the batch ends")
    assert [log["a"] for log in journal.read_logs(0)] == [1, 2]
    assert not os.path.lexists(path + ".lock")  # lock released
    with journal.batch():  # and can be taken again at once
        journal.append_logs([{"op_code": 0, "a": 3}])
    assert [log["a"] for log in journal.read_logs(0)] == [1, 2, 3]


def test_store_rows_get_the_numbers_of_their_copies_in_the_study():
    """Each trial-store row gets the Optuna number of the study's copy with its (worker,
    generation, index), -1 where the study has none: the sorted-key match equals a
    lookup row by row, over workers, repeated rows and copies of rows the store lacks."""
    from tawarp.design.storage import _copy_numbers

    rng = np.random.default_rng(3)
    n = 5000
    stored = {
        "worker": rng.choice(np.array(["island0", "island1", "w/2"], dtype=object), n),
        "generation": rng.integers(0, 40, n),
        "index": rng.integers(0, 64, n),
    }
    keys = list(zip(stored["worker"], stored["generation"].tolist(), stored["index"].tolist()))
    numbers = {k: 1000 + i for i, k in enumerate(dict.fromkeys(keys[j] for j in rng.integers(0, n, 300)))}
    numbers.update({("island0", 3, 64): 1, ("island9", 0, 0): 2, (None, -1, -1): 3, ("island1", 41, 0): 4})
    expected = np.array([numbers.get(k, -1) for k in keys])
    got = _copy_numbers(stored, numbers)
    np.testing.assert_array_equal(got, expected)
    assert (got >= 1000).sum() > 300  # (repeated rows share a copy)
    np.testing.assert_array_equal(_copy_numbers(stored, {}), np.full(n, -1))


def test_rows_found_in_evaluation_order_are_those_the_sort_leaves_in_place():
    """A study's rows are sorted by time, worker, generation and index unless the check
    between neighbours finds them in that order: whenever it does, the sort would leave
    them in place, and it does for a lone worker's store, whose rows come in that order."""
    from tawarp.design.storage import _in_evaluation_order

    rng = np.random.default_rng(5)

    def table(n, workers, times):
        return {
            "time": rng.choice(times, n),
            "worker": rng.choice(np.array(workers, dtype=object), n),
            "generation": rng.integers(0, 4, n),
            "index": rng.integers(0, 8, n),
        }

    def lexsorted(cols):
        order = np.lexsort((cols["index"], cols["generation"], cols["worker"].astype(str), cols["time"]))
        return {k: v[order] for k, v in cols.items()}

    found = 0
    for trial in range(300):
        workers = ["island0", "island1", "w"][: 1 + trial % 3]
        times = np.array([1.0, 2.0, 3.0, np.nan][: 2 + trial % 3])
        cols = table(int(rng.integers(2, 40)), workers, times)
        for c in (cols, lexsorted(cols)):
            if _in_evaluation_order(c):
                found += 1
                order = np.lexsort((c["index"], c["generation"], c["worker"].astype(str), c["time"]))
                np.testing.assert_array_equal(order, np.arange(len(order)))
        if len(workers) == 1 and not np.isnan(times).any():
            assert _in_evaluation_order(lexsorted(cols))
    assert found > 100


def test_a_segment_read_the_moment_it_appears_is_still_written(tmp_path, monkeypatch):
    """Islands run as threads of one process read the store while others write it: a reader
    that opens a new segment the moment it appears (before its writer's own open, once
    seen in a distributed islands test) must not stop its writer, since HDF5 refuses a
    file for writing that its process holds open for reading alone."""
    import tawarp.design.storage as S

    replace, readers = os.replace, []

    def seen_at_once(src, dst):
        replace(src, dst)
        if str(dst).endswith(".h5"):
            readers.append(S.open_segment(Path(dst)))

    monkeypatch.setattr(S.os, "replace", seen_at_once)
    w = TrialStore(tmp_path, "s").writer("w", 0, {}, 64)
    k = np.arange(64)
    w.append(0, k, {"x": k / 64.0}, {"y": k * 2.0}, None, k == 3)
    assert len(readers) == 1 and int(readers[0]["committed"][0]) in (0, 64)
    for f in readers:
        f.close()
    w.close()
    cols = TrialStore(tmp_path, "s").read()
    np.testing.assert_array_equal(cols["metric:y"], k * 2.0)


def test_a_segment_that_cannot_be_renamed_is_not_written_unseen(tmp_path, monkeypatch):
    """A failed rename of a new segment raises, and the writer is left writing no file that
    readers cannot see: its next append makes the segment again, and the store reads it."""
    import errno

    import tawarp.design.storage as S

    replace = os.replace

    def failing(src, dst):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(S.os, "replace", failing)
    w = TrialStore(tmp_path, "s").writer("w", 0, {}, 64)
    k = np.arange(64)
    with pytest.raises(OSError, match="Input/output error"):
        w.append(0, k, {"x": k / 64.0}, {"y": k * 2.0}, None, k == 3)
    monkeypatch.setattr(S.os, "replace", replace)
    assert TrialStore(tmp_path, "s").segments() == []
    w.append(0, k, {"x": k / 64.0}, {"y": k * 2.0}, None, k == 3)
    w.close()
    np.testing.assert_array_equal(TrialStore(tmp_path, "s").read()["metric:y"], k * 2.0)
