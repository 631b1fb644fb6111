"""Many callers' fits and predictions as one batch (tawarp.fit.lockstep): the fits of
several callers run together are the fits each runs alone, bit for bit where the kinds
predict alone; kinds of one family (one core structure, the same rows) share one launch
whose predictions are each kind's own."""

import dataclasses
import functools

import numpy as np
import pytest
from test_fit_lm import ExpKind, linear_case

from tawarp.fit import lockstep
from tawarp.fit.lockstep import Together, run_together
from tawarp.fit.problems import Families, FitCall, KindProblems, Sets, _absent, fit_batch, run_sets
from tawarp.loop import default_base_params
from tawarp.measure import TMatrixKind
from tawarp.measure.files import TMatrixData
from tawarp.model.core import load_core
from tawarp.model.effects import Param, tmatrix_library
from tawarp.model.forward import ForwardSettings


def exp_kind(seed: int) -> tuple:
    A, sigma, _, _, _ = linear_case(seed)
    rng = np.random.default_rng(seed)
    kind = ExpKind(A, sigma, A @ np.exp(rng.uniform(-0.5, 0.5, 3)) + sigma * 0.01)
    params = [Param(f"v{j}", (f"v{j}",), 0.5, 1.0) for j in range(3)]
    return kind, [(params, None, np.zeros(3)), (params, None, np.full(3, 0.7))]


def steps(kind, specs, n: int) -> list:
    """n fits in a row, each from the one before's solutions: a caller whose next fit
    depends on its last."""
    out = []
    for _ in range(n):
        fits = fit_batch(kind, specs, xtol=1e-12, gtol=1e-10)
        specs = [(sp[0], None, f.x[0] * 0.5) for sp, f in zip(specs, fits)]
        out.append(fits)
    return out


def test_callers_run_together_get_the_fits_they_get_alone():
    # three callers of 2, 3 and 1 dependent fit calls: batched, each caller's fits are bit for
    # bit its own alone (a kind that predicts alone; the LM's slots iterate independently),
    # in as many batches as the longest caller has calls
    cases = [exp_kind(seed) for seed in (1, 2, 3)]
    counts = (2, 3, 1)
    alone = [steps(kind, specs, n) for (kind, specs), n in zip(cases, counts)]
    together = Together()
    got = together.run([lambda k=k, s=s, n=n: steps(k, s, n) for (k, s), n in zip(cases, counts)])
    assert together.batches == max(counts) and together.calls == sum(counts)
    for a, b in zip(alone, got):
        for fa, fb in zip(a, b):
            for x, y in zip(fa, fb):
                assert np.array_equal(x.x, y.x) and x.reason[0] == y.reason[0]
                assert np.array_equal(x.jacobian, y.jacobian)


def test_an_eager_request_adds_no_round_to_the_others():
    # a caller that makes a cheap (eager) request before its next fit joins the others' fit
    # batch as if it had not waited: the eager batch runs first and alone, then one batch of
    # every caller's normal request
    log = []

    def batch(requests, _state):
        log.append(("normal", sorted(requests)))
        return requests

    def quick(requests, _state):
        log.append(("eager", sorted(requests)))
        return requests

    def caller(i: int, first_eager: bool):
        together = lockstep.current()
        if first_eager:
            assert together.call(-i, quick, eager=True) == -i
        return together.call(i, batch)

    together = Together()
    got = together.run([functools.partial(caller, i, i % 2 == 0) for i in range(5)])
    assert got == list(range(5))
    assert log == [("eager", [-4, -2, 0]), ("normal", [0, 1, 2, 3, 4])]


def test_a_caller_that_raises_leaves_the_others_their_fits():
    kind, specs = exp_kind(4)

    def failing():
        fit_batch(kind, specs)
        raise RuntimeError("a caller's own failure")

    got = run_together([failing, lambda: steps(kind, specs, 2)])
    assert isinstance(got[0], RuntimeError)
    assert all(f.converged[0] for fits in got[1] for f in fits)


FREQS = np.linspace(40.0, 400.0, 5)
QS = (0.0, 20.0, 40.0)


def mesh_kind(seed: int, cells: dict | None = None) -> TMatrixKind:
    """The mesh core with its base parameters 10-30 % off (seeded), at 5 frequencies and 3
    heat inputs (the data's values do not enter a prediction)."""
    mesh = load_core("mesh")
    data = TMatrixData(np.repeat(QS, FREQS.size), np.tile(FREQS, len(QS)), np.broadcast_to(np.eye(2), (15, 2, 2)))
    names = [p.label for p in default_base_params(TMatrixKind(data, mesh))]
    rng = np.random.default_rng(seed)
    core = mesh.replace(**{n: mesh.get(n) * (1 + rng.uniform(0.1, 0.3)) for n in names if "porosity" not in n})
    return TMatrixKind(data, core, ForwardSettings(device="cpu", cells=cells))


