"""The one least-squares engine (tawarp.fit.lm) and the kind fits on it (tawarp.fit.problems)
against the closed form of a linear model: y = A v + noise with known sigma, whose
weighted least-squares solution and covariance are the normal equations'
v = (A^T W A)^-1 A^T W y and C = (A^T W A)^-1."""

import numpy as np
import pytest

from tawarp.fit.lm import levenberg_marquardt
from tawarp.fit.problems import fit_batch
from tawarp.measure import MeasurementKind
from tawarp.model.effects import Param


def linear_case(seed, m=40, p=3):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((m, p))
    sigma = rng.uniform(0.5, 2.0, m)
    v_true = rng.uniform(-2.0, 2.0, p)
    y = A @ v_true + sigma * rng.standard_normal(m)
    W = np.diag(1 / sigma**2)
    C = np.linalg.inv(A.T @ W @ A)
    return A, sigma, y, C @ A.T @ W @ y, C


class LinearProblems:
    """LMProblems of r = (A z - y) / sigma with the exact Jacobian (N problems)."""

    def __init__(self, A, sigma, Y):
        self.A, self.sigma, self.Y = A, sigma, Y
        p = A.shape[1]
        self.zlo, self.zhi = np.full((len(Y), p), -np.inf), np.full((len(Y), p), np.inf)

    def change_rule(self):
        """|dz| / |z| (v = z: linear with scale 1, offset 0)."""
        N, p = self.zlo.shape
        return np.zeros(p, dtype=np.int32), np.ones((N, p)), np.zeros((N, p))

    def evaluate(self, pid, z, max_sets=0):
        J = self.A / self.sigma[:, None]
        r = (z @ self.A.T - self.Y[pid]) / self.sigma
        return np.sum(r**2, 1), np.sum(r**2, 1), r @ J, np.repeat((J.T @ J)[None], len(pid), axis=0)


@pytest.mark.parametrize("damping", ["nielsen", "paper"])
def test_lm_equals_normal_equations(damping):
    # one batch of three problems sharing A and sigma, different data
    A, sigma, y, _, _ = linear_case(0)
    Y = np.stack([y + k for k in range(3)])
    W = np.diag(1 / sigma**2)
    C = np.linalg.inv(A.T @ W @ A)
    prob = LinearProblems(A, sigma, Y)
    st = levenberg_marquardt(
        prob, np.arange(3), np.zeros((3, A.shape[1])), damping=damping, xtol=1e-15, gtol=1e-15, max_iter=200
    )
    # values to 1e-8: a step is accepted on a lower cost, and at 1e-9 from the minimum the
    # cost differs from it by ~1e-18 of itself, below rounding (seen: 4e-10 Nielsen, 1.3e-9
    # the paper's rule); the covariance from J^T J at the solution to 1e-10
    for i in range(3):
        v = C @ A.T @ W @ Y[i]
        assert np.max(np.abs(st.z[i] - v)) <= 1e-8 * np.max(np.abs(v))
        assert np.max(np.abs(np.linalg.inv(st.H[i]) - C)) <= 1e-10 * np.max(np.abs(C))


