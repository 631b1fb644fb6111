"""Batched fits, sweeps and design evaluations spread over Dask workers
(tawarp.distributed) equal a single-process run: here on a local cluster of two CPU
worker processes, the same code that runs one worker per GPU."""

from __future__ import annotations

import os
import pickle
import sys
import time

import numpy as np
import pytest

pytest.importorskip("distributed")

from tawarp import reference  # noqa: E402
from tawarp.design.evaluate import Evaluator  # noqa: E402
from tawarp.design.search import search  # noqa: E402
from tawarp.design.space import DesignSpace  # noqa: E402
from tawarp.distributed import (  # noqa: E402
    ClusterEvaluator,
    fit_on_cluster,
    local_cluster,
    ordered_map,
    worker_addresses,
)
from tawarp.fit.estimate import fit  # noqa: E402
from tawarp.model.core import load_core  # noqa: E402

FREQS = np.linspace(30.0, 500.0, 8)


@pytest.fixture(scope="module")
def client():
    # in-process workers (threads): the same scheduling and code as worker processes;
    # test_worker_processes_sweep_and_evaluate_as_one_process and test_task_arguments_pickle
    # cover what processes add (pickling)
    c = local_cluster(["cpu", "cpu"], processes=False)
    yield c
    cluster = c.cluster
    c.close()
    cluster.close()


def _space():
    return DesignSpace(load_core("rvc_foam"), ["stack.length=0.004:0.1", "heat_input=1:9", "hot_hx.length=0.005:0.03"])


def test_workers_get_their_devices_and_results_come_in_order(client):
    from tawarp.distributed import worker_settings

    workers = worker_addresses(client, fresh=True)
    settings = client.gather([client.submit(worker_settings, None, workers=[w], pure=False) for w in workers])
    assert [s.device for s in settings] == ["cpu", "cpu"] and all(s.cpu_threads >= 1 for s in settings)
    assert worker_settings(None).device is None  # outside a worker: unchanged
    # more chunks than the window: gathered in submission order whatever finishes first
    assert list(ordered_map(client, lambda x, k: x * k, range(20), 3, window=3)) == [3 * x for x in range(20)]


def test_fit_on_cluster_equals_one_process(client):
    # Geometry fits (Q = 0) of noisy reference data (not the fitted model's), starts
    # 10-30 % off; 5 problems in chunks of 2 over 2 workers vs one call.
    core = load_core("mesh")
    names = ["stack.porosity", "stack.pore_radius", "stack.tortuosity"]
    Y0 = reference.dimensionless_transfer(core, FREQS, 0.0)
    rng = np.random.default_rng(0)
    sd = 0.005 * np.abs(Y0) / np.sqrt(2)
    Y = Y0 + sd * (rng.standard_normal((5,) + Y0.shape) + 1j * rng.standard_normal((5,) + Y0.shape))
    truth = np.array([core.get(k) for k in names])
    start = truth * rng.uniform(0.7, 1.3, (5, 3))
    kw = dict(weights=np.broadcast_to(1 / sd, Y.shape), warn=False)
    one = fit(core, FREQS, Y, names, start, device="cpu", **kw)
    many = fit_on_cluster(client, core, FREQS, Y, names, start, chunk=2, **kw)
    assert one.converged.all() and many.converged.all()
    for f in ("values", "std", "cost", "covariance", "rms_error"):
        np.testing.assert_allclose(getattr(many, f), getattr(one, f), rtol=1e-12, atol=0, err_msg=f)
    assert np.array_equal(many.iterations, one.iterations) and many.evaluations == one.evaluations
    # a spread of starts (no start given) with restarts: the per-problem extras join in order too
    kw.update(weights=kw["weights"][:3], n_starts=4, restarts=2)
    one = fit(core, FREQS, Y[:3], names, device="cpu", **kw)
    many = fit_on_cluster(client, core, FREQS, Y[:3], names, chunk=2, **kw)
    for f in ("values", "std", "restart_values", "restart_cost", "distinct_minima"):
        np.testing.assert_allclose(getattr(many, f), getattr(one, f), rtol=1e-12, atol=0, err_msg=f)
    assert many.problem_warnings == one.problem_warnings


def _geometry_problems(n: int):
    """(core, names, Y (n, m, 4), sd, start): noisy reference data of the mesh core at
    Q = 0 (real noise, 0.5 %), the start 20 % off."""
    core = load_core("mesh")
    names = ["stack.porosity", "stack.pore_radius"]
    Y0 = reference.dimensionless_transfer(core, FREQS, 0.0)
    sd = 0.005 * np.abs(Y0) / np.sqrt(2)
    Y = Y0 + sd * np.random.default_rng(2).standard_normal((n,) + Y0.shape)
    return core, names, Y, sd, np.array([core.get(k) for k in names]) * [1.2, 0.8]


def test_fit_of_data_on_the_workers_equals_one_process(client):
    # chunks of data made on the workers (futures): each fitted where it lies, in the
    # list's order; the start and the weights given once hold for every problem
    core, names, Y, sd, start = _geometry_problems(5)
    one = fit(core, FREQS, Y, names, start, weights=1 / sd, device="cpu", warn=False)
    workers = worker_addresses(client, fresh=True)
    chunks = [client.scatter([{"Y": Y[lo:hi]}], workers=[w])[0] for (lo, hi), w in zip([(0, 3), (3, 5)], workers)]
    many = fit_on_cluster(client, core, FREQS, chunks, names, start, weights=1 / sd, warn=False)
    for f in ("values", "std", "cost", "covariance"):
        np.testing.assert_allclose(getattr(many, f), getattr(one, f), rtol=1e-12, atol=0, err_msg=f)
    assert np.array_equal(many.iterations, one.iterations) and many.converged.all()
    # the chunks' sizes given, as the caller that made the data knows them: no query first
    sized = fit_on_cluster(client, core, FREQS, chunks, names, start, weights=1 / sd, warn=False, sizes=[3, 2])
    assert np.array_equal(sized.values, many.values) and np.array_equal(sized.cost, many.cost)
    with pytest.raises(ValueError, match="holds 3 problems, not 2"):
        fit_on_cluster(client, core, FREQS, chunks, names, start, weights=1 / sd, warn=False, sizes=[2, 3])
    with pytest.raises(ValueError, match="every problem"):
        fit_on_cluster(client, core, FREQS, chunks, names, np.tile(start, (5, 1)))


def test_design_evaluations_on_cluster_equal_one_process(client):
    space = _space()
    rng = np.random.default_rng(1)
    values = space.from_unit(rng.random((50, 3)))
    one = Evaluator(space, extra=["acoustic_loss"], settings=None).evaluate(values)
    many = ClusterEvaluator(client, space, extra=["acoustic_loss"], chunk=16).evaluate(values)
    assert set(many) == set(one)
    for k in one:
        np.testing.assert_allclose(many[k], one[k], rtol=1e-12, atol=0, err_msg=k)


