"""The benchmarks' helpers: where a benchmark writes its JSON (bench/_results.py), what
bench/loop.py counts and times, the host's CPU time by function (bench/_host_time.py), the
wall time of reads and uploads (bench/_read_waits.py)."""

import importlib.util
import json
import time
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


def _bench(name: str, monkeypatch=None):
    """The module of ``bench/<name>.py`` (``monkeypatch``: its folder on the path while
    the test runs, for a script that imports its folder's modules)."""
    if monkeypatch is not None:
        monkeypatch.syspath_prepend(str(BENCH))
    spec = importlib.util.spec_from_file_location(f"bench_{name.strip('_')}", BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _results():
    return _bench("_results")


def test_an_existing_folder_as_out_takes_the_benchmarks_own_file_name(tmp_path):
    path = _results().write_result({"cases": 3}, "loop_study_x.json", str(tmp_path))
    assert path == tmp_path / "loop_study_x.json"
    assert json.loads(path.read_text()) == {"cases": 3}


def test_a_file_as_out_is_written_under_that_name(tmp_path):
    path = _results().write_result({"cases": 3}, "loop_study_x.json", str(tmp_path / "mine.json"))
    assert path == tmp_path / "mine.json"
    assert json.loads(path.read_text()) == {"cases": 3}
    assert not (tmp_path / "loop_study_x.json").exists()


def test_the_device_time_sums_each_kind_and_ranks_activities_by_their_time(monkeypatch):
    import warp as wp

    loop = _bench("loop", monkeypatch)
    timed = [
        wp.TimingResult("cuda:0", "forward kernel heat", wp.TIMING_KERNEL, 3.0),
        wp.TimingResult("cuda:0", "memcpy DtoH", wp.TIMING_MEMCPY, 1.5),
        wp.TimingResult("cuda:0", "forward kernel heat", wp.TIMING_KERNEL, 5.0),
        wp.TimingResult("cuda:0", "forward kernel transfer", wp.TIMING_KERNEL, 2.0),
    ]
    got = loop.device_time(timed, cases=2, top=2)
    assert got["seconds"]["kernels"] == 0.010 and got["seconds"]["copies"] == 0.0015
    assert got["ms_per_case"]["kernels"] == 5.0 and got["ms_per_case"]["memsets"] == 0.0
    assert got["activities_per_case"] == 2.0
    assert got["by_name"] == [
        {"name": "forward kernel heat", "seconds": 0.008, "count": 2},
        {"name": "forward kernel transfer", "seconds": 0.002, "count": 1},
    ]


def test_sets_are_counted_once_whether_predicted_on_the_host_or_left_on_the_device(monkeypatch):
    # bench/loop.py's forward_sets: a fit on a GPU asks for its model values on the device
    # (predict_on_device), which for an elastic frame, or a kind without its own, forms them
    # with predict: every set counts once, and the kind's methods are its own again after
    from test_lockstep import mesh_kind

    from tawarp.measure import MeasurementKind, TMatrixKind

    loop = _bench("loop", monkeypatch)
    kind = mesh_kind(0)

    def values(n):
        return {"stack.porosity": np.full(n, kind.core.get("stack.porosity"))}

    own = (TMatrixKind.__dict__["predict"], TMatrixKind.__dict__["predict_on_device"])
    with loop.counting_sets(TMatrixKind) as count:
        kind.predict(values(3), 3)
        kind.predict_on_device(values(2), 2)
        MeasurementKind.predict_on_device(kind, values(4), 4)  # the host's values copied there
    assert count["sets"] == 3 + 2 + 4 and count["columns"] > 0
    assert (TMatrixKind.__dict__["predict"], TMatrixKind.__dict__["predict_on_device"]) == own


def test_every_timed_function_is_wrapped_inside_and_put_back_after():
    """A function, a method, and a function another module imported by name (the fits'
    covariances, called from tawarp.fit.problems): wrapped everywhere, then the originals."""
    import tawarp.fit.problem_model as pm
    import tawarp.fit.problems as problems
    import tawarp.model.forward as fw

    ht = _bench("_host_time")
    before = (fw.distinct_columns, fw.Engine.heat, pm.covariances, problems.covariances)
    with ht.thread_times():
        inside = (fw.distinct_columns, fw.Engine.heat, pm.covariances, problems.covariances)
        assert all(a is not b for a, b in zip(inside, before))
        assert problems.covariances is pm.covariances
    assert (fw.distinct_columns, fw.Engine.heat, pm.covariances, problems.covariances) == before


def test_a_callers_time_excludes_the_timed_functions_it_calls(monkeypatch):
    """A timed function that spends 60 ms of CPU of its own around a timed callee that
    spends 40 ms: 60 ms exclusive (within 15 ms: the clock's and the machine's jitter)."""
    import tawarp.model.forward as fw

    def busy(seconds):
        end = time.thread_time() + seconds
        while time.thread_time() < end:
            pass

    def inner(key):
        busy(0.04)
        return np.arange(key.shape[1]), np.arange(key.shape[1])

    ht = _bench("_host_time")
    monkeypatch.setattr(fw, "distinct_columns", inner)
    monkeypatch.setattr(ht, "TIMED", {"tawarp.model.forward": ["distinct_columns", "Engine.distinct"]})

    def outer(self, varying, on_device=False):
        busy(0.03)
        fw.distinct_columns(varying)
        busy(0.03)

    monkeypatch.setattr(fw.Engine, "distinct", outer)
    with ht.thread_times() as totals:
        fw.Engine.distinct(None, np.zeros((2, 3)))
    got = ht.summary(totals, 2, 0.1)
    by = {f["function"]: f for f in got["functions"]}
    assert by["Engine.distinct"]["seconds"] == pytest.approx(0.06, abs=0.015)
    assert by["Engine.distinct"]["inclusive_seconds"] == pytest.approx(0.10, abs=0.015)
    assert by["distinct_columns"]["seconds"] == pytest.approx(0.04, abs=0.015)
    assert by["distinct_columns"]["calls"] == 1
    assert got["untimed_seconds"] == pytest.approx(0.1 - got["timed_seconds"])


def test_a_name_no_longer_in_the_code_is_refused(monkeypatch):
    ht = _bench("_host_time")
    monkeypatch.setattr(ht, "TIMED", {"tawarp.model.forward": ["no_such_function"]})
    with pytest.raises(AttributeError, match="no_such_function"):
        with ht.thread_times():
            pass


def test_a_garbage_collection_is_its_own_line_not_the_interrupted_functions(monkeypatch):
    """A timed function that collects 200 000 cyclic objects: the collection's time is
    the collector's line and not the function's (its exclusive time is its inclusive time
    less the collection's, to the microsecond)."""
    import gc

    import tawarp.model.forward as fw

    ht = _bench("_host_time")
    monkeypatch.setattr(ht, "TIMED", {"tawarp.model.forward": ["distinct_columns"]})

    def collecting(key):
        cycles = [[] for _ in range(200_000)]
        for c in cycles:
            c.append(c)
        del cycles
        gc.collect()
        return np.arange(key.shape[1]), np.arange(key.shape[1])

    monkeypatch.setattr(fw, "distinct_columns", collecting)
    with ht.thread_times() as totals:
        fw.distinct_columns(np.zeros((2, 3)))
    by = {f["function"]: f for f in ht.summary(totals, 1, 1.0)["functions"]}
    collected = by[ht.GARBAGE_COLLECTION]
    assert collected["calls"] >= 1 and collected["seconds"] > 0
    own = by["distinct_columns"]
    assert own["seconds"] == pytest.approx(own["inclusive_seconds"] - collected["seconds"], abs=1e-6)


def test_reads_and_uploads_are_timed_by_call_site_and_the_arrays_restored():
    # bench/_read_waits.py on Warp's CPU device (on_cuda_only off: a CPU array's read waits
    # for nothing, but it is timed the same way): three reads at one line, two more at two others,
    # one upload from a NumPy array and none from a Warp array's own copy; the wrappers go
    # on leaving, and the summary adds the sites up
    import warp as wp

    rw = _bench("_read_waits")
    read, make = wp.array.numpy, wp.array.__init__
    a = wp.array(np.arange(4.0), device="cpu")
    with rw.read_waits(on_cuda_only=False) as totals:
        for _ in range(3):
            a.numpy()
        b = wp.zeros(3, dtype=wp.float64, device="cpu")
        b.numpy()
        b.numpy()
        wp.array(np.ones(3), device="cpu")
    assert wp.array.numpy is read and wp.array.__init__ is make
    sites = totals["sites"]
    reads = sorted(n for k, (n, _) in sites.items() if k.startswith("read test_bench_results.py:"))
    uploads = [n for k, (n, _) in sites.items() if k.startswith("upload test_bench_results.py:")]
    assert reads == [1, 1, 3], sites
    assert uploads == [1], sites
    assert all(s >= 0.0 for _, s in sites.values())
    got = rw.summary(totals, cases=2, top=1)
    assert got["calls"] == sum(n for n, _ in sites.values()) and len(got["by_site"]) == 1
    assert got["ms_per_case"] == 1e3 * got["seconds"] / 2
    assert got["voluntary_switches"] >= 0 and got["involuntary_switches"] >= 0
    # on_cuda_only (the default): a CPU array's reads are not timed
    with rw.read_waits() as totals:
        a.numpy()
    assert totals["sites"] == {}