class LinearKind(MeasurementKind):
    """A measurement kind whose observable is linear in three named parameters: y = A v
    (real part; the imaginary part is an exact 0 with unit weight)."""

    name = "linear"
    coef_names = ("y",)

    def __init__(self, A, sigma, y):
        self.A = A
        self.y = y.astype(complex)
        self.w = np.stack([1 / sigma, np.ones_like(sigma)], axis=1)
        self.freq = np.arange(1.0, y.size + 1)
        self.group = np.zeros(y.size)
        self.coef = np.zeros(y.size, dtype=int)
        self.has_sigma = True

    def predict(self, values, n, effect=None):
        V = np.stack([np.broadcast_to(values[f"v{j}"], (n,)) for j in range(self.A.shape[1])], axis=1)
        return (V @ self.A.T).astype(complex)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kind_fit_equals_normal_equations(seed):
    # forward-difference Jacobian (step 1e-6) of a linear model: exact up to rounding of
    # |y| eps / 1e-6 ~ 1e-10 relative, so values and covariance agree to 1e-8
    A, sigma, y, v, C = linear_case(seed)
    kind = LinearKind(A, sigma, y)
    params = [Param(f"v{j}", (f"v{j}",), 0.5, 1.0) for j in range(3)]
    # the stopping rule tightened below what the loop uses (GTOL 1e-6 leaves ~1e-6 std)
    res = fit_batch(kind, [(params, None, None)], xtol=1e-14, gtol=1e-12)[0]
    assert res.converged[0]
    assert np.max(np.abs(res.values[0] - v)) <= 1e-8 * np.max(np.abs(v))
    assert np.max(np.abs(res.covariance[0] - C)) <= 1e-8 * np.max(np.abs(C))
    assert np.allclose(res.std[0], np.sqrt(np.diag(C)), rtol=1e-8)
    # chi^2 at the solution and the docs/formats.md error
    r = (A @ v - y) / sigma
    assert abs(res.cost[0] - r @ r) <= 1e-10 * (r @ r)
    assert abs(res.rms_error[0] - np.sqrt(np.mean((A @ v - y) ** 2) / np.mean(y**2))) <= 1e-8


@pytest.mark.parametrize("seed", [0, 1])
def test_map_fit_covariance_is_the_posterior_one(seed):
    # a Gaussian prior (mu, sd) in x on each parameter of the linear model (x = (v - 0.5) /
    # scale): the posterior is Gaussian with precision P = S (A^T W A) S + diag(1/sd^2) in x
    # (S = diag(scale)), mean x* = P^-1 (S A^T W (y - A 0.5) + mu / sd^2), and in values
    # C_v = S P^-1 S; the MAP fit's values and covariance are these to 1e-8
    A, sigma, y, _, _ = linear_case(seed)
    kind = LinearKind(A, sigma, y)
    scale = np.array([1.0, 0.5, 2.0])
    params = [Param(f"v{j}", (f"v{j}",), 0.5, scale[j]) for j in range(3)]
    mu, sd = np.array([0.3, -1.0, 0.2]), np.array([0.4, 1.0, 0.05])
    res = fit_batch(kind, [(params, None, None)], xtol=1e-14, gtol=1e-12, priors=[(mu, sd)])[0]
    W, S = np.diag(1 / sigma**2), np.diag(scale)
    P = S @ A.T @ W @ A @ S + np.diag(1 / sd**2)
    x = np.linalg.solve(P, S @ A.T @ W @ (y - A @ np.full(3, 0.5)) + mu / sd**2)
    C = S @ np.linalg.inv(P) @ S
    assert res.converged[0]
    assert np.max(np.abs(res.values[0] - (0.5 + scale * x))) <= 1e-8 * np.max(np.abs(0.5 + scale * x))
    assert np.max(np.abs(res.covariance[0] - C)) <= 1e-8 * np.max(np.abs(C))
    # the third prior is tight (sd 0.05 against the data's ~0.3): the posterior sd is near it
    assert np.isclose(res.std[0, 2], np.sqrt(C[2, 2]), rtol=1e-8) and res.std[0, 2] < 0.05 * scale[2]


class ExpKind(LinearKind):
    """y = A exp(v): a nonlinear kind (its LM takes several damped steps), each parameter
    set's prediction the same numbers in any batch (no matrix product, whose blocking
    depends on the batch: the forward kernels give each set its own thread)."""

    def predict(self, values, n, effect=None):
        V = np.stack([np.broadcast_to(values[f"v{j}"], (n,)) for j in range(self.A.shape[1])], axis=1)
        self.calls = getattr(self, "calls", 0) + 1
        self.points = getattr(self, "points", 0) + n
        return np.sum(np.exp(V)[:, None, :] * self.A[None], axis=-1).astype(complex)


