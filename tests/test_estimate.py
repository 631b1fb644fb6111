"""Batched Levenberg-Marquardt (tawarp.estimate, kernels/lm.py) on the CPU.

Sizes are small (16 frequencies, 8 Magnus cells in the fits, 12 in the data so that the
fit is not an inverse crime at Q > 0) so the file runs in well under a minute.
"""

import re

import numpy as np
import pytest

from tawarp.model.core import load_core
from tawarp.fit.estimate import FitWarning, Problems, fit
from tawarp.model.forward import ForwardSettings, transfer_matrices
from tawarp.measure.synthetic import paper_frequencies

FIT = ForwardSettings(cells=8, device="cpu")
GEOM = ["stack.porosity", "stack.pore_radius", "stack.tortuosity"]
HEAT = ["stack.h", "hot_hx.h", "tbt.h"]


def noisy(core, freqs, Q, n, seed, noise=0.005, cells=12):
    """n noise draws (n, m, 4) of the model at heat input Q and their sigma (m, 4)."""
    Y0 = transfer_matrices(core, freqs, Q, cells=cells, device="cpu").dimensionless()[0]
    sd = noise * np.abs(Y0) / np.sqrt(2)
    rng = np.random.default_rng(seed)
    return Y0 + sd * (rng.standard_normal((n,) + Y0.shape) + 1j * rng.standard_normal((n,) + Y0.shape)), sd


@pytest.mark.parametrize("m", [12, 13])
@pytest.mark.parametrize("jacobian, tol", [("difference", 1e-5), ("tangent", 1e-8), ("broyden", 1e-5)])
def test_normal_equations_match_central_differences(jacobian, tol, m):
    """The kernels' Jacobian (forward differences, the tangent cascade, or the secant
    store's forward differences at a start), reduced to H = J^T J and g = J^T r, against
    Richardson-extrapolated central differences of the forward model (transfer_matrices)
    in the same scaled variables; m = 13 frequencies is not a multiple of the kernels'
    row block (ROW_BLOCK frequencies per thread, the last block shorter)."""
    core = load_core("mesh")
    freqs = paper_frequencies("mesh", m)
    names = GEOM + ["stack.h"]
    Y, sd = noisy(core, freqs, 40.0, 1, seed=3)
    rng = np.random.default_rng(0)
    w = rng.uniform(0.5, 2.0, (1, m, 4, 2)) / sd[None, ..., None]
    start = np.array([0.7, 4.4e-5, 1.1, 40.0])
    prob = Problems(
        core, freqs, Y, names, heat_input=40.0, weights=w, settings=FIT, scale=start[None], jacobian=jacobian
    )
    z = prob.to_z(start * np.array([1.02, 0.97, 1.01, 1.1]), 0)
    if jacobian == "broyden":
        sums = prob.evaluate_start(np.array([0]), z[None], prob.secant_store(1))
    else:
        sums = prob.evaluate(np.array([0]), z[None])
    cost, raw, g, H = [a.numpy() for a in sums]
    # host reference: central differences at steps 2h and h in z, extrapolated (the h^2
    # terms cancel: ~1e-11 relative, rounding included)
    h = 1e-4
    zs = [z] + [z + s * k * h * e for e in np.eye(4) for k in (2, 1) for s in (1, -1)]
    vs = np.array([prob.to_v(zz, 0) for zz in zs])
    Ym = transfer_matrices(
        core, freqs, 40.0, params={k: vs[:, a] for a, k in enumerate(names)}, settings=FIT
    ).dimensionless()

    def real(Yc):
        d = np.stack([Yc.real, Yc.imag], axis=-1) * w[0]
        return d.reshape(-1)

    r = real(Ym[0] - Y[0])
    d2 = [(real(Ym[1 + 4 * a]) - real(Ym[2 + 4 * a])) / (4 * h) for a in range(4)]
    d1 = [(real(Ym[3 + 4 * a]) - real(Ym[4 + 4 * a])) / (2 * h) for a in range(4)]
    J = np.stack([(4 * d1[a] - d2[a]) / 3 for a in range(4)], axis=1)
    # forward differences (step 1e-6) have a truncation error ~1e-6 relative; the tangent
    # cascade's point coefficients come from central differences with step 1e-5: ~1e-10
    assert cost[0] == pytest.approx(r @ r, rel=1e-12)
    scale = np.sqrt(np.outer(np.diag(J.T @ J), np.diag(J.T @ J)))
    assert np.max(np.abs(H[0] - J.T @ J) / scale) < tol
    gscale = np.sqrt(np.diag(J.T @ J) * (r @ r))
    assert np.max(np.abs(g[0] - J.T @ r) / gscale) < tol
    # the unweighted sum of squares of the error measure
    assert raw[0] == pytest.approx(np.sum(np.abs(Ym[0] - Y[0]) ** 2), rel=1e-12)


