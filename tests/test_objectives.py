"""The objectives table (tawarp.design.objectives) and the evaluator that reads it, on the CPU."""

from __future__ import annotations

import numpy as np
import pytest

from tawarp.design.evaluate import Evaluator
from tawarp.design.objectives import OBJECTIVES, Objective, absorbed_fraction, kernel_metrics, register_objective
from tawarp.design.space import DesignSpace
from tawarp.kernels.design import N_METRICS
from tawarp.model.coefficients import duct_impedance
from tawarp.model.core import load_core
from tawarp.model.forward import steady_temperature, transfer_matrices


def test_every_kernel_column_has_exactly_one_row():
    cols = sorted(o.column for o in OBJECTIVES.values() if o.column is not None)
    assert cols == list(range(N_METRICS))
    assert kernel_metrics() == ["gradient", "T_max", "heat_leak", "T_hot"]
    with pytest.raises(ValueError, match="exactly one of column"):
        Objective("x", "minimize", "-", "neither")
    with pytest.raises(ValueError, match="direction"):
        Objective("x", "up", "-", "bad direction", column=0)
    with pytest.raises(ValueError, match="already registered"):
        register_objective(Objective("gradient", "maximize", "K/m", "again", column=0))


def test_metrics_match_the_heat_model():
    """gradient, T_max and heat leak of the batched kernel against steady_temperature and
    the exact NumPy solution (tawarp.reference)."""
    from tawarp.reference import heat_profile_exact

    core = load_core("rvc_foam")
    space = DesignSpace(core, ["material=ceramic,mesh,rvc_foam", "stack.length=0.01:0.08", "heat_input=1:18"])
    pts = {
        "material": np.array(["ceramic", "mesh", "rvc_foam", "rvc_foam"]),
        "stack.length": np.array([0.02, 0.05, 0.01, 0.08]),
        "heat_input": np.array([9.0, 18.0, 3.0, 12.0]),
    }
    m = Evaluator(space, settings=None).evaluate(pts)
    for j in range(4):
        c, q = space.core_for({k: v[j] for k, v in pts.items()})
        pos = c.positions()
        T, _ = steady_temperature(c, [pos[1], pos[2]], heat_input=q)
        assert m["gradient"][j] == pytest.approx((T[0, 1] - T[0, 0]) / (pos[2] - pos[1]), rel=1e-10)
        hs = heat_profile_exact(c, q)
        exact = (hs.theta_in(1, pos[2]) - hs.theta_in(1, pos[1])) / (pos[2] - pos[1])
        assert m["gradient"][j] == pytest.approx(float(exact), rel=1e-9)
        assert m["T_max"][j] == pytest.approx(c.gas.T_cold + hs.theta_max()[1], rel=1e-9)
        x = np.linspace(pos[1], pos[2], 20001)
        th = hs.theta_in(1, x)
        leak = 2 * c.segments[1].h / c.radius * c.area * np.sum(0.5 * (th[1:] + th[:-1]) * np.diff(x))
        assert m["heat_leak"][j] == pytest.approx(leak, rel=1e-7)


def _cell_max_40_digits(theta_l, theta_r, k, sigma, d):
    """Largest theta of the exact constant-coefficient cell (ends, or the root of theta'
    found by a bracketing solver) to 40 digits: the cell's ODE solution written directly,
    theta = A cosh(k m)/cosh(v) + half sinh(k m)/sinh(v) + sigma/k^2 about the centre m."""
    import mpmath as mp

    with mp.workdps(40):
        tl, tr, k, s, d = (mp.mpf(float(x)) for x in (theta_l, theta_r, k, sigma, d))
        mean, half = (tl + tr) / 2, (tr - tl) / 2
        if k == 0:  # the parabola
            th = lambda m: mean + 2 * half * m / d + s * (d * d / 4 - m * m) / 2
            dth = lambda m: 2 * half / d - s * m
        else:
            v, A = k * d / 2, mean - s / k**2
            th = lambda m: A * mp.cosh(k * m) / mp.cosh(v) + half * mp.sinh(k * m) / mp.sinh(v) + s / k**2
            dth = lambda m: k * (A * mp.sinh(k * m) / mp.cosh(v) + half * mp.cosh(k * m) / mp.sinh(v))
        best = max(tl, tr)
        if dth(-d / 2) > 0 and dth(d / 2) < 0:
            m = mp.findroot(dth, (-d / 2, d / 2), solver="illinois", tol=mp.mpf(10) ** -60, maxsteps=400)
            best = max(best, th(m))
        return float(best)