def _exp_case():
    A, sigma, y, _, _ = linear_case(3)
    kind = ExpKind(A, sigma, A @ np.exp([0.3, -0.2, 0.5]) + sigma * 0.01)
    params = [Param(f"v{j}", (f"v{j}",), 0.5, 1.0) for j in range(3)]
    specs = [(params, None, np.zeros(3)), (params[:2], None, np.full(2, 0.8)), (params, None, np.full(3, -1.0))]
    return kind, specs


def test_kind_fit_results_are_the_evaluation_at_the_solution():
    # fit_batch takes each fit's Jacobian and model values from the iterations' evaluation at
    # its solution, not from one more evaluation: the same numbers, bit for bit, as a fresh
    # one there, with one predict call for the starts and at most two per LM iteration (the
    # trials, then the neighbours of those that lower their fit's cost)
    from tawarp.fit.problems import KindProblems

    kind, specs = _exp_case()
    res = fit_batch(kind, specs, xtol=1e-12, gtol=1e-10)
    iterations = max(int(r.iterations[0]) for r in res)
    assert 1 + iterations <= kind.calls <= 1 + 2 * iterations
    lm = KindProblems(kind, specs)
    z = np.zeros((len(specs), 3))
    for c, r in enumerate(res):
        z[c, : r.x.shape[1]] = r.x[0]
    lm.evaluate(np.arange(len(specs)), z)
    for c, r in enumerate(res):
        assert np.array_equal(r.jacobian[0], lm.last[c][0]) and np.array_equal(r.model[0], lm.last[c][1])


def test_rejected_trials_cost_no_jacobian(monkeypatch):
    # KindProblems.evaluate forms the forward differences of an LM trial only where the
    # trial beats its fit's cost (the LM rejects the others whatever their Jacobian): the
    # same fits, bit for bit, as with every trial's Jacobian evaluated (a kind whose
    # neighbours share their point's columns), on fewer points
    kind, specs = _exp_case()
    lazy = fit_batch(kind, specs, xtol=1e-12, gtol=1e-10)
    lazy_points = kind.points
    monkeypatch.setattr(ExpKind, "neighbours_share_columns", True)
    kind.points = 0
    full = fit_batch(kind, specs, xtol=1e-12, gtol=1e-10)
    for a, b in zip(lazy, full):
        assert a.reason[0] == b.reason[0] and a.iterations[0] == b.iterations[0]
        assert np.array_equal(a.x, b.x) and np.array_equal(a.jacobian, b.jacobian)
    # precondition: some trial was rejected (a damped LM on this nonlinear model rejects
    # steps), and each rejected one saved its fit's p neighbours
    assert lazy_points < kind.points


def test_on_a_gpu_a_trial_and_its_neighbours_share_one_launch(monkeypatch):
    # where the kind predicts on a GPU (a launch costs its latency whatever its sets),
    # KindProblems.evaluate predicts each LM trial with its neighbours in one call: one call
    # per iteration instead of up to two, the same fits bit for bit
    kind, specs = _exp_case()
    lazy = fit_batch(kind, specs, xtol=1e-12, gtol=1e-10)
    lazy_calls = kind.calls
    monkeypatch.setattr(ExpKind, "predicts_on_gpu", lambda self: True)
    kind.calls = 0
    gpu = fit_batch(kind, specs, xtol=1e-12, gtol=1e-10)
    for a, b in zip(lazy, gpu):
        assert a.reason[0] == b.reason[0] and a.iterations[0] == b.iterations[0]
        assert np.array_equal(a.x, b.x) and np.array_equal(a.jacobian, b.jacobian)
    assert kind.calls == 1 + max(int(r.iterations[0]) for r in gpu) < lazy_calls


