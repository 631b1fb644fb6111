"""The fits' misfits and normal equations formed where the model values are
(tawarp.kernels.misfit; KindProblems.evaluate where the kinds predict on a GPU): the host's
cost, gradient and Gauss-Newton matrix to the rounding of their sums, and the host's fits.
Run on the CPU (the same kernels), the T-matrix kind with field, structural and host-side
effects, fits of some rows alone and a bootstrap's repeated rows, priors."""

import dataclasses

import numpy as np
import pytest
import warp as wp

from tawarp.fit.problems import KindProblems, fit_batch, residual
from tawarp.loop import default_base_params
from tawarp.measure.files import TMatrixData
from tawarp.measure.tmatrix import TMatrixKind
from tawarp.model.effects import tmatrix_library

from test_lockstep import FREQS, QS, mesh_kind

wp.init()


def _specs(kind, seed):
    """Fits of the base parameters alone and with a field (plane offsets, convection), a
    structural (porosity gradient) and a host-side effect (calibration), of the Q = 0 rows
    alone and of every row twice; starts within 20 % of the core's values."""
    rng = np.random.default_rng(seed)
    params = default_base_params(kind)
    lib = {e.name: e for e in tmatrix_library(kind.core)}
    specs = []
    for name in (None, "plane_offsets", "porosity_gradient", "calibration", "convection"):
        effect = lib.get(name)
        ps = params + (list(effect.params) if effect else [])
        specs.append((ps, effect, rng.uniform(-0.2, 0.2, len(ps))))
    q0 = kind.first_step_rows()
    specs.append((params[:3], None, rng.uniform(-0.2, 0.2, 3), q0))
    specs.append((params, None, rng.uniform(-0.2, 0.2, len(params)), np.repeat(np.arange(kind.y.size), 2)))
    return specs


def _padded(specs):
    z = np.zeros((len(specs), max(len(s[0]) for s in specs)))
    for c, s in enumerate(specs):
        z[c, : len(s[0])] = s[2]
    return z


