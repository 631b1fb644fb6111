"""The host's CPU time by function (bench/_host_time.py, ``bench/loop.py --host-time``)."""

import importlib.util
import time
from pathlib import Path

import numpy as np
import pytest


def _host_time():
    path = Path(__file__).resolve().parents[1] / "bench" / "_host_time.py"
    spec = importlib.util.spec_from_file_location("bench_host_time", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_timed_function_is_wrapped_inside_and_put_back_after():
    """A function, a method, and a function another module imported by name (the fits'
    covariances, called from tawarp.fit.problems): wrapped everywhere, then the originals."""
    import tawarp.fit.problem_model as pm
    import tawarp.fit.problems as problems
    import tawarp.model.forward as fw

    ht = _host_time()
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

    ht = _host_time()
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
    ht = _host_time()
    monkeypatch.setattr(ht, "TIMED", {"tawarp.model.forward": ["no_such_function"]})
    with pytest.raises(AttributeError, match="no_such_function"):
        with ht.thread_times():
            pass