def test_a_kind_that_reduces_on_a_gpu_gets_the_hosts_optima(monkeypatch):
    # a kind that says so (MeasurementKind.reduces_on_device) has its fits' misfits and
    # normal equations formed on the device (tawarp.kernels.misfit, here on the CPU; this
    # kind's host values copied there by the default predict_on_device): one call per
    # iteration and one on the host at the solutions for their Jacobians; the optima to the
    # rounding of the sums (not the same stopping rule or iteration: these tolerances are
    # at the rounding)
    kind, specs = _exp_case()
    host = fit_batch(kind, specs, xtol=1e-12, gtol=1e-10)
    monkeypatch.setattr(ExpKind, "predicts_on_gpu", lambda self: True)
    monkeypatch.setattr(ExpKind, "reduces_on_device", True)
    kind.calls = 0
    gpu = fit_batch(kind, specs, xtol=1e-12, gtol=1e-10)
    for a, b in zip(host, gpu):
        np.testing.assert_allclose(b.x, a.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(b.cost, a.cost, rtol=1e-12)
        np.testing.assert_allclose(b.jacobian, a.jacobian, rtol=1e-6)
    assert kind.calls == 2 + max(int(r.iterations[0]) for r in gpu)


def test_decrement_stops_within_its_cost_of_the_minimum():
    # levenberg_marquardt's decrement: a fit stops (converged, reason "decrement") where the
    # Gauss-Newton step would lower its cost by less than eps, before the tight gradient
    # test; near the minimum the quadratic model holds, so its cost is within eps (and a
    # little rounding) of the gtol-converged fit's from the same start, in fewer iterations
    kind, specs = _exp_case()
    tight = fit_batch(kind, specs, xtol=1e-14, gtol=1e-12)
    for eps in (1e-2, 1e-4):
        early = fit_batch(kind, specs, xtol=1e-14, gtol=1e-12, decrement=eps)
        for a, b in zip(early, tight):
            assert b.converged[0] and a.converged[0] and a.reason[0] == "decrement"
            assert a.iterations[0] < b.iterations[0]
            assert b.cost[0] - 1e-12 <= a.cost[0] <= b.cost[0] + eps


def test_dropped_starts_leave_the_others_alone():
    # levenberg_marquardt's drop: a start dropped after its first iteration stops there
    # (reason "dropped", not converged); the other fits run as they would without it
    kind, specs = _exp_case()
    alone = fit_batch(kind, specs[:2], xtol=1e-12, gtol=1e-10)
    seen = []

    def drop(slots, cost):
        seen.append(cost.size)
        return slots == 2

    raced = fit_batch(kind, specs, xtol=1e-12, gtol=1e-10, drop=drop)
    assert seen[0] == 3
    assert raced[2].reason[0] == "dropped" and not raced[2].converged[0] and raced[2].iterations[0] == 1
    for a, b in zip(alone, raced[:2]):
        assert a.reason[0] == b.reason[0] != "dropped" and a.converged[0] and b.converged[0]
        assert np.array_equal(a.x, b.x) and np.array_equal(a.jacobian, b.jacobian)


def test_superseded_starts_come_back_as_none():
    # starts of one fit (fit_batch's starts): three starts of the full model from near the
    # optimum meet, a fourth start (another label) is dropped alone, a fit without a label
    # is dropped too. The starts that stopped dropped or merged beside a start of their fit
    # that did neither come back as None; the others as they would alone, to the bit
    kind, specs = _exp_case()
    params = specs[0][0]
    near = [(params, None, np.array(x)) for x in ([0.25, -0.15, 0.45], [0.3, -0.25, 0.55], [0.35, -0.2, 0.5])]
    batch = near + [specs[2], specs[1]]

    def drop(slots, cost):
        return slots >= 3

    got = fit_batch(kind, batch, xtol=1e-12, gtol=1e-10, drop=drop, starts=np.array([0, 0, 0, 1, -1]), merge=10.0)
    reasons = [None if f is None else f.reason[0] for f in got]
    # precondition: two of the three near starts met the third
    assert sum(f is None for f in got[:3]) == 2, reasons
    lead = next(i for i in range(3) if got[i] is not None)
    assert got[lead].reason[0] not in ("merged", "dropped")
    # a fit whose every start stopped keeps them all; a start without a label is kept
    assert got[3] is not None and got[3].reason[0] == "dropped"
    assert got[4] is not None and got[4].reason[0] == "dropped"
    alone = fit_batch(kind, [batch[lead]], xtol=1e-12, gtol=1e-10)[0]
    assert np.array_equal(alone.x, got[lead].x) and np.array_equal(alone.jacobian, got[lead].jacobian)
    assert np.array_equal(alone.covariance, got[lead].covariance)


def test_which_starts_are_superseded():
    # per call's labels: a start that stopped dropped or merged is superseded only where
    # another start of its fit did neither; unlabelled fits never are
    from tawarp.fit.problems import FitCall, _starts, _superseded

    calls = [
        FitCall(None, [0] * 5, starts=np.array([0, 0, 0, 1, 1]), merge=10.0),
        FitCall(None, [0] * 1),
        FitCall(None, [0] * 2, starts=np.array([0, 0]), merge=10.0),
    ]
    reason = ["gtol", "merged", "dropped", "dropped", "merged", "dropped", "merged", "decrement"]
    got = _superseded(_starts(calls)["starts_of"], np.array(reason, dtype=object))
    assert got.tolist() == [False, True, True, False, False, False, True, False]
    assert _starts(calls[1:2]) == {} and not _superseded(None, np.array(["dropped"], dtype=object)).any()
    # a call with labels and no fits beside one without labels
    empty = [FitCall(None, [], starts=np.array([], dtype=int), merge=10.0), calls[1]]
    assert not _superseded(_starts(empty)["starts_of"], np.array(["dropped"], dtype=object)).any()


def _bowls(rng, n, p):
    """n quadratic bowls F = (z - m)^T A (z - m) + c: each point's Gauss-Newton model is
    exact, so the minimum it predicts is the bowl's own m."""
    B = rng.standard_normal((n, p, p))
    return B @ np.swapaxes(B, 1, 2) + 0.5 * np.eye(p)


def _at(A, m, z, c=0.0):
    """z, g, H and cost at z of the bowl (A, m) whose minimum costs c."""
    d = z - m
    return z, A @ d, A, float(d @ A @ d) + c


def test_starts_meet_where_their_models_predict_one_minimum():
    # stop_tests on exact quadratic bowls, where each start's Gauss-Newton model is its
    # bowl: a start meets its problem's lead (the lowest cost of the open slots) where the
    # predicted minima lie within merge sd in the lead's metric, at costs within MEET_COST,
    # and the lead's model predicts the start's cost. Each slot below fails one of these or
    # passes them all; the lead, a start without a problem (label -1) and one whose H is
    # not positive definite never stop. The decrements it returns beside are each slot's
    # g^T H^-1 g (no bounds here), inf where H is not positive definite.
    from tawarp.fit.lm import MEET_COST, stop_tests

    rng = np.random.default_rng(5)
    p = 3
    A = _bowls(rng, 6, p)
    m = rng.uniform(-1.0, 1.0, p)
    u = rng.standard_normal(p)

    def sd(Ak, s):  # a step of s sd along u in the metric of Ak
        return s * u / np.sqrt(u @ Ak @ u)

    half = m + sd(A[1], 0.5)
    rows = [
        _at(A[0], m, m + 0.01),  # 0: problem 0's lead
        _at(A[0], m, m + sd(A[0], 40.0)),  # 1: its bowl, 40 sd away: meets
        _at(A[1], m, m - 0.01),  # 2: problem 1's lead
        _at(A[1], half, half + 0.01),  # 3: a minimum 0.5 sd off: meets at merge 10, not 0.4
        _at(A[2], m, m + 0.02),  # 4: problem 2's lead
        _at(A[2], m, m + 0.3, c=2.0 * MEET_COST),  # 5: one place, another cost: stays
        _at(A[3], m, m),  # 6: problem 3's lead
        _at(4.0 * A[3], m, m + sd(A[3], 2.0)),  # 7: one minimum, a steeper cost: stays
        _at(A[4], m, m + 0.05),  # 8: no problem
        _at(A[4], m, m + 0.02),  # 9: problem 4's lowest, dropped: not open
        _at(A[4], m, m + 0.03),  # 10: problem 4's lead then
        _at(A[4], m, m + 0.5),  # 11: meets 10
        _at(A[5], m, m + 0.04),  # 12: problem 5's lead
        _at(-A[5], m, m + 0.6),  # 13: H not positive definite
    ]
    z, g, H, cost = (np.array(a) for a in zip(*rows))
    cost[13] = cost[12] + 1.0
    starts_of = np.array([0, 0, 1, 1, 2, 2, 3, 3, -1, 4, 4, 4, 5, 5])
    open_ = np.ones(z.shape[0], dtype=bool)
    open_[9] = False
    lo, hi = np.full(z.shape, -np.inf), np.full(z.shape, np.inf)
    slots = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 10, 11, 12, 13])
    Q = z.shape[0]
    dec, got = stop_tests(z, g, H, lo, hi, cost, slots, starts_of, np.full(Q, 10.0), open_)
    assert dict(zip(slots.tolist(), got.tolist())) == {
        0: False, 1: True, 2: False, 3: True, 4: False, 5: False, 6: False, 7: False,
        8: False, 10: False, 11: True, 12: False, 13: False,
    }  # fmt: skip
    want = np.array([np.inf if i == 13 else g[i] @ np.linalg.solve(H[i], g[i]) for i in slots])
    assert np.array_equal(np.isinf(dec), np.isinf(want))
    assert np.allclose(dec[np.isfinite(want)], want[np.isfinite(want)], rtol=1e-10, atol=1e-14)
    _, none = stop_tests(z, g, H, lo, hi, cost, slots, starts_of, np.zeros(Q), open_)
    assert not none.any()
    _, tight = stop_tests(z, g, H, lo, hi, cost, slots, starts_of, np.full(Q, 0.4), open_)
    assert tight.tolist() == [s in (1, 11) for s in slots.tolist()]