@pytest.mark.parametrize(
    "device",
    [
        "cpu",
        pytest.param(
            "cuda",
            marks=[pytest.mark.gpu, pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device")],
        ),
    ],
)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_normal_equations_on_the_device_are_the_hosts(seed, device):
    kind = mesh_kind(seed)
    specs = _specs(kind, seed)
    if device != "cpu":
        # on a GPU no column is kept between evaluations (the CPU's memo), and a
        # temperature-dependent solve starts warm from another's: the same to its tolerance,
        # not to the bit, so the convection's fit is left out
        kind = TMatrixKind(kind.data, kind.core, dataclasses.replace(kind.settings, device=device))
        specs = [s for s in specs if s[1] is None or s[1].name != "convection"]
    z, pid = _padded(specs), np.arange(len(specs))
    host = KindProblems(kind, specs)
    host.evaluate(pid, z, host=True)  # the heat solves' warm starts and the column memo filled
    want = host.evaluate(pid, z, host=True)
    device = KindProblems(kind, specs)
    device.on_device = True
    got = device.evaluate(pid, z)
    # precondition: the device's path ran (it keeps no fit's J or model values)
    assert all(v is None for v in device.last) and all(v is not None for v in host.last)
    cost, raw, g, H = want
    # a start off the effect's range (a negative convection coefficient) is a bad point on both
    finite = np.isfinite(cost)
    assert np.array_equal(np.isfinite(got[0]), finite) and np.sum(finite) >= len(specs) - 2
    # the same terms summed in another order, and each model value to the rounding of its
    # last operations (a complex product's rounding may differ: the calibration's gain),
    # which the forward difference's step raises in J: within those bounds, four times over
    for c in np.flatnonzero(finite):
        J, Y = host.last[c]
        rows = host.rows[c]
        r = residual(kind, Y, rows)
        p = J.shape[1]
        dY = 4 * np.finfo(float).eps * np.abs(Y[rows])
        dJ = 4 * (np.concatenate([dY * kind.w[rows, 0], dY * kind.w[rows, 1]]) / 1e-6)[:, None]
        bound_g = dJ.T @ np.abs(r) + 1e-13 * (np.abs(J).T @ np.abs(r))
        bound_H = dJ.T @ np.abs(J) + np.abs(J).T @ dJ + 1e-13 * (np.abs(J).T @ np.abs(J))
        np.testing.assert_allclose(got[0][c], cost[c], rtol=1e-12)
        np.testing.assert_allclose(got[1][c], raw[c], rtol=1e-12)
        assert np.all(np.abs(got[2][c, :p] - g[c, :p]) <= bound_g)
        assert np.all(np.abs(got[3][c, :p, :p] - H[c, :p, :p]) <= bound_H)
        # the padding as the host leaves it
        assert np.all(got[2][c, p:] == g[c, p:]) and np.all(got[3][c, p:] == H[c, p:])
        assert np.all(got[3][c, :, p:] == H[c, :, p:])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_trials_neighbours_take_their_points_values(seed):
    # the launch's tables of fits at z with their forward-difference neighbours, made from
    # the points' values and the names each parameter sets (ValueLayout.neighbour_table),
    # against every set's values computed in full: equal to the bit, for fits with a field,
    # a structural and a host-side effect, some rows alone and repeated rows, at random
    # points, some components at their upper bound (a step towards the interior)
    from tawarp.fit.problems import FD_STEP

    kind = mesh_kind(seed)
    specs = _specs(kind, seed)
    lm = KindProblems(kind, specs)
    rng = np.random.default_rng(seed)
    z = _padded(specs) + rng.uniform(-0.3, 0.3, _padded(specs).shape)
    z = np.clip(z, lm.zlo, lm.zhi)
    z[:, 0] = np.where(np.isfinite(lm.zhi[:, 0]), lm.zhi[:, 0], z[:, 0])
    pid = np.arange(len(specs))
    step = np.where(z + FD_STEP > lm.zhi[pid], -FD_STEP, FD_STEP)
    sizes, X = lm._with_neighbours(pid, z, step)
    full, _, _ = lm._jobs(pid, sizes, X, False)
    got, _, _ = lm._jobs(pid, sizes, X, False, (z, step))
    assert len(got) == len(full) >= 2 and np.any(step < 0)
    for a, b in zip(full, got):
        assert a.values.names == b.values.names
        assert np.array_equal(a.values.array, b.values.array, equal_nan=True)


def _data_of(kind, truth_values, noise, seed):
    """The kind with its data the model's at ``truth_values`` plus relative noise."""
    Y = kind.predict({k: np.array([v]) for k, v in truth_values.items()}, 1)[0]
    rng = np.random.default_rng(seed)
    Yn = Y * (1 + noise * (rng.standard_normal(Y.size) + 1j * rng.standard_normal(Y.size)))
    nq, m = len(QS), FREQS.size
    T = np.empty((nq * m, 2, 2), dtype=complex)
    Zc = kind.Zc
    coef = Yn.reshape(nq * m, 4)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = coef[:, 0], coef[:, 1] * Zc, coef[:, 2] / Zc, coef[:, 3]
    data = TMatrixData(np.repeat(QS, m), np.tile(FREQS, nq), T)
    return TMatrixKind(data, kind.core, kind.settings)


@pytest.mark.parametrize("seed", [3, 4, 5, 6])
def test_fits_reduced_on_the_device_end_where_the_hosts_do(seed, monkeypatch):
    # the fits of a kind on a GPU (a trial and its neighbours in one call, reduced there)
    # against the same fits on the host: starts 10-30 % off the truth, data with 0.3 %
    # noise; the same optimum, the results' J and model values the host's at it
    base = mesh_kind(seed)
    params = default_base_params(base)
    rng = np.random.default_rng(seed)
    truth = {p.label: base.core.get(p.label) / (1 + rng.uniform(0.1, 0.3) * rng.choice([-1, 1])) for p in params}
    truth = {k: min(v, 0.95) if "porosity" in k else v for k, v in truth.items()}
    kind = _data_of(base, truth, 0.003, seed)
    specs = [(params, None, np.zeros(len(params))), (params[:2], None, np.zeros(2))]
    host = fit_batch(kind, specs)
    monkeypatch.setattr(TMatrixKind, "predicts_on_gpu", lambda self: True)
    device = fit_batch(kind, specs)
    for a, b in zip(host, device):
        assert a.converged[0] and b.converged[0]
        np.testing.assert_allclose(b.cost, a.cost, rtol=1e-9)
        np.testing.assert_allclose(b.values, a.values, rtol=1e-6 * max(1.0, float(np.max(a.std / a.values))))
        # its J and model values from one evaluation on the host at its solution
        lm = KindProblems(kind, [(p, e, x) for (p, e, _), x in zip(specs, [r.x[0] for r in device])])
        z = _padded([(p, e, r.x[0]) for (p, e, _), r in zip(specs, device)])
        lm.evaluate(np.arange(len(specs)), z, host=True)
        for c, r in enumerate(device):
            np.testing.assert_allclose(r.jacobian[0], lm.last[c][0], rtol=1e-6, atol=1e-9 * np.abs(lm.last[c][0]).max())
            np.testing.assert_allclose(r.model[0], lm.last[c][1], rtol=1e-9)