def jobs_of(kind: TMatrixKind, seed: int) -> list[Sets]:
    """Sets of the base parameters at random values, with a field effect (plane offsets), a
    structural one (a porosity gradient) and the host-side calibration."""
    rng = np.random.default_rng(seed)
    params = default_base_params(kind)
    lib = {e.name: e for e in tmatrix_library(kind.core)}
    out = []
    for name in (None, "plane_offsets", "porosity_gradient", "calibration"):
        effect = lib.get(name)
        pars = params + (list(effect.params) if effect else [])
        values = {}
        for par in pars:
            par.assign(par.value(rng.uniform(-0.2, 0.2, 3)), values)
        out.append(Sets(kind, values, 3, effect if effect is not None and effect.transform else None))
    return out


@pytest.fixture(scope="module")
def family():
    cells = {"stack": 7, "hot_hx": 17, "tbt": 13}
    return mesh_kind(1, cells), mesh_kind(2, cells)


def test_one_family_shares_a_launch_and_predicts_each_kind_as_its_own(family, monkeypatch):
    # two cores of one structure with different values: their sets in one launch per
    # structure, each set at its own core's values, the same numbers as its own kind's launch
    a, b = family
    assert a.family() == b.family() and a.core != b.core
    jobs = jobs_of(a, 1) + jobs_of(b, 2)
    alone = [run_sets([j])[0] for j in jobs]
    calls = []
    predict = TMatrixKind.predict
    monkeypatch.setattr(TMatrixKind, "predict", lambda self, *a, **k: calls.append(1) or predict(self, *a, **k))
    merged = run_sets(jobs, Families([a, b]))
    assert len(calls) == 2  # the core's structure and the porosity gradient's
    for x, y in zip(alone, merged):
        assert np.max(np.abs(x - y)) <= 1e-12 * np.max(np.abs(x))


def test_a_family_predicts_with_the_finest_cells_of_its_members():
    a = mesh_kind(1, {"stack": 7, "hot_hx": 17, "tbt": 13})
    b = mesh_kind(2, {"stack": 9, "hot_hx": 12, "tbt": 13})
    fam = Families([a, b]).of(b)
    assert fam.kind.settings.cells == {"stack": 9, "hot_hx": 17, "tbt": 13}
    assert a.settings.cells == {"stack": 7, "hot_hx": 17, "tbt": 13}  # the member's own unchanged
    assert dataclasses.replace(fam.kind.settings, cells=None) == dataclasses.replace(a.settings, cells=None)


def test_a_name_other_jobs_set_takes_the_core_value_or_the_effect_off():
    # a job's sets take, for a name only another job of its launch sets, their own core's
    # value, or an effect's neutral value (off); with neither (a frame field, which has no
    # "off" value) the job cannot share the launch
    a = mesh_kind(1)
    job = Sets(a, {"stack.porosity": np.full(2, 0.7)}, 2)
    fill = _absent(job, {"stack.porosity", "stack.pore_radius", "calibration.gain", "stack.porosity_gradient"})
    assert fill == {
        "stack.pore_radius": a.core.get("stack.pore_radius"),
        "calibration.gain": 1.0,
        "stack.porosity_gradient": 0.0,
    }
    assert _absent(job, {"stack.frame_wave_speed"}) is None


def test_fits_of_one_family_take_one_table_per_structure(family):
    # the fits of several calls whose kinds share a family form one parameter table per
    # structure (not one per call), each set at its own call's fixed values and its own
    # core's values elsewhere: the model values each call's fits get alone
    a, b = family
    lib = {e.name: e for e in tmatrix_library(a.core)}
    base = default_base_params(a)

    def specs(seed):
        rng = np.random.default_rng(seed)
        out = []
        for name in (None, "plane_offsets", "porosity_gradient"):
            effect = lib.get(name)
            params = base + (list(effect.params) if effect else [])
            out.append((params, effect, rng.uniform(-0.2, 0.2, len(params))))
        return out

    fixed_a = {"hot_hx.porosity": 0.55}
    calls = [FitCall(a, specs(1), fixed_a), FitCall(b, specs(2))]
    merged = KindProblems.merged(calls, Families([a, b]))
    assert len(merged.groups) == 2  # the core's structure and the porosity gradient's
    rng = np.random.default_rng(3)
    requests = [(c, rng.uniform(-0.3, 0.3, (2, merged.p[c]))) for c in range(len(merged.specs))]
    got = merged.predict(requests)
    alone = [KindProblems(call.kind, call.specs, call.fixed) for call in calls]
    for c, (_, X) in enumerate(requests):
        own = alone[c // 3].predict([(c % 3, X)])[0]
        assert np.max(np.abs(got[c] - own)) <= 1e-12 * np.max(np.abs(own))

    # the names a launch carries choose its engine: a launch of the first call's fits alone
    # carries that call's names, as its own batch does, not the other call's too
    def names(lm, fits):
        X = np.zeros((len(fits), lm.zlo.shape[1]))
        return {frozenset(job.values) for job in lm._jobs(np.array(fits), np.ones(len(fits), dtype=int), X, False)[0]}

    assert names(merged, [0, 1, 2]) == names(alone[0], [0, 1, 2])
    (first,), (second,), (both,) = names(merged, [0]), names(merged, [3]), names(merged, [0, 3])
    assert both == first | second and "hot_hx.porosity" in first and "hot_hx.porosity" not in second