def test_std_matches_scatter_over_noise_draws():
    """30 noise draws fitted as ONE batch: the reported std (mean over draws) agrees with
    the scatter of the estimates within a factor 1.5 (the sample std of 30 draws is
    uncertain by ~13 %, so 1.5 is a > 3 sigma bound), for geometry at Q = 0 and for the
    heat-exchange coefficients at Q = 9 W."""
    n = 30
    core = load_core("mesh")
    freqs = paper_frequencies("mesh", 16)
    Y, sd = noisy(core, freqs, 0.0, n, seed=11)
    r = fit(
        core,
        freqs,
        Y,
        GEOM,
        {"stack.porosity": 0.6, "stack.pore_radius": 6e-5, "stack.tortuosity": 1.2},
        weights=1 / sd,
        settings=FIT,
        warn=False,
    )
    assert r.converged.all()
    ratio = r.values.std(axis=0, ddof=1) / r.std.mean(axis=0)
    assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), ratio
    core = load_core("rvc_foam")
    Y, sd = noisy(core, freqs, 9.0, n, seed=12)
    r = fit(core, freqs, Y, HEAT, [12.0, 60.0, 0.5], heat_input=9.0, weights=1 / sd, settings=FIT, warn=False)
    assert r.converged.all()
    ratio = r.values.std(axis=0, ddof=1) / r.std.mean(axis=0)
    assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), ratio
    # s^2 estimates the variance of the weighted residual: ~1 with the true sigmas (8 m - p = 125
    # degrees of freedom per fit: mean over 30 fits within 5 %)
    assert abs(r.s2.mean() - 1) < 0.05


def test_lam_s_with_h_s_gives_the_warning():
    """The paper: the conductivities are too correlated with the h's to be fitted together.
    Fitting lam_s (stack.solid_conductivity) with h_s names that pair; a parameter with no
    sensitivity (stack.h at Q = 0) makes the problem ill-conditioned and is named."""
    core = load_core("nicr_foam")
    freqs = paper_frequencies("nicr_foam", 16)
    Y, sd = noisy(core, freqs, 40.0, 1, seed=5)
    names = ["stack.h", "stack.solid_conductivity", "hot_hx.h", "hot_hx.solid_conductivity", "tbt.h"]
    # every correlated pair is named (and the restarts' minima): all caught, this one asserted
    with pytest.warns(FitWarning) as caught:
        r = fit(
            core, freqs, Y, names, [core.get(k) * 1.2 for k in names], heat_input=40.0, weights=1 / sd, settings=FIT
        )
    assert any("stack.h and stack.solid_conductivity are too correlated" in str(w.message) for w in caught)
    assert abs(r.correlation[0, 0, 1]) > 0.95
    Y0, sd0 = noisy(core, freqs, 0.0, 1, seed=6)
    with pytest.warns(FitWarning) as caught:
        r = fit(core, freqs, Y0, ["stack.porosity", "stack.h"], [0.9, 30.0], weights=1 / sd0, settings=FIT, restarts=2)
    assert any(re.search("ill-conditioned.*mostly along stack.h", str(w.message)) for w in caught)
    assert not np.isfinite(r.std[0, 1])  # h has no effect at Q = 0: infinite std, not a number
    # a flat direction is a continuum of minima: the ±20 % restarts stay where they start
    assert r.distinct_minima[0]
    assert any("restarts landed in different minima" in w for w in r.warnings)