class TwoWells:
    """LMProblems of r = [(z^2 - 4) / 0.1, 0.1 (z - 1)]: minima near z = +2 and z = -2, the
    one at +2 lower; its posterior sd is about 0.025, so the wells lie ~160 sd apart."""

    zlo, zhi = np.full((1, 1), -10.0), np.full((1, 1), 10.0)

    def change_rule(self):
        return np.zeros(1, dtype=np.int32), np.ones((1, 1)), np.zeros((1, 1))

    def evaluate(self, pid, z, max_sets=0):
        z = np.asarray(z)[:, 0]
        r = np.stack([(z**2 - 4.0) / 0.1, 0.1 * (z - 1.0)], axis=1)
        J = np.stack([2.0 * z / 0.1, np.full_like(z, 0.1)], axis=1)
        cost = np.sum(r**2, 1)
        return cost, cost, np.sum(r * J, 1)[:, None], np.sum(J * J, 1)[:, None, None]


def test_starts_that_meet_end_in_their_leads_minimum_and_wells_stay_apart():
    # levenberg_marquardt's merge on one problem started four times: of the three starts in
    # the well at +2 two meet the third (reason "merged", not converged), which ends as it
    # would alone, to the bit, at the well's minimum; the start in the other well runs to
    # its own minimum; the merged starts take fewer iterations than they would alone
    prob = TwoWells()
    z0 = np.array([[1.0], [3.0], [1.5], [-1.0]])
    kw = dict(xtol=1e-14, gtol=1e-12, max_iter=100)
    alone = levenberg_marquardt(prob, np.zeros(4, dtype=int), z0, **kw)
    met = levenberg_marquardt(prob, np.zeros(4, dtype=int), z0, starts_of=np.zeros(4, dtype=int), merge=10.0, **kw)
    assert np.allclose(alone.z[:3, 0], 2.0, atol=0.01) and np.isclose(alone.z[3, 0], -2.0, atol=0.01)
    kept = [i for i in range(3) if met.reason[i] != "merged"]
    assert len(kept) == 1
    lead = kept[0]
    assert met.reason[lead] == alone.reason[lead] and met.converged[lead]
    assert np.array_equal(met.z[lead], alone.z[lead]) and met.cost[lead] == alone.cost[lead]
    assert met.cost[lead] <= alone.cost[:3].min() * (1 + 1e-12)
    others = [i for i in range(3) if i != lead]
    assert all(met.reason[i] == "merged" and not met.converged[i] for i in others)
    assert sum(met.iterations[others]) < sum(alone.iterations[others])
    assert met.reason[3] != "merged" and np.array_equal(met.z[3], alone.z[3])


