"""Batched fits, sweeps and design evaluations spread over Dask workers
(tawarp.distributed) equal a single-process run: here on a local cluster of two CPU
worker processes, the same code that runs one worker per GPU."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("distributed")

from tawarp import reference  # noqa: E402
from tawarp.design.evaluate import Evaluator  # noqa: E402
from tawarp.design.search import search  # noqa: E402
from tawarp.design.space import DesignSpace  # noqa: E402
from tawarp.distributed import ClusterEvaluator, fit_on_cluster, local_cluster, ordered_map  # noqa: E402
from tawarp.fit.estimate import fit  # noqa: E402
from tawarp.model.core import load_core  # noqa: E402

FREQS = np.linspace(30.0, 500.0, 8)


@pytest.fixture(scope="module")
def client():
    # in-process workers (threads): the same scheduling and code as worker processes
    # (processes=True, as on GPUs: measured to pass too, but 30 s slower to start and stop
    # on the 2-core CI machine); test_task_arguments_pickle covers what processes add
    c = local_cluster(["cpu", "cpu"], processes=False)
    yield c
    cluster = c.cluster
    c.close()
    cluster.close()


def _space():
    return DesignSpace(load_core("rvc_foam"), ["stack.length=0.004:0.1", "heat_input=1:9", "hot_hx.length=0.005:0.03"])


def test_workers_get_their_devices_and_results_come_in_order(client):
    from tawarp.distributed import worker_settings

    workers = list(client.scheduler_info()["workers"])
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


def test_design_evaluations_on_cluster_equal_one_process(client):
    space = _space()
    rng = np.random.default_rng(1)
    values = space.from_unit(rng.random((50, 3)))
    one = Evaluator(space, extra=["acoustic_loss"], settings=None).evaluate(values)
    many = ClusterEvaluator(client, space, extra=["acoustic_loss"], chunk=16).evaluate(values)
    assert set(many) == set(one)
    for k in one:
        np.testing.assert_allclose(many[k], one[k], rtol=1e-12, atol=0, err_msg=k)


def test_search_and_sweep_on_cluster_equal_one_process(client, tmp_path):
    import xarray as xr

    from tawarp.design.sweep import sweep

    one = search(_space(), n_trials=32, batch=16, seed=4)
    many = search(_space(), n_trials=32, batch=16, seed=4, client=client)
    a = [(t.params, t.values) for t in one.study.trials]
    b = [(t.params, t.values) for t in many.study.trials]
    assert a == b
    sweep(_space(), tmp_path / "one.nc", mode="sobol", n_samples=96, chunk=32, seed=2)
    sweep(_space(), tmp_path / "many.nc", mode="sobol", n_samples=96, chunk=32, seed=2, client=client)
    with xr.open_dataset(tmp_path / "one.nc", engine="h5netcdf") as x, \
            xr.open_dataset(tmp_path / "many.nc", engine="h5netcdf") as y:
        xr.testing.assert_identical(x, y)


def test_task_arguments_pickle():
    # worker processes receive the chunks' arguments pickled: core, space, settings
    import pickle

    from tawarp.measure.kind import smooth_settings

    core = load_core("ceramic")
    spec = {"space": _space(), "extra": ["acoustic_loss"], "settings": smooth_settings(core, FREQS, None)}
    back = pickle.loads(pickle.dumps((core, spec)))
    assert repr(back[0]) == repr(core) and back[1]["settings"] == spec["settings"]  # repr: NaN fields
    assert back[1]["space"].param_names == spec["space"].param_names