def test_restarts_agree_and_bounds_hold():
    """Restarts from the solution ±20 % come back (no distinct minima) and the bounds hold:
    a ceramic fitted with a free tortuosity, whose true value 1 is the lower bound."""
    core = load_core("ceramic")
    freqs = paper_frequencies("ceramic", 16)
    Y, sd = noisy(core, freqs, 0.0, 6, seed=7)
    ties = {"stack.porosity": ["hot_hx.porosity"], "stack.pore_radius": ["hot_hx.pore_radius"]}
    r = fit(
        core,
        freqs,
        Y,
        ["stack.porosity", "stack.pore_radius", "stack.tortuosity"],
        [0.8, 0.6e-3, 1.3],
        ties=ties,
        weights=1 / sd,
        settings=FIT,
        restarts=3,
        warn=False,
    )
    assert r.restart_values.shape == (6, 3, 3)
    assert not r.distinct_minima.any()
    assert r.restart_converged.all()
    assert np.all(r.values[:, 2] >= 1.0) and np.all(r.values[:, 0] <= 1.0)
    # restarts land within their stopping tolerance: 0.1 % steps leave < 1 % differences
    assert np.allclose(r.restart_values, r.values[:, None, :], rtol=1e-2)


def test_spread_of_starts_without_prior():
    """No start: a Sobol spread of 8 starts per problem; the best lands on the truth
    (within 2 std: 0.5 % noise, one draw) and the result says whether runs disagree."""
    core = load_core("rvc_foam")
    freqs = paper_frequencies("rvc_foam", 16)
    Y, sd = noisy(core, freqs, 0.0, 1, seed=8)
    r = fit(core, freqs, Y, GEOM, None, weights=1 / sd, settings=FIT, n_starts=8, warn=False)
    truth = np.array([core.get(k) for k in GEOM])
    assert np.all(np.abs(r.values[0] - truth) < 2 * r.std[0])
    assert r.distinct_minima is not None and r.distinct_minima.shape == (1,)


def test_early_converged_problem_keeps_its_answer():
    """Active-set compaction: a problem that converges early keeps exactly the answer it
    gets alone, while a slow problem in the same batch keeps iterating."""
    core = load_core("mesh")
    freqs = paper_frequencies("mesh", 12)
    Y, sd = noisy(core, freqs, 0.0, 2, seed=9)
    starts = np.array([[0.68, 4.0e-5, 1.06], [0.5, 1.2e-4, 1.6]])
    both = fit(core, freqs, Y, GEOM, starts, weights=1 / sd, settings=FIT, warn=False)
    alone = fit(core, freqs, Y[:1], GEOM, starts[:1], weights=1 / sd, settings=FIT, warn=False)
    assert both.converged.all()
    assert both.iterations[0] < both.iterations[1]
    # bitwise: the same launches (sets are independent threads) give the same numbers
    assert np.array_equal(both.values[0], alone.values[0])
    assert both.iterations[0] == alone.iterations[0]


def test_paper_damping_converges_to_the_same_answer():
    """Both damping rules reach the same minimum (to well inside the 0.1 % stopping rule's
    reach: 0.3 std)."""
    core = load_core("nicr_foam")
    freqs = paper_frequencies("nicr_foam", 12)
    Y, sd = noisy(core, freqs, 0.0, 4, seed=10)
    kw = dict(weights=1 / sd, settings=FIT, warn=False)
    a = fit(core, freqs, Y, GEOM, [0.8, 4e-4, 1.5], damping="nielsen", **kw)
    b = fit(core, freqs, Y, GEOM, [0.8, 4e-4, 1.5], damping="paper", **kw)
    assert a.converged.all() and b.converged.all()
    assert np.all(np.abs(a.values - b.values) < 0.3 * a.std)