def test_each_calls_starts_keep_their_own_labels():
    # fits of several calls in one LM: a call's start labels follow those of the calls
    # before it, so starts of different calls never meet; a call without labels has none
    from tawarp.fit.problems import FitCall, _starts

    calls = [
        FitCall(None, [0] * 3, starts=np.array([0, 0, 1]), merge=10.0),
        FitCall(None, [0] * 2),
        FitCall(None, [0] * 2, starts=np.array([0, 0]), merge=5.0),
    ]
    got = _starts(calls)
    assert got["starts_of"].tolist() == [0, 0, 1, -1, -1, 2, 2]
    assert got["merge"].tolist() == [10.0, 10.0, 10.0, 0.0, 0.0, 5.0, 5.0]
    assert _starts(calls[1:2]) == {}


def test_newton_decrement_of_a_batch_is_each_slots_reduced_one():
    # slots with components on their bounds (pulled out of the range: not free; pulled in:
    # free), pinned padding (zlo = zhi), a step that would leave the range and an H that is
    # not positive definite: each slot's decrement is g^T H^-1 g on its free components
    # alone, inf where that H has no Cholesky factor or the step leaves the range
    from tawarp.fit.lm import newton_steps

    rng = np.random.default_rng(3)
    n, p = 40, 5
    B = rng.standard_normal((n, p, p))
    H = B @ np.swapaxes(B, 1, 2) + 0.1 * np.eye(p)
    H[3] = -H[3]  # not positive definite
    g = rng.standard_normal((n, p))
    z = rng.uniform(-1.0, 1.0, (n, p))
    zlo, zhi = np.full((n, p), -3.0), np.full((n, p), 3.0)
    zlo[::4, 0] = z[::4, 0]  # on a lower bound
    zhi[1::4, 1] = z[1::4, 1]  # on an upper bound
    zlo[:, 4] = zhi[:, 4] = 0.0  # padding
    z[:, 4] = 0.0
    zhi[2::7, 2] = z[2::7, 2] + 1e-3  # a step that leaves the range
    got = newton_steps(z, g, H, zlo, zhi).decrement()
    want = np.full(n, np.inf)
    for i in range(n):
        f = (zhi[i] > zlo[i]) & ~((z[i] <= zlo[i]) & (g[i] > 0)) & ~((z[i] >= zhi[i]) & (g[i] < 0))
        Hf = H[i][np.ix_(f, f)]
        if np.any(np.linalg.eigvalsh(Hf) <= 0):
            continue
        d = np.linalg.solve(Hf, g[i, f])
        to = z[i, f] - d
        if np.all((to > zlo[i, f]) & (to < zhi[i, f])):
            want[i] = g[i, f] @ d
    assert np.isinf(got[3]) and np.isinf(want[3])
    assert np.sum(np.isfinite(want)) > n // 2 and np.sum(np.isinf(want)) >= 3
    assert np.array_equal(np.isfinite(got), np.isfinite(want))
    finite = np.isfinite(want)
    assert np.allclose(got[finite], want[finite], rtol=1e-10, atol=0.0)