def test_sobol_evaluations_drawn_on_the_workers_equal_one_process(client):
    # the workers draw the points of their chunks on their devices: the objectives of
    # points 5 .. 54 of the space's Sobol sequence, as one process evaluates them
    from tawarp.design.space import DeviceTable

    space = DesignSpace(load_core("rvc_foam"), ["stack.length=0.004:0.1", "material=ceramic,mesh", "heat_input=1:9"])
    ev = Evaluator(space, extra=["acoustic_loss"])
    one = ev.evaluate_table(DeviceTable(space, ev.device).sobol(5, 55, 7)[0])
    many = ClusterEvaluator(client, space, extra=["acoustic_loss"], chunk=16).evaluate_sobol(50, seed=7, first=5)
    assert set(many) == set(one) and all(np.array_equal(many[k], one[k], equal_nan=True) for k in one)
    assert np.isfinite(one["gradient"]).all()


def test_search_on_cluster_equals_one_process(client):
    one = search(_space(), n_trials=32, batch=16, seed=4)
    many = search(_space(), n_trials=32, batch=16, seed=4, client=client)
    a = [(t.params, t.values) for t in one.study.trials]
    b = [(t.params, t.values) for t in many.study.trials]
    assert a == b


@pytest.mark.parametrize("objectives", [("gradient",), ("gradient", "heat_leak")])
def test_islands_equal_the_islands_run_one_after_another(client, tmp_path, objectives):
    # an island per worker, each its own lineage of the one study: the same trials (points,
    # values, generation and member) and the same best as running island0 then island1 in
    # one process; CMA-ES and NSGA-II
    from tawarp.design.storage import best_designs, trials_table
    from tawarp.design.islands import search_islands

    kw = dict(objectives=objectives, n_trials=48, batch=16, seed=4)
    for name in ("island0", "island1"):
        search(_space(), worker=name, storage=str(tmp_path / "one.journal"), **kw)
    many = search_islands(client, _space(), storage=str(tmp_path / "many.journal"), **kw)
    assert [t["worker"] for t in many.timing["islands"]] == ["island0", "island1"]
    assert many.timing["evaluations"] == 2 * 48
    from tawarp.design.storage import open_study

    one = open_study(str(tmp_path / "one.journal"), "tawarp-design", objectives, _space().binding())

    def rows(study):
        t = trials_table(study)
        keys = zip(t["worker"].values.tolist(), t["generation"].values.tolist(), t["index"].values.tolist())
        cols = [t[c].values.tolist() for c in [*t.attrs["parameters"], *t.attrs["metrics"]]]
        return sorted((k, tuple(c[j] for c in cols)) for j, k in enumerate(keys))

    a, b = rows(one), rows(many.study)
    assert len(a) == 2 * 48 and a == b
    best = best_designs(one, objectives, 673.0)
    assert [d["values"] for d in best] == [d["values"] for d in many.best] and best
    for island in many.timing["islands"]:  # each island's own best: its lineage's
        mine = best_designs(one, objectives, 673.0, worker=island["worker"])
        assert island["best"] == [d["values"] for d in mine] and mine
        # and in the study, where its summary was merged
        merged = best_designs(many.study, objectives, 673.0, copies=True, worker=island["worker"])
        if len(objectives) == 1:
            assert [d["values"] for d in merged] == island["best"]
        else:  # the study's front of both islands' fronts: this island's members on it
            assert all(d["values"] in island["best"] for d in merged)