def test_problem_warnings_formatted_when_read():
    """Per-problem warnings are groups formatted on reading (a 1e5-problem batch no longer
    formats 1e5 messages per fit): each problem gets exactly its groups' messages in order,
    the summary counts the problems of each, and a pickled copy (a Dask result) is the
    plain lists."""
    import pickle

    from tawarp.fit.estimate import _problem_warnings
    from tawarp.fit.result import ProblemWarnings

    N, names = 10, ["a", "b", "c"]
    corr = np.tile(np.eye(3), (N, 1, 1))
    corr[[2, 5, 7], 0, 2] = corr[[2, 5, 7], 2, 0] = 0.99
    cond = np.full(N, 10.0)
    cond[5] = 1e12
    V = np.tile(np.eye(3), (N, 1, 1))
    converged = np.ones(N, dtype=bool)
    converged[[1, 5]] = False
    reason = np.array(["xtol"] * N, dtype=object)
    reason[1], reason[5] = "max_iterations", "stalled"
    pw = ProblemWarnings(N, _problem_warnings(names, corr, cond, V, converged, reason, 0.95, 1e8))
    assert len(pw) == N and pw[0] == [] and pw[3] == []
    assert pw[2] == ["a and c are too correlated to separate (correlation +0.9900); fix one of them"]
    assert [m.split(" ")[0] for m in pw[5]] == ["a", "ill-conditioned", "did"] and "stalled" in pw[5][2]
    assert pw[1] == ["did not converge (max_iterations)"]
    summary = pw.summary()
    assert summary[0].startswith("3 of 10 problems (e.g. problem 2): a and c are too correlated")
    assert any(s.startswith("problem 5: ill-conditioned") for s in summary)
    copy = pickle.loads(pickle.dumps(pw))
    assert isinstance(copy, ProblemWarnings) and list(copy) == [pw[i] for i in range(N)] and pw == copy
    assert copy.summary() == summary


def test_problem_warnings_concatenate():
    """Joined batches (a cluster's chunks: some pickled, some plain lists) read as the
    concatenation of their lists, and the summary counts each warning over all of them."""
    import pickle

    from tawarp.fit.result import ProblemWarnings

    def batch(n, hits, key="cond"):
        return ProblemWarnings(n, [((key,), np.array(hits), lambda i: f"{key} {i}")])

    a, b = batch(4, [1, 3]), batch(3, [0, 2])
    lists = [[], ["x", "y"], []]
    parts = [a, pickle.loads(pickle.dumps(b)), lists, batch(2, [1], "other")]
    joined = ProblemWarnings.concatenate(parts)
    expected = [m for p in parts for m in (list(p) if not isinstance(p, list) else p)]
    assert len(joined) == 12 and list(joined) == expected
    assert joined[4] == ["cond 0"] and joined[6] == ["cond 2"] and joined[8] == ["x", "y"] and joined[11] == ["other 1"]
    assert joined.summary()[0] == "4 of 12 problems (e.g. problem 1): cond 1"
    assert list(pickle.loads(pickle.dumps(joined))) == expected


def test_cells_sized_at_the_starts_are_checked_at_the_solutions(monkeypatch):
    """fit() sizes its fixed cells at the starts with a margin of 1.25 on k; a start far
    below the truth (tbt.h at 0.3x) ends where the rule asks for more cells: the problems
    are re-run from their solutions with cells sized there, which cover the rule at the
    solutions, and the values agree with fits on 40 cells per segment (a converged model)
    to 2e-3 standard deviations (forward differences at every step: their last steps end
    far inside xtol, so the two fits differ by the model alone). A start near the truth
    needs no re-run."""
    from tawarp.fit import estimate
    from tawarp.measure.kind import smooth_settings

    core = load_core("mesh")
    freqs = paper_frequencies("mesh", 16)
    Y, sd = noisy(core, freqs, 40.0, 4, seed=11, cells=48)
    truth = np.array([core.get(k) for k in HEAT])
    runs = []
    original = estimate._cells_at_solutions
    monkeypatch.setattr(estimate, "_cells_at_solutions", lambda *a: runs.append(original(*a)) or runs[-1])
    for factor, rerun in (([1.0, 1.0, 0.3], True), ([1.2, 0.8, 1.2], False)):
        kw = dict(heat_input=40.0, weights=1 / sd, warn=False, jacobian="difference")
        r = fit(core, freqs, Y, HEAT, truth * np.array(factor), device="cpu", **kw)
        ref = fit(core, freqs, Y, HEAT, truth, settings=ForwardSettings(cells=40), **kw)
        assert (runs[-1] is not None) == rerun
        assert r.converged.all()
        assert np.max(np.abs(r.values - ref.values) / ref.std) < 2e-3
        if rerun:
            need = smooth_settings(core, freqs, None, {k: r.values[:, a] for a, k in enumerate(HEAT)}, 40.0, 1.0).cells
            used = runs[-1][0].settings.cells
            assert all(used[s] >= need[s] for s in need)