@pytest.mark.parametrize("block_bytes", [None, 80])
def test_value_layout_is_param_assign_bit_for_bit(block_bytes, monkeypatch):
    # the vectorized parameter values of a group of fits equal Param.assign's, parameter by
    # parameter in order, to the bit: log and linear parameters, ties, two parameters
    # setting one name (the last wins), a parameter with its own expand, and names a fit
    # leaves at its own base value (each fit's core differs); formed in one block or in
    # blocks of two sets
    from tawarp.fit import problems
    from tawarp.fit.problems import ValueLayout

    if block_bytes is not None:
        monkeypatch.setattr(problems, "BLOCK_BYTES", block_bytes)

    def halves(v):
        return {"a.x": v / 2.0, "c.z": v * 3.0}

    a = Param("a.x", ("a.x", "b.y"), 0.37, log=True)
    b = Param("b.y", ("b.y",), 1.5, scale=0.01)
    c = Param("c.z", ("c.z",), 2.0, scale=0.3)
    e = Param("e.w", ("e.w",), 0.8, log=True, expand=halves)
    fits = [[a, b], [c], [b, a, c], [a, e], []]
    base = {"a.x": 0.37, "b.y": 1.5, "c.z": 2.0, "d.u": -4.0, "e.w": 0.8}
    rng = np.random.default_rng(3)
    requests = [(c_, rng.normal(0.0, 2.0, (int(rng.integers(1, 6)), len(ps)))) for c_, ps in enumerate(fits)]
    requests += [(2, rng.normal(0.0, 2.0, (3, 3)))]
    sizes = [X.shape[0] for _, X in requests]
    # the sets' x as the rows of one array, each fit's in its first p columns
    X_all = np.zeros((sum(sizes), 3))
    k0 = 0
    for (_, X), n in zip(requests, sizes):
        X_all[k0 : k0 + n, : X.shape[1]] = X
        k0 += n
    set_fits = np.repeat([c_ for c_, _ in requests], sizes)
    # each fit's own base: its core's value of a name differs from the others'
    rows = np.array([list(base.values())] * len(fits)) + np.arange(len(fits))[:, None]
    got = ValueLayout(tuple(base), rows, list(range(len(fits))), fits).table(set_fits, X_all)
    assert list(got) == list(base) and len(got) == len(base) and "d.u" in got and "q" not in got
    # the names the fits set alone, in another order: those rows of the whole table
    names = ("e.w", "c.z", "a.x", "b.y")
    part = ValueLayout(tuple(base), rows, list(range(len(fits))), fits).table(set_fits, X_all, names)
    assert tuple(part) == names
    np.testing.assert_array_equal(part.array, got.array[[4, 2, 0, 1]])
    k0 = 0
    for (c_, X), n in zip(requests, sizes):
        own = {}
        for j, par in enumerate(fits[c_]):
            par.assign(par.value(X[:, j]), own)
        for name, v in zip(base, rows[c_]):
            np.testing.assert_array_equal(got[name][k0 : k0 + n], np.broadcast_to(own.get(name, v), (n,)))
        k0 += n


def test_misfits_in_blocks_are_the_whole_batchs(monkeypatch):
    # KindProblems.evaluate forms a batch's misfits in blocks of at most BLOCK_BYTES: the
    # same cost, gradient and Gauss-Newton matrix, bit for bit, as in one block
    from tawarp.fit import problems
    from tawarp.fit.problems import KindProblems

    kind, specs = _exp_case()
    specs = specs * 7
    z = np.random.default_rng(5).normal(0.0, 0.3, (len(specs), 3))
    whole = KindProblems(kind, specs).evaluate(np.arange(len(specs)), z)
    monkeypatch.setattr(problems, "BLOCK_BYTES", 3 * 4 * 16 * kind.y.size)  # three fits a block
    blocks = KindProblems(kind, specs).evaluate(np.arange(len(specs)), z)
    for a, b in zip(whole, blocks):
        np.testing.assert_array_equal(a, b)