def test_cell_max_is_the_cell_profiles_maximum():
    """The T_max kernel's closed-form stationary point (design.cell_max) against a 40-digit
    root of theta' of the same cell, from k d = 0 (the parabola) and 1e-5 (series branches)
    to 50 (exponential profile), with and without an interior maximum: to rel 1e-14 (a few
    ulp)."""
    import warp as wp

    from tawarp.kernels.design import cell_max

    @wp.kernel
    def maxima(c: wp.array2d(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
        i = wp.tid()
        out[i] = cell_max(c[i, 0], c[i, 1], c[i, 2], c[i, 3], c[i, 4])

    rng = np.random.default_rng(3)
    n = 400
    d = 10 ** rng.uniform(-3, -1, n)
    kd = 10 ** rng.uniform(-5, 1.7, n)
    kd[:8] = 0.0
    theta_l, theta_r = rng.uniform(0, 500, n), rng.uniform(0, 500, n)
    # from a source too weak for an interior maximum to one that dominates the ends
    sigma = 10 ** rng.uniform(-1, 2, n) * (np.abs(theta_l - theta_r) + 50) * (8 / d**2 + (kd / d) ** 2)
    cells = np.stack([theta_l, theta_r, kd / d, sigma, d], axis=1)
    out = wp.empty(n, dtype=wp.float64, device="cpu")
    wp.launch(maxima, dim=n, inputs=[wp.array(cells, dtype=wp.float64, device="cpu"), out], device="cpu")
    got = out.numpy()
    ref = np.array([_cell_max_40_digits(*c) for c in cells])
    interior = ref > np.maximum(theta_l, theta_r)
    assert 0.2 * n < interior.sum() < 0.95 * n  # both kinds of cell are tested
    np.testing.assert_allclose(got, ref, rtol=1e-14, atol=0)


def test_acoustic_loss_is_a_passive_absorbed_fraction():
    core = load_core("ceramic")
    res = transfer_matrices(core, [50, 200, 500], heat_input=0.0)
    a = absorbed_fraction(res.T, duct_impedance(core))
    assert np.all(a > 0) and np.all(a < 1)
    k = 2 * np.pi * 100 / 343.0
    T = np.array([[[np.cos(k), 1j * np.sin(k)], [1j * np.sin(k), np.cos(k)]]])[None]
    assert absorbed_fraction(T, 1.0) == pytest.approx(0.0, abs=1e-14)  # lossless duct
    # the evaluator's acoustic_loss is the mean over its frequencies, at Q = 0 whatever the heat input
    space = DesignSpace(core, ["heat_input=0:18"])
    ev = Evaluator(space, extra=["acoustic_loss"], freqs=[50, 200, 500])
    m = ev.evaluate({"heat_input": np.array([0.0, 9.0, 18.0])})
    np.testing.assert_allclose(m["acoustic_loss"], a.mean(axis=-1).ravel()[0], rtol=1e-10)


@pytest.fixture
def toy_objective():
    """A user objective registered from outside the package: minus the gradient [K/m]."""
    row = register_objective(
        Objective(
            "minus_gradient",
            "minimize",
            "K/m",
            "minus the stack gradient",
            compute=lambda evaluator, table, metrics: -metrics["gradient"],
        )
    )
    yield row.name
    OBJECTIVES.pop(row.name)


def test_objective_registered_from_outside_is_searched_and_swept(toy_objective, tmp_path):
    import xarray as xr

    from tawarp.design.search import search
    from tawarp.design.sweep import sweep

    space = DesignSpace(load_core("rvc_foam"), ["stack.length=0.004:0.1", "heat_input=1:9"])
    res = search(space, (toy_objective,), n_trials=64, batch=16, seed=2)
    trials = [t for t in res.study.get_trials() if t.state.name == "COMPLETE"]
    best = res.best[0]
    # the search minimized the toy objective: its best is minus the largest gradient of all trials
    assert best["values"][toy_objective] == pytest.approx(-best["metrics"]["gradient"], rel=0, abs=1e-12)
    assert best["values"][toy_objective] == pytest.approx(
        -max(t.user_attrs["gradient"] for t in trials), rel=0, abs=1e-12
    )
    assert res.study.directions[0].name == "MINIMIZE"
    space_g = DesignSpace(load_core("rvc_foam"), ["stack.length=0.01:0.08:4", "heat_input=1:9:3"])
    sweep(space_g, tmp_path / "toy.nc", outputs=["gradient", toy_objective], chunk=5)
    ds = xr.open_dataset(tmp_path / "toy.nc", engine="h5netcdf")
    np.testing.assert_array_equal(ds[toy_objective].values, -ds.gradient.values)  # float32 negation is exact
    assert (
        ds[toy_objective].attrs["units"] == "K/m" and ds[toy_objective].attrs["long_name"] == "minus the stack gradient"
    )
    ds.close()


def test_onset_objectives_are_the_onset_of_the_closed_core():
    """Q_onset and onset_T_ratio of designs of the ceramic core equal onset() of the
    bundled standing-wave engine (whose core is the ceramic one) with the same stack
    values, set by set (1e-12); Q_onset_p90 with a zero-covariance material is Q_onset;
    with the ceramic's covariance it is the 90th percentile of onset() over the same draws."""
    import dataclasses

    from tawarp.design.catalogue import default_catalogue
    from tawarp.design.objectives import OnsetSpec
    from tawarp.model.onset import onset
    from tawarp.model.resonator import load_engine

    eng = load_engine("standing_wave")
    space = DesignSpace(load_core("ceramic"), ["stack.length=0.03:0.08", "stack.porosity=0.8:0.95"])
    pts = {"stack.length": np.array([0.048, 0.03, 0.07]), "stack.porosity": np.array([0.9, 0.85, 0.93])}
    cer = default_catalogue()["ceramic"]
    exact = dataclasses.replace(cer, std={})
    ev = Evaluator(
        space,
        extra=["Q_onset", "onset_T_ratio", "Q_onset_p90"],
        onset=OnsetSpec(Q_max=100.0, uncertainty=exact, n_draws=2),
    )
    m = ev.evaluate(pts)
    ref = onset(eng, Q_max=100.0, params=pts)
    np.testing.assert_allclose(m["Q_onset"], ref.Q_onset, rtol=1e-12)
    np.testing.assert_allclose(m["onset_T_ratio"], ref.T_hot / 293.15, rtol=1e-12)
    np.testing.assert_allclose(m["Q_onset_p90"], ref.Q_onset, rtol=1e-12)
    ev = Evaluator(space, extra=["Q_onset_p90"], onset=OnsetSpec(Q_max=100.0, uncertainty=cer, n_draws=8, seed=3))
    p90 = ev.evaluate(pts)["Q_onset_p90"]
    d = cer.sample(8, 3)
    for j in range(3):
        params = {
            "stack.length": pts["stack.length"][j],
            "stack.porosity": pts["stack.porosity"][j] + d["porosity"] - 0.9,
            "stack.pore_radius": d["pore_radius"],
            "stack.h": d["h_s"],
        }
        q = onset(eng, Q_max=100.0, params=params).Q_onset
        assert p90[j] == pytest.approx(np.percentile(q, 90), rel=1e-12)
    with pytest.raises(ValueError, match="uncertainty"):
        Evaluator(space, extra=["Q_onset_p90"]).evaluate(pts)


def test_design_search_on_onset(tmp_path):
    """``tawarp design --objectives Q_onset`` (one objective, CMA-ES) finds a ceramic stack
    that starts below the bundled engine's 25.09 W, and its stored value is onset() of
    that design; two objectives (Q_onset, onset_T_ratio) give a front with both columns."""
    import json

    from tawarp.cli import main
    from tawarp.model.onset import onset
    from tawarp.model.resonator import load_engine

    out = tmp_path / "d"
    assert (
        main(
            [
                "design",
                "ceramic",
                "--var",
                "stack.length=0.02:0.08",
                "--var",
                "stack.porosity=0.8:0.95",
                "--objectives",
                "Q_onset",
                "--trials",
                "48",
                "--batch",
                "16",
                "--Q-max",
                "100",
                "--no-plots",
                "-o",
                str(out),
                "--device",
                "cpu",
                "--quiet",
            ]
        )
        == 0
    )
    best = json.loads((out / "design.json").read_text())["best"][0]
    q = onset(load_engine("standing_wave"), Q_max=100.0, params=best["params"]).Q_onset[0]
    assert best["values"]["Q_onset"] == pytest.approx(q, rel=1e-12) and q < 25.0
    out2 = tmp_path / "d2"
    assert (
        main(
            [
                "design",
                "ceramic",
                "--var",
                "stack.length=0.02:0.08",
                "--objectives",
                "Q_onset,onset_T_ratio",
                "--trials",
                "32",
                "--batch",
                "16",
                "--no-plots",
                "-o",
                str(out2),
                "--device",
                "cpu",
                "--quiet",
            ]
        )
        == 0
    )
    front = json.loads((out2 / "design.json").read_text())["best"]
    assert front and all({"Q_onset", "onset_T_ratio"} <= set(b["values"]) for b in front)