def test_islands_write_their_own_journals_and_merge_their_summaries(client, tmp_path, monkeypatch):
    # each island keeps its claim, heartbeat and copies in a journal of its own: the study's
    # journal holds no island's claim (the companion studies "STUDY#worker=...") and, once
    # merged, each island's improvements of its best, strictly better generation after
    # generation, ending at its best; run again with more trials, the islands resume from
    # their journals and the merge adds what is new, nothing twice; the trials are those of
    # the islands run one after another
    import optuna

    from tawarp.design import islands
    from tawarp.design.islands import island_journal, search_islands
    from tawarp.design.storage import copies_in_study, lineage, make_storage, open_study, trials_table

    storage = str(tmp_path / "study.journal")
    kw = dict(n_trials=64, batch=16, seed=4)
    first = search_islands(client, _space(), storage=storage, **kw)
    assert optuna.get_all_study_names(make_storage(storage)) == ["tawarp-design"]
    for name in ("island0", "island1"):
        own = make_storage(str(island_journal(storage, "tawarp-design", name)))
        assert f"tawarp-design#worker={name}" in optuna.get_all_study_names(own)
    stored = {name: sorted(lineage(first.study, name)) for name in ("island0", "island1")}
    again = search_islands(client, _space(), storage=storage, **dict(kw, n_trials=128))
    ran = {i["worker"]: {k: i[k] for k in ("evaluations", "resumed")} for i in again.timing["islands"]}
    assert again.timing["evaluations"] == 2 * 64, f"islands run {ran}; generations stored before {stored}"
    assert first.timing["merged"] > 0
    copies = copies_in_study(again.study)
    assert len(set(copies)) == len(copies) == len(again.study.trials)
    for island in again.timing["islands"]:
        name = island["worker"]
        gens = lineage(again.study, name)
        assert sorted(gens) == list(range(128 // 16))
        bests = [np.nanmax(np.where(g["constraint"] <= 0, g["metric:gradient"], np.nan)) for g in gens.values()]
        mine = sorted((g, j) for w, g, j in copies if w == name)
        kept = [bests[g] for g, _ in mine]
        assert kept and np.all(np.diff(kept) > 0) and kept[-1] == max(bests) == island["best"][0]["gradient"]
        improved = [g for g in range(len(bests)) if bests[g] > max(bests[:g], default=-np.inf)]
        assert [g for g, _ in mine] == improved and len(improved) > 2
        # at most SUMMARY_COPIES of them, the latest (read from the island's own journal)
        monkeypatch.setattr(islands, "SUMMARY_COPIES", 2)
        own = open_study(str(island_journal(storage, "tawarp-design", name)), "tawarp-design", ("gradient",))
        assert islands.island_summary(own, name, ("gradient",), 673.0)["generation"].tolist() == improved[-2:]
        monkeypatch.undo()
    for name in ("island0", "island1"):
        search(_space(), worker=name, storage=str(tmp_path / "one.journal"), **dict(kw, n_trials=128))
    one = trials_table(open_study(str(tmp_path / "one.journal"), "tawarp-design", ("gradient",), _space().binding()))
    many = trials_table(again.study)
    key = ["worker", "generation", "index"]
    a = one.sortby([one[k] for k in key])
    b = many.sortby([many[k] for k in key])
    for v in ["worker", "generation", "index", *one.attrs["parameters"], *one.attrs["metrics"]]:
        assert a[v].values.tolist() == b[v].values.tolist(), v


@pytest.mark.parametrize(
    "mode, outputs, parts",
    [
        ("sobol", None, False),
        ("grid", None, False),
        ("sobol", ["gradient", "acoustic_loss"], False),
        ("sobol", None, True),
        ("grid", ["gradient", "acoustic_loss"], True),
    ],
)
def test_sweep_on_cluster_equals_one_process(client, tmp_path, mode, outputs, parts):
    # the workers make the chunks' tables (grid indices, Sobol points) on their devices and
    # send back the float32 outputs and a Sobol chunk's design values, or write them to part
    # files that the file maps (parts=True): the same file, bit for bit; a material variable
    # (int8 in a Sobol file, labels in a grid) and objectives outside the kernel
    # (acoustic_loss: float64 on the host, rounded by the worker) too
    import shutil

    import xarray as xr

    from tawarp.design.sweep import parts_path, sweep

    space = DesignSpace(
        load_core("rvc_foam"), ["stack.length=0.01:0.08:4", "material=ceramic,mesh,rvc_foam", "heat_input=1:9:3"]
    )
    kw = dict(
        mode=mode, n_samples=96, seed=2, outputs=outputs, chunk=8 if mode == "grid" else 20
    )  # grid: hyperslabs of 2 x 3 points
    one = sweep(space, tmp_path / "one.nc", **kw)
    if parts:  # over an older sweep of other chunks, whose parts go
        sweep(space, tmp_path / "many.nc", client=client, parts=True, **{**kw, "seed": 5, "chunk": 3})
    many = sweep(space, tmp_path / "many.nc", client=client, parts=parts, **kw)
    assert many.chunks == one.chunks > 2
    assert parts_path(many.path).is_dir() == parts
    if parts:  # the file and its folder moved together (the file names its parts relative to itself)
        assert len(list(parts_path(many.path).iterdir())) == many.chunks
        (tmp_path / "moved").mkdir()
        for p in (many.path, parts_path(many.path)):
            shutil.move(p, tmp_path / "moved" / p.name)
    with (
        xr.open_dataset(tmp_path / "one.nc", engine="h5netcdf") as x,
        xr.open_dataset(tmp_path / ("moved" if parts else ".") / "many.nc", engine="h5netcdf") as y,
    ):
        xr.testing.assert_identical(x, y)
        assert x["gradient"].size == one.n_points and np.isfinite(x["gradient"].values).all()


def test_worker_processes_sweep_and_evaluate_as_one_process(tmp_path, monkeypatch, request):
    # the path of GPU workers: tasks and results pickled between processes (the job, the
    # int8 material of a Sobol file, float32 outputs, float64 objectives); ~5 s here. The
    # shared files in a tmpfs folder of this test's own: other processes of the host may
    # hold theirs in /dev/shm meanwhile
    import os
    import shutil
    import tempfile
    from pathlib import Path

    import xarray as xr

    from tawarp import distributed
    from tawarp.design.space import DeviceTable
    from tawarp.design.sweep import sweep

    shared = tempfile.mkdtemp(prefix="tawarp-test-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None)
    request.addfinalizer(lambda: shutil.rmtree(shared, ignore_errors=True))
    monkeypatch.setattr(distributed, "SHARED_FOLDERS", (shared,))

    space = DesignSpace(
        load_core("rvc_foam"), ["stack.length=0.01:0.08", "material=ceramic,mesh,rvc_foam", "heat_input=1:9"]
    )
    values = space.from_unit(np.random.default_rng(3).random((40, 2)))
    values["material"] = np.arange(40) % 3
    from tawarp.design.islands import search_islands

    reduced = dict(mode="sobol", n_samples=96, chunk=20, seed=2, reduce="best,quantiles,pareto,top=5", raw=False)
    procs = local_cluster(["cpu", "cpu"], processes=True)
    try:
        # each worker a process of its own that sees no GPU (a GPU worker: its GPU alone)
        seen = procs.run(lambda: (os.getpid(), os.environ["CUDA_VISIBLE_DEVICES"]))
        assert len({pid for pid, _ in seen.values()} | {os.getpid()}) == 3
        assert [v for _, v in seen.values()] == ["", ""]

        def faults():
            import resource

            before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            for _ in range(20):
                np.ones(1 << 17)  # (1 MB, freed before the next)
            return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

        # a worker keeps the memory it frees (keep_freed_memory): twenty 1 MB arrays in turn
        # fault their 256 pages in once, not twenty times (Dask's 64 kB trim threshold)
        if sys.platform == "linux":
            assert all(f < 5 * 256 for f in procs.run(faults).values())
        # and drops its mappings of shared files once their pool has unlinked them
        checks = procs.run(lambda dask_worker: dask_worker.periodic_callbacks["tawarp-housekeeping"].is_running())
        assert list(checks.values()) == [True, True]
        many = ClusterEvaluator(procs, space, chunk=16).evaluate(values)
        # Sobol points drawn on the workers, their objectives written in shared memory
        drawn = ClusterEvaluator(procs, space, extra=["acoustic_loss"], chunk=16)
        assert drawn.shared
        drawn.warm_up()
        sobol = drawn.evaluate_sobol(50, seed=7, first=5)
        # chunks of two pages of points and a shorter last one: a file each, mapped as one;
        # the files of a result let go are written again by a later call (the workers copy
        # into their kept mappings), never those of a result still held
        pooled = ClusterEvaluator(procs, space, chunk=2 * 4096)
        paged = pooled.evaluate_sobol(2 * 2 * 4096 + 50, seed=3, first=1)
        pooled.evaluate_sobol(2 * 2 * 4096 + 50, seed=4, first=1)  # (let go at once)
        again = pooled.evaluate_sobol(2 * 2 * 4096 + 50, seed=5, first=1)
        assert len(pooled._files._files) == 2 * 3  # (three chunks a call: the second's files reused)
        assert {os.path.dirname(p) for p in pooled._files._files} == {shared}
        pooled.close()
        sweep(space, tmp_path / "many.nc", mode="sobol", n_samples=96, chunk=20, seed=2, client=procs)
        sweep(space, tmp_path / "parts.nc", mode="sobol", n_samples=96, chunk=20, seed=2, client=procs, parts=True)
        reduced_many = sweep(space, tmp_path / "reduced_many.nc", client=procs, **reduced)
        islands = search_islands(procs, _space(), storage=str(tmp_path / "islands.journal"), n_trials=32, batch=16)
        # fits of data made on the worker processes: the results pickled back and joined
        core, names, Y, sd, start = _geometry_problems(4)
        workers = worker_addresses(procs, fresh=True)
        chunks = [procs.scatter([{"Y": Y[lo:hi]}], workers=[w])[0] for (lo, hi), w in zip([(0, 1), (1, 4)], workers)]
        fitted = fit_on_cluster(procs, core, FREQS, chunks, names, start, weights=1 / sd, warn=False)
    finally:
        cluster = procs.cluster
        procs.close()
        cluster.close()
    one = Evaluator(space).evaluate(values)
    assert set(many) == set(one) and all(np.array_equal(many[k], one[k]) for k in one)
    ev = Evaluator(space, extra=["acoustic_loss"])
    one = ev.evaluate_table(DeviceTable(space, ev.device).sobol(5, 55, 7)[0])
    assert set(sobol) == set(one) and all(np.array_equal(sobol[k], one[k], equal_nan=True) for k in one)
    for got, seed in ((paged, 3), (again, 5)):
        one = Evaluator(space).evaluate_table(DeviceTable(space, ev.device).sobol(1, 1 + 4 * 4096 + 50, seed)[0])
        assert set(got) == set(one) and all(np.array_equal(got[k], one[k], equal_nan=True) for k in one)
    assert not list(Path(shared).glob("*"))  # the shared files went at once
    sweep(space, tmp_path / "one.nc", mode="sobol", n_samples=96, chunk=20, seed=2)
    for name in ("many.nc", "parts.nc"):  # parts: written by the worker processes
        with (
            xr.open_dataset(tmp_path / "one.nc", engine="h5netcdf") as x,
            xr.open_dataset(tmp_path / name, engine="h5netcdf") as y,
        ):
            xr.testing.assert_identical(x, y)
    # the reductions' states and the islands' results pickled back from the processes
    assert reduced_many.reductions == sweep(space, tmp_path / "reduced_one.nc", **reduced).reductions
    one = fit(core, FREQS, Y, names, start, weights=1 / sd, device="cpu", warn=False)
    for f in ("values", "std", "cost", "covariance"):
        np.testing.assert_allclose(getattr(fitted, f), getattr(one, f), rtol=1e-12, atol=0, err_msg=f)
    for name, island in zip(("island0", "island1"), islands.timing["islands"]):
        alone = search(_space(), n_trials=32, batch=16, worker=name)
        assert island["worker"] == name and island["best"] == [d["values"] for d in alone.best]
    with pytest.raises(ValueError, match="parts=True.*client="):
        sweep(space, tmp_path / "no.nc", mode="sobol", n_samples=8, parts=True)
    assert not (tmp_path / "no.nc").exists()


def test_cluster_sweep_sends_no_table(client, tmp_path, monkeypatch):
    # a sweep task's arguments are its point range and the job (space, outputs, settings: a
    # few kB), whatever the chunk: a table of 2048 points (3 rows, float64) would be 48 kB

    from tawarp.design.sweep import sweep

    sizes = []
    submit = client.submit

    def spy(func, *args, **kw):
        sizes.append(len(pickle.dumps(args)))
        return submit(func, *args, **kw)

    monkeypatch.setattr(client, "submit", spy)
    space = _space()
    sweep(space, tmp_path / "s.nc", mode="sobol", n_samples=4096, chunk=2048, client=client)
    assert max(sizes) < 8 * 1024 and len(sizes) == 2, sizes
    assert space.varying_table(space.from_unit(np.zeros((2048, 3)))).nbytes == 48 * 1024


def test_worker_threads_keep_their_own_state(client):
    # worker threads of one process (processes=False) each build their own Evaluator on
    # their own device: the state of a job is per worker, not per process
    import threading

    from tawarp.distributed import worker_settings, worker_state

    def state(key):
        return worker_state(key, lambda: (worker_settings(None).device, threading.get_ident(), object()))

    workers = worker_addresses(client, fresh=True)
    built = client.gather([client.submit(state, "job", workers=[w], pure=False) for w in workers])
    again = client.gather([client.submit(state, "job", workers=[w], pure=False) for w in workers])
    assert built[0][1] != built[1][1] and built[0][2] is not built[1][2]  # two threads, two objects
    assert all(a[2] is b[2] for a, b in zip(built, again))  # kept between tasks


def _here(i, scale):
    from distributed import get_worker

    if i < 0:
        raise ValueError(f"task {i} failed")
    return i * scale, get_worker().address


def test_tasks_sent_at_once_go_to_their_workers_and_their_errors_are_raised(client):
    # submit_all: every task in one message, each on the worker given for it, in order; a
    # worker not there: another takes its task; wait_all raises a task's error
    from tawarp.distributed import submit_all, wait_all

    workers = worker_addresses(client)
    assert len(workers) == 2 and workers == sorted(client.nthreads())
    where = [workers[i % 2] for i in range(6)] + ["tcp://127.0.0.1:9"]  # (no worker listens there)
    futures = submit_all(client, _here, range(7), 10, workers=where)
    wait_all(futures)
    done = client.gather(futures)
    assert [v for v, _ in done] == [10 * i for i in range(7)] and [w for _, w in done[:6]] == where[:6]
    assert done[6][1] in workers
    with pytest.raises(ValueError, match="task -1 failed"):
        wait_all(submit_all(client, _here, [1, -1, 2], 1))


def test_the_workers_are_all_listed_while_the_client_refreshes_its_scheduler_info(client):
    # the client's periodic refresh of its copy of the scheduler's identity asks for no
    # worker's and may overwrite the copy scheduler_info() is about to return, listing no
    # workers (search_islands then ran no island); worker_addresses asks its own question.
    # Refreshed every millisecond here, as a busy host may delay the caller's thread
    import dask
    from distributed import Client

    with dask.config.set({"distributed.client.scheduler-info-interval": "1ms"}):
        busy = Client(client.scheduler.address, timeout=30)
    try:
        listed = [len(worker_addresses(busy, fresh=True)) for _ in range(200)]
    finally:
        busy.close()
    assert listed == [2] * 200


def test_fit_data_is_known_again_by_its_memory_while_it_lives():
    # what lock_for_uploads page-locks on a GPU worker: the memory of data fitted a second
    # time (a worker's own data, fitted again), not data that arrives anew with each fit
    import gc

    from tawarp.distributed import _FITTED, fitted_again

    a = np.zeros((4, 3), dtype=complex)
    assert fitted_again(a[1:]) is None  # the first fit of this memory
    assert fitted_again(a[:2]) is a and fitted_again(a) is a  # again, through any view
    assert fitted_again(a.copy()) is None  # the same values in other memory: new
    key = id(a)
    del a
    gc.collect()
    assert key not in _FITTED  # forgotten with the memory
    not_owned = np.frombuffer(bytearray(64), dtype=complex)  # (a buffer NumPy does not own)
    assert fitted_again(not_owned) is None and fitted_again(not_owned) is None


def test_task_arguments_pickle():
    # worker processes receive the chunks' arguments pickled: core, space, settings

    from tawarp.measure.kind import smooth_settings

    core = load_core("ceramic")
    from tawarp.design.sweep import _Job
    from tawarp.model.forward import ForwardSettings

    spec = {"space": _space(), "extra": ["acoustic_loss"], "settings": smooth_settings(core, FREQS, None)}
    back = pickle.loads(pickle.dumps((core, spec)))
    assert repr(back[0]) == repr(core) and back[1]["settings"] == spec["settings"]  # repr: NaN fields
    assert back[1]["space"].param_names == spec["space"].param_names
    job = _Job(_space(), "sobol", 3, ["gradient"], (50.0,), ForwardSettings(chunk=64))
    back = pickle.loads(pickle.dumps(job))
    assert (back.mode, back.seed, back.outputs, back.settings) == (job.mode, job.seed, job.outputs, job.settings)
    assert back.space.param_names == job.space.param_names


def test_interrupted_parts_sweep_keeps_the_older_one(client, tmp_path, monkeypatch):
    # a sweep that fails before its end (here: while mapping its parts) leaves the older
    # file and its parts as they were, and no temporary file or folder behind
    import xarray as xr

    from tawarp.design import sweep as sweep_module

    space = _space()
    kw = dict(mode="sobol", n_samples=64, chunk=16, client=client, parts=True)
    sweep_module.sweep(space, tmp_path / "s.nc", seed=1, **kw)
    with xr.open_dataset(tmp_path / "s.nc", engine="h5netcdf") as ds:
        before = ds.load()

    def fail(*args, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(sweep_module, "_map_parts", fail)
    with pytest.raises(KeyboardInterrupt):
        sweep_module.sweep(space, tmp_path / "s.nc", seed=2, **kw)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.nc", "s.nc.parts"]
    assert len(list((tmp_path / "s.nc.parts").iterdir())) == 4
    with xr.open_dataset(tmp_path / "s.nc", engine="h5netcdf") as ds:
        xr.testing.assert_identical(ds.load(), before)


@pytest.mark.parametrize("mode", ["sobol", "grid"])
def test_reduced_sweep_on_cluster_equals_one_process(client, tmp_path, mode):
    # each worker reduces its share of the chunks on its device and sends back its
    # reductions; merged here they are one process's, value for value (counts summed, best
    # keys minimized, top K and front merged with the point index as tie-break)
    import xarray as xr

    from tawarp.design.sweep import sweep

    space = DesignSpace(
        load_core("rvc_foam"),
        ["stack.length=0.01:0.08:5", "material=ceramic,mesh,rvc_foam", "heat_input=1:18:4"],
    )
    kw = dict(mode=mode, n_samples=300, seed=3, chunk=24, reduce="best,quantiles,histogram,pareto,top=7", raw=False)
    one = sweep(space, tmp_path / "one.nc", **kw)
    many = sweep(space, tmp_path / "many.nc", client=client, **kw)
    assert many.chunks == one.chunks > 2 and many.n_points == one.n_points
    assert many.reductions == one.reductions
    for group in ("best", "top", "pareto", "histogram", "quantiles"):
        with (
            xr.open_dataset(tmp_path / "one.nc", engine="h5netcdf", group=group) as x,
            xr.open_dataset(tmp_path / "many.nc", engine="h5netcdf", group=group) as y,
        ):
            xr.testing.assert_identical(x.load(), y.load())
    with pytest.raises(ValueError, match="raw=False"):
        sweep(space, tmp_path / "no.nc", client=client, **{**kw, "raw": True})


@pytest.mark.parametrize("writers", [1, 2])
def test_shared_columns_hold_what_each_writer_wrote(tmp_path, writers):
    # columns of several dtypes and row shapes in one file, each at a 64-byte offset; two
    # writers' row ranges (by the write call, or through populated mappings) read back
    # exactly through the client's one mapping
    from tawarp.distributed import SharedColumns

    layout = {"gradient": ("<f8", ()), "window": ("<f4", (3,)), "material": ("|i1", ())}
    cols = SharedColumns.create(5, layout, folders=[str(tmp_path)], writers=writers)
    assert cols.writers == writers
    assert all(v % 64 == 0 for v in cols.offsets().values())
    rows = {
        "gradient": np.arange(5.0) / 3,
        "window": np.arange(15, dtype=np.float32).reshape(5, 3),
        "material": [1, 0, 2, 2, 1],
    }
    cols.write(2, {k: np.asarray(v)[2:] for k, v in rows.items()})
    cols.write(0, {k: np.asarray(v)[:2] for k, v in rows.items()})
    back = cols.columns()
    assert all(np.array_equal(back[k], np.asarray(v, dtype=layout[k][0])) for k, v in rows.items())
    assert SharedColumns.create(5, layout, folders=[str(tmp_path / "missing")]) is None


@pytest.mark.skipif(sys.platform != "linux", reason="chunk files are mapped back to back on Linux")
def test_chunk_files_read_back_as_one_column_each(tmp_path):
    # three chunks of a page multiple in rows and a shorter last one, each written whole
    # into its own file in any order: the reader sees one column each, exactly what was
    # written, still there once the files are removed and the columns' owner gone
    import gc
    import mmap

    from tawarp.distributed import SharedColumns

    page = mmap.PAGESIZE
    n = 3 * page + 77
    layout = {"gradient": ("<f8", ()), "window": ("<f4", (3,)), "material": ("|i1", ()), "ok": ("|b1", ())}
    rng = np.random.default_rng(5)
    rows = {
        "gradient": rng.standard_normal(n),
        "window": rng.standard_normal((n, 3)).astype(np.float32),
        "material": rng.integers(-3, 4, n).astype(np.int8),
        "ok": rng.random(n) < 0.5,
    }
    starts = (0, page, 2 * page, 3 * page)
    cols = SharedColumns.create(n, layout, folders=[str(tmp_path)], writers=2, chunks=starts)
    for lo in (2 * page, 3 * page, 0, page):
        hi = min(n, lo + page)
        cols.write(lo, {k: v[lo:hi] for k, v in rows.items()})
    back = cols.columns()
    cols.remove()
    del cols
    gc.collect()
    assert not list(tmp_path.iterdir())
    for k, v in rows.items():
        assert back[k].dtype == np.dtype(layout[k][0]) and np.array_equal(back[k], v), k
    back["gradient"][:2] = 0.0  # (writable, as the one file's mapping is)
    assert np.array_equal(back["gradient"][2:], rows["gradient"][2:])


def _pooled_call(pool, rows: dict, layout: dict, starts: tuple, chunk: int, order) -> tuple:
    """A call's result ``rows`` written chunk by chunk (``chunk`` rows from each of
    ``starts``, in ``order``) into files that ``pool`` lends, as
    :meth:`tawarp.distributed.ClusterEvaluator.evaluate_sobol` writes them: (its columns,
    whose files go back to the pool once they are let go; the files)."""
    from tawarp.distributed import SharedColumns

    n = len(next(iter(rows.values())))
    out = SharedColumns("", n, layout, chunks=starts)
    out = SharedColumns("", n, layout, chunks=starts, files=pool.take(out.chunk_sizes()))
    for lo in order:
        out.write(int(lo), {k: v[lo : lo + chunk] for k, v in rows.items()})
    return out.columns(on_release=lambda: pool.give_back(out.files)), out.files


@pytest.mark.skipif(not os.path.isdir("/dev/shm"), reason="pooled chunk files are reused in tmpfs")
def test_pooled_chunk_files_are_written_again_only_once_let_go():
    # the files of a result still held are never lent again: a second call gets files of
    # its own; once the first result has gone its files come back and a third call's
    # chunks are copied into their pages (through the writer's kept mapping), read back
    # exactly; files beyond one call's go, and closing the pool unlinks every file
    import gc
    import mmap
    import tempfile

    from tawarp.distributed import _WRITTEN, ChunkFiles, drop_unlinked_mappings

    page = mmap.PAGESIZE
    n = 2 * page + 5
    layout = {"gradient": ("<f8", ()), "window": ("<f4", (3,))}
    starts = (0, page, 2 * page)
    rng = np.random.default_rng(11)

    def call(pool, seed):
        rows = {
            "gradient": np.random.default_rng(seed).standard_normal(n),
            "window": np.random.default_rng(seed + 1).standard_normal((n, 3)).astype(np.float32),
        }
        return (rows, *_pooled_call(pool, rows, layout, starts, page, rng.permutation(starts)))

    with tempfile.TemporaryDirectory(dir="/dev/shm") as folder:
        pool = ChunkFiles(folders=[folder])
        rows1, back1, files1 = call(pool, 1)
        rows2, back2, files2 = call(pool, 2)
        assert not set(files1) & set(files2)
        del back2
        gc.collect()
        rows3, back3, files3 = call(pool, 3)  # (the files of the second call again)
        assert files3 == files2 and all(f in _WRITTEN for f in files3)  # (chunk i: the same file)
        for rows, back in ((rows1, back1), (rows3, back3)):
            for k, v in rows.items():
                assert np.array_equal(back[k], v), k
        del back1, back3, back
        gc.collect()
        rows4, back4, files4 = call(pool, 4)
        assert len(os.listdir(folder)) == len(starts)  # (one call's: the others' went)
        assert all(np.array_equal(back4[k], v) for k, v in rows4.items())
        pool.close()
        assert not os.listdir(folder)
        assert all(np.array_equal(back4[k], v) for k, v in rows4.items())  # (its pages stay mapped)
        # the writer's kept mappings of the unlinked files go (a worker checks every few seconds)
        assert any(f in _WRITTEN for f in files4)
        drop_unlinked_mappings()
        assert not any(f in _WRITTEN for f in files1 + files2 + files4)


@pytest.mark.skipif(not os.path.isdir("/dev/shm"), reason="pooled chunk files are reused in tmpfs")
def test_kept_mappings_hold_at_most_their_budget_and_every_chunk_is_written(monkeypatch):
    # with room for two of a call's three chunk files, a writer keeps the mappings of two
    # (page-locked memory on a GPU worker: mapping_budget) and writes the third through the
    # write call; with room for none, every chunk goes through the write call; the results
    # read back exactly either way
    import gc
    import mmap
    import tempfile

    import tawarp.distributed as dist

    page = mmap.PAGESIZE
    n = 3 * page
    layout = {"gradient": ("<f8", ())}
    starts = (0, page, 2 * page)
    chunk_bytes = 8 * page
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")

    def call(pool, seed):
        rows = {"gradient": np.random.default_rng(seed).standard_normal(n)}
        back, files = _pooled_call(pool, rows, layout, starts, page, starts)
        assert np.array_equal(back["gradient"], rows["gradient"])
        return back, files

    for room, kept in ((2.5, 2), (0.5, 0)):
        dist.drop_unlinked_mappings()
        monkeypatch.setattr(dist, "LOCKED_SHARE", room * chunk_bytes / memory)
        with tempfile.TemporaryDirectory(dir="/dev/shm") as folder:
            pool = dist.ChunkFiles(folders=[folder])
            back, _ = call(pool, 1)  # (fresh files: the write call)
            del back
            gc.collect()
            back, files = call(pool, 2)  # (the same files again: through kept mappings where they fit)
            assert sum(f in dist._WRITTEN for f in files) == kept, room
            assert dist._MAPPED_BYTES <= dist.mapping_budget() + 1e-9
            del back
            gc.collect()
            pool.close()
        dist.drop_unlinked_mappings()
        assert not any(f in dist._WRITTEN for f in files)


def test_a_populated_mapping_writes_the_bytes_the_write_call_writes(tmp_path):
    # byte ranges that start inside a page past the first mapping granule and cross page
    # boundaries, written through populated mappings, leave the file byte for byte as the
    # write call does, the bytes around them untouched
    import mmap

    from tawarp.distributed import write_at

    page = mmap.ALLOCATIONGRANULARITY
    rng = np.random.default_rng(3)
    size = 5 * page
    pieces = [
        (page + 7, rng.integers(0, 256, 2 * page + 100, dtype=np.uint8)),
        (3 * page + 200, np.arange(9, dtype=np.uint8)),
    ]
    files = {}
    for mapped in (False, True):
        path = tmp_path / f"mapped{mapped}"
        path.write_bytes(b"\xab" * size)
        fd = os.open(path, os.O_RDWR)
        try:
            for at, data in pieces:
                write_at(fd, data, at, mapped=mapped)
            write_at(fd, np.empty(0, dtype=np.uint8), 0, mapped=mapped)
        finally:
            os.close(fd)
        files[mapped] = np.frombuffer(path.read_bytes(), dtype=np.uint8)
    want = np.full(size, 0xAB, dtype=np.uint8)
    for at, data in pieces:
        want[at : at + data.size] = data
    assert np.array_equal(files[False], want) and np.array_equal(files[True], want)


def test_a_gpus_cpus_are_those_its_numa_node_lists(tmp_path):
    # the kernel's cpulist format (ranges and single CPUs, comma separated) under the PCI
    # address that Warp's pci_bus_id names (domain of 8 hex digits there, 4 in sysfs); an
    # unknown device, or none, leaves the workers where they are
    from tawarp.distributed import gpu_cpus, near_gpu

    node = tmp_path / "0000:1b:00.0"
    node.mkdir()
    (node / "local_cpulist").write_text("0-3,8,10-11\n")
    assert gpu_cpus("00000000:1B:00", str(tmp_path)) == {0, 1, 2, 3, 8, 10, 11}
    assert gpu_cpus("00000000:1C:00", str(tmp_path)) is None
    assert gpu_cpus(None, str(tmp_path)) is None
    before = os.sched_getaffinity(0)
    near_gpu(None)
    assert os.sched_getaffinity(0) == before


def test_processes_spawned_side_by_side_share_the_cores_among_their_blas_threads(monkeypatch):
    # each of P processes spawned inside cores_shared(P) starts with cpu_share(P) threads of
    # linear algebra, as Dask's nanny starts its workers with one; without it each pool has a
    # thread per core (a study's 16 loop processes ran 16 pools of 16 threads on 16 cores);
    # a variable the user set stands, and the environment is as it was after
    import importlib
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from threadpoolctl import threadpool_info

    from tawarp.distributed import BLAS_THREAD_VARIABLES, cores_shared
    from tawarp.model.forward import cpu_share

    for k in BLAS_THREAD_VARIABLES:
        monkeypatch.delenv(k, raising=False)
    cores = len(os.sched_getaffinity(0))

    def blas_threads():
        spawn = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(
            1, mp_context=spawn, initializer=importlib.import_module, initargs=("scipy.linalg",)
        ) as pool:
            pools = pool.submit(threadpool_info).result()
        return {p["num_threads"] for p in pools if p["user_api"] == "blas"}

    alone = blas_threads()  # NumPy's and SciPy's pools as a process starts them
    if not alone:
        pytest.skip("NumPy's BLAS has no thread pool that threadpoolctl sees")
    if cores > 1:
        assert max(alone) > 1
    for P in (2, 4 * cores):
        with cores_shared(P) as share:
            assert share == cpu_share(P) and blas_threads() == {share}
        assert not any(k in os.environ for k in BLAS_THREAD_VARIABLES)
    assert cpu_share(4 * cores) == 1
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "1")
    with cores_shared(1):
        assert os.environ["OPENBLAS_NUM_THREADS"] == "1" and os.environ["OMP_NUM_THREADS"] == str(cpu_share(1))
    assert os.environ["OPENBLAS_NUM_THREADS"] == "1" and "OMP_NUM_THREADS" not in os.environ


def test_the_mps_daemon_is_seen_by_its_control_pipe(tmp_path, monkeypatch):
    # NVIDIA's MPS daemon makes the control pipe in its pipe folder (CUDA_MPS_PIPE_DIRECTORY,
    # else /tmp/nvidia-mps): there it runs, and nowhere else
    from tawarp.distributed import cuda_mps_running

    monkeypatch.setenv("CUDA_MPS_PIPE_DIRECTORY", str(tmp_path))
    assert not cuda_mps_running()
    (tmp_path / "log").write_text("")
    assert not cuda_mps_running()
    os.mkfifo(tmp_path / "control")
    assert cuda_mps_running()


class _FakeDriver:
    """The CUDA driver's calls on the current context that :func:`wait_by_blocking` and
    :func:`context_waits` make, on a context that holds ``flags``; ``refuse``: its
    cuCtxSetFlags fails (as a driver refuses a flag)."""

    def __init__(self, flags: int, refuse: bool = False):
        self.flags, self.refuse = flags, refuse

    def cuCtxGetFlags(self, flags):
        flags._obj.value = self.flags
        return 0

    def cuCtxSetFlags(self, flags):
        if self.refuse:
            return 1
        self.flags = flags
        return 0


class _OlderDriver:
    """A driver before CUDA 12.1: no cuCtxSetFlags."""

    def cuCtxGetFlags(self, flags):
        flags._obj.value = 0
        return 0


def test_blocking_waits_set_the_scheduling_bits_of_warps_context(monkeypatch):
    # CU_CTX_SCHED_BLOCKING_SYNC (cuda.h: 0x4) in the scheduling bits of the context Warp
    # started, its other flags (Warp's CU_CTX_MAP_HOST, 0x8) kept; a refused flag, a driver
    # without cuCtxSetFlags, no driver or the CPU: False
    import contextlib
    import types

    import warp as wp

    import tawarp.distributed as dist

    gpu = types.SimpleNamespace(is_cuda=True, context_guard=contextlib.nullcontext())
    monkeypatch.setattr(wp, "get_device", lambda device=None: gpu)
    driver = _FakeDriver(0x8)
    monkeypatch.setattr(dist, "_cuda_driver", lambda: driver)
    assert dist.context_waits("cuda") == "auto"
    assert dist.wait_by_blocking("cuda")
    assert driver.flags == 0x8 | 0x4
    assert dist.context_waits("cuda") == "blocking"
    driver.flags = 0x8 | 0x1
    assert dist.context_waits("cuda") == "spin"
    dist.require_blocking_waits("cuda")  # (taken: no error)
    for other in (_FakeDriver(0x8, refuse=True), _OlderDriver(), None):
        monkeypatch.setattr(dist, "_cuda_driver", lambda other=other: other)
        assert not dist.wait_by_blocking("cuda")
        # a study that asked for blocking waits is not run with spinning ones
        with pytest.raises(RuntimeError, match="--blocking-waits: .* on cuda"):
            dist.require_blocking_waits("cuda")
    monkeypatch.setattr(dist, "_cuda_driver", lambda: driver)
    monkeypatch.setattr(wp, "get_device", lambda device=None: types.SimpleNamespace(is_cuda=False))
    assert not dist.wait_by_blocking("cpu") and dist.context_waits("cpu") is None


def test_fit_parts_in_shared_memory_join_as_the_arrays_would(tmp_path):
    # worker processes write each chunk's per-problem numeric arrays into one shared file
    # and send the rest; a chunk that could not (no room, the file gone) sends them all and
    # the client copies them in: either way the result is the one of joining the chunks'
    # results, array for array; a longer reason string in a later chunk is kept whole
    import dataclasses

    from tawarp.distributed import SharedColumns, _joined_parts, _shared_part, concatenate_results

    core, names, Y, sd, start = _geometry_problems(5)
    parts = [
        fit(core, FREQS, Y[lo:hi], names, start, weights=1 / sd, device="cpu", warn=False)
        for lo, hi in ((0, 2), (2, 5))
    ]
    parts[1] = dataclasses.replace(parts[1], reason=np.array(["max_iterations", "gtol", "xtol"]))
    joined = concatenate_results(parts)
    assert joined.reason.tolist() == [*parts[0].reason.tolist(), "max_iterations", "gtol", "xtol"]
    out = SharedColumns.create(5, None, folders=[str(tmp_path)])
    sent = [_shared_part(parts[0], out, 0), (parts[1], None)]
    assert sent[0][1] is not None and sent[0][0].values is None and sent[0][0].reason is not None
    many = _joined_parts(iter(sent), 5, [0, 2], out)
    for f in dataclasses.fields(joined):
        a, b = getattr(joined, f.name), getattr(many, f.name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), f.name
    assert list(many.problem_warnings) == list(joined.problem_warnings)
    assert (many.evaluations, many.launches) == (joined.evaluations, joined.launches)
    gone = SharedColumns(str(tmp_path / "gone"), 5, None)
    back, layout = _shared_part(parts[0], gone, 0)
    assert back is parts[0] and layout is None


def test_islands_go_on_from_lineages_searched_into_the_study(client, tmp_path):
    # a lineage searched into the study itself (search(worker="island0")) goes on as an
    # island in its own journal: with another seed it is refused as search refuses it; with
    # its own, the trials are those of one uninterrupted search, none stored twice
    from tawarp.design.islands import search_islands
    from tawarp.design.storage import StudyConflict, lineage

    storage = str(tmp_path / "study.journal")
    kw = dict(n_trials=32, batch=16)
    for name in ("island0", "island1"):
        search(_space(), worker=name, storage=storage, seed=4, **kw)
    with pytest.raises(StudyConflict, match="seed 4"):
        search_islands(client, _space(), storage=storage, seed=5, **dict(kw, n_trials=64))
    res = search_islands(client, _space(), storage=storage, seed=4, **dict(kw, n_trials=64))
    assert res.timing["evaluations"] == 2 * 32
    ref = search(_space(), worker="island1", seed=4, **dict(kw, n_trials=64))
    got, want = lineage(res.study, "island1"), lineage(ref.study, "island1")
    assert sorted(got) == sorted(want) == list(range(4))
    for g in want:
        assert got[g]["index"].tolist() == want[g]["index"].tolist()
        for k in ("param:stack.length", "param:heat_input", "metric:gradient"):
            assert got[g][k].astype(float).tolist() == want[g][k].astype(float).tolist(), (g, k)


def test_sobol_chunks_written_to_shared_memory_equal_one_process(tmp_path):
    # what a worker process does with a chunk of evaluate_sobol: the kernel's columns
    # copied into its host buffer (kept, grown for a longer chunk) and written to its rows
    # of the shared file; chunks of 20, 30 and 10 points: the objectives of one process
    import uuid

    from tawarp.design.evaluate import DEFAULT_FREQS
    from tawarp.design.space import DeviceTable
    from tawarp.distributed import SharedColumns, _evaluate_sobol_chunk, _objective_layout

    space = _space()
    spec = pickle.dumps({"space": space, "extra": [], "settings": None, "freqs": DEFAULT_FREQS, "onset": None})
    key = uuid.uuid4().hex
    out = SharedColumns.create(60, _objective_layout(key, spec), folders=[str(tmp_path)])
    for lo, hi in ((0, 20), (30, 60), (20, 30)):
        assert _evaluate_sobol_chunk((5 + lo, 5 + hi, 7, lo), key, spec, out) is None
    ev = Evaluator(space)
    one = ev.evaluate_table(DeviceTable(space, ev.device).sobol(5, 65, 7)[0])
    many = out.columns()
    assert set(many) == set(one) and all(np.array_equal(many[k], one[k], equal_nan=True) for k in one)


@pytest.mark.skipif(not os.path.isdir("/dev/shm"), reason="pooled chunk files are reused in tmpfs")
def test_sobol_chunks_copied_straight_into_pooled_files_equal_one_process(monkeypatch):
    # a pooled chunk file written before (its pages there, the worker's mapping kept) takes
    # the device's columns straight, without the worker's host buffer: three chunks of
    # two pages of points and a shorter one, a first call (seed 7) then a second (seed 8)
    # into the same files, each equal to one process's objectives
    import gc
    import mmap
    import tempfile
    import uuid

    import tawarp.distributed as dist
    from tawarp.design.evaluate import DEFAULT_FREQS
    from tawarp.design.space import DeviceTable

    space = _space()
    spec = pickle.dumps({"space": space, "extra": [], "settings": None, "freqs": DEFAULT_FREQS, "onset": None})
    key = uuid.uuid4().hex
    step = 2 * mmap.PAGESIZE
    n = 2 * step + 10
    starts = (0, step, 2 * step)
    ev = Evaluator(space)
    with tempfile.TemporaryDirectory(dir="/dev/shm") as folder:
        pool = dist.ChunkFiles(folders=[folder])
        layout = dist._objective_layout(key, spec)
        for seed in (7, 8):
            out = dist.SharedColumns("", n, layout, chunks=starts)
            out = dist.SharedColumns("", n, layout, chunks=starts, files=pool.take(out.chunk_sizes()))
            for lo in starts:
                assert dist._evaluate_sobol_chunk((5 + lo, 5 + min(n, lo + step), seed, lo), key, spec, out) is None
            got = out.columns(on_release=lambda: pool.give_back(out.files))
            one = ev.evaluate_table(DeviceTable(space, ev.device).sobol(5, 5 + n, seed)[0])
            assert set(got) == set(one) and all(np.array_equal(got[k], one[k], equal_nan=True) for k in one)
            del got
            gc.collect()
            # the second call's chunks go straight into the kept mappings
            monkeypatch.setattr(dist, "_on_host", lambda *a: pytest.fail("copied through the host buffer"))
        pool.close()
        dist.drop_unlinked_mappings()


def test_a_done_board_returns_once_every_share_is_posted_and_raises_a_failed_one(client, tmp_path):
    # each task sets its slot once its results are written: the client returns on the
    # posts (tasks that then sleep are still running), and on a failed task's error where
    # it posted nothing
    import time

    from tawarp.distributed import DoneBoard

    def share(slot, path, gate=None):
        DoneBoard.post(path, slot)
        end = time.monotonic() + 60.0  # (held until the client has returned, a minute at most)
        while gate is not None and not os.path.exists(gate) and time.monotonic() < end:
            time.sleep(0.01)

    def fails(slot):
        raise ValueError(f"share {slot} failed")

    board = DoneBoard(3, folders=[str(tmp_path)])
    try:
        gate = tmp_path / "gate"
        futures = [client.submit(share, i, board.path, str(gate), pure=False) for i in range(2)]
        board.wait(futures)
        assert board.board.tolist() == [1, 1, 0]
        assert all(f.status == "pending" for f in futures)  # (held at the gate: returned on the posts)
    finally:
        gate.touch()
        board.close()
    assert not os.path.exists(board.path)
    DoneBoard.post(board.path, 0)  # (a share ending after its call: nothing)
    board = DoneBoard(2, folders=[str(tmp_path)])
    try:
        with pytest.raises(ValueError, match="share 1 failed"):
            board.wait([client.submit(share, 0, board.path, pure=False), client.submit(fails, 1)])
    finally:
        board.close()


@pytest.mark.skipif(sys.platform != "linux", reason="glibc's malloc")
def test_a_worker_near_its_memory_limit_gives_its_kept_heap_back():
    # a worker process keeps the heap it frees (keep_freed_memory) until its memory passes
    # TRIM_SHARE of its limit: then housekeeping returns it to the kernel. In a process of
    # its own: 64 MB of 1 MB arrays freed stay resident, and go under a limit they pass
    import subprocess
    import textwrap

    code = textwrap.dedent(
        """
        import types
        import numpy as np
        import psutil
        from tawarp.distributed import TRIM_SHARE, housekeeping, keep_freed_memory

        def worker(limit):
            memory = psutil.Process().memory_info().rss
            return types.SimpleNamespace(
                memory_manager=types.SimpleNamespace(memory_limit=limit),
                monitor=types.SimpleNamespace(get_process_memory=lambda: memory),
            )

        assert keep_freed_memory()
        arrays = [np.ones(1 << 17) for _ in range(64)]
        del arrays
        kept = psutil.Process().memory_info().rss
        assert not housekeeping(worker(None)) and not housekeeping(worker(2 * kept / TRIM_SHARE))
        assert psutil.Process().memory_info().rss > kept - (8 << 20)
        assert housekeeping(worker(kept / TRIM_SHARE - 1))
        assert psutil.Process().memory_info().rss < kept - (48 << 20)
        """
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={**os.environ})
    assert run.returncode == 0, run.stderr


def test_a_thread_cluster_starts_warp_before_its_workers():
    # worker threads share one Warp runtime; two of them starting it lazily at once (their
    # first launches) can disturb a module load, so local_cluster starts it first. In a
    # process of its own, where nothing has started Warp yet
    import subprocess
    import textwrap

    code = textwrap.dedent(
        """
        from warp._src import context
        from tawarp.distributed import local_cluster

        assert context.runtime is None
        client = local_cluster(["cpu", "cpu"], processes=False)
        try:
            assert context.runtime is not None
        finally:
            cluster = client.cluster
            client.close()
            cluster.close()
        """
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={**os.environ})
    assert run.returncode == 0, run.stderr


@pytest.mark.skipif(sys.platform != "linux", reason="advisory locks on a tmpfs")
def test_files_of_a_killed_process_are_swept_and_a_living_ones_kept(tmp_path):
    # a client killed mid-call leaves its shared-memory files; the next process's first
    # file in that folder sweeps them (sweep_orphans), never those of a process alive, nor
    # a file made so recently that its maker may not hold its lock yet
    import signal
    import subprocess
    import textwrap

    from tawarp.distributed import ChunkFiles, sweep_orphans

    code = textwrap.dedent(
        """
        import os, signal, sys
        from tawarp.distributed import ChunkFiles, DoneBoard
        pool, board = ChunkFiles(folders=[sys.argv[1]]), DoneBoard(2, folders=[sys.argv[1]])
        print(*pool.take([4096, 8192]), board.path, flush=True)
        if sys.argv[2] == "kill":
            os.kill(os.getpid(), signal.SIGKILL)
        sys.stdin.read()  # alive until the test closes its input
        pool.close()
        board.close()
        """
    )
    folder = str(tmp_path)

    def start(how):
        p = subprocess.Popen(
            [sys.executable, "-c", code, folder, how], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )
        return p, p.stdout.readline().split()

    killed, dead = start("kill")
    assert killed.wait(60) == -signal.SIGKILL
    living, alive = start("live")
    try:
        assert len(dead) == len(alive) == 3 and all(os.path.exists(f) for f in dead + alive)
        assert sweep_orphans(folder) == []  # all of them just made
        for f in dead + alive:
            os.utime(f, (time.time() - 3600, time.time() - 3600))
        assert sorted(sweep_orphans(folder)) == sorted(dead)
        assert not any(os.path.exists(f) for f in dead) and all(os.path.exists(f) for f in alive)
        # a file of this process is its own, however old
        pool = ChunkFiles(folders=[folder])
        (mine,) = pool.take([4096])
        os.utime(mine, (time.time() - 3600, time.time() - 3600))
        assert sweep_orphans(folder) == [] and os.path.exists(mine)
        pool.close()
        assert not os.path.exists(mine)
    finally:
        living.stdin.close()
        assert living.wait(60) == 0
    assert os.listdir(folder) == []
