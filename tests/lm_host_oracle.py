"""The host (NumPy) batched Levenberg-Marquardt the package ran before the LM iteration moved to the device, kept
here only as the oracle of :func:`tawarp.fit.lm.levenberg_marquardt` (the device kernels
of :mod:`tawarp.kernels.lm_step` must take the same decisions)."""

import numpy as np

from tawarp.fit.lm import LMProblems, LMState
from tawarp.kernels import lm_step


def _project(prob, z, pid):
    return np.clip(z, prob.zlo[pid], prob.zhi[pid])


def _evaluate(prob, pid, z, max_sets):
    """The evaluation in NumPy (Warp arrays copied back), an invalid one's cost inf."""
    cost, raw, g, H = [a.numpy() if hasattr(a, "numpy") else np.asarray(a) for a in prob.evaluate(pid, z, max_sets)]
    bad = ~(np.isfinite(cost) & np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(H), axis=(1, 2)))
    cost = np.where(bad, np.inf, cost)
    return cost, raw, g, H


def _relative_change(prob, dz, z, pid):
    """The problem's change rule (:meth:`LMProblems.change_rule`) on the host."""
    kind, scale, offset = prob.change_rule()
    s, o = scale[pid], offset[pid]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        lin = s * np.abs(dz) / np.maximum(np.abs(o + s * z), 1e-300)
        return np.where(
            kind == lm_step.CHANGE_LOG, np.abs(np.expm1(dz)), np.where(kind == lm_step.CHANGE_LINEAR, lin, np.abs(dz))
        )


def chol_solve(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve A x = b for a batch of small symmetric positive definite A (n, p, p) by a
    vectorised Cholesky factorisation; returns (x, ok) with ok False where A is not
    positive definite (x is then 0)."""
    n, p = b.shape
    L = np.zeros_like(A)
    ok = np.ones(n, dtype=bool)
    for j in range(p):
        d = A[:, j, j] - np.sum(L[:, j, :j] ** 2, axis=1)
        ok &= d > 0
        L[:, j, j] = np.sqrt(np.where(d > 0, d, 1.0))
        for i in range(j + 1, p):
            L[:, i, j] = (A[:, i, j] - np.sum(L[:, i, :j] * L[:, j, :j], axis=1)) / L[:, j, j]
    y = np.zeros_like(b)
    for i in range(p):
        y[:, i] = (b[:, i] - np.sum(L[:, i, :i] * y[:, :i], axis=1)) / L[:, i, i]
    x = np.zeros_like(b)
    for i in reversed(range(p)):
        x[:, i] = (y[:, i] - np.sum(L[:, i + 1 :, i] * x[:, i + 1 :], axis=1)) / L[:, i, i]
    x[~ok] = 0.0
    return x, ok


def _free_mask(z, g, zlo, zhi):
    """Components not held at a bound by a gradient pushing outward."""
    at_lo = (z <= zlo) & (g > 0)
    at_hi = (z >= zhi) & (g < 0)
    return ~(at_lo | at_hi)


def _grad_cosine(g, H, cost, free):
    den = np.sqrt(np.maximum(np.einsum("nii->ni", H), 1e-300) * np.maximum(cost, 1e-300)[:, None])
    c = np.where(free, np.abs(g) / den, 0.0)
    return c.max(axis=1) if c.shape[1] else np.zeros(len(c))


def levenberg_marquardt(
    prob: LMProblems,
    pid: np.ndarray,
    z0: np.ndarray,
    *,
    damping: str = "nielsen",
    xtol: float = 1e-3,
    gtol: float = 1e-8,
    max_iter: int = 100,
    tau: float = 1e-3,
    progress: bool = False,
    max_sets: int = 1 << 20,
) -> LMState:
    """Run batched LM on problems with data index ``pid`` (Q,) from scaled starts ``z0``
    (Q, p). Converged problems drop out of later launches (active-set compaction).
    ``prob``: any :class:`tawarp.fit.lm.LMProblems`."""
    if damping not in ("nielsen", "paper"):
        raise ValueError(f"damping = {damping!r}; expected 'nielsen' or 'paper'")
    Q, p = z0.shape
    z = _project(prob, np.array(z0, dtype=float), pid)
    cost, raw, g, H = _evaluate(prob, pid, z, max_sets)
    iterations = np.zeros(Q, dtype=int)
    reason = np.array([""] * Q, dtype=object)
    converged = np.zeros(Q, dtype=bool)
    bad = ~np.isfinite(cost)
    reason[bad] = "invalid"
    mu = tau * np.max(np.einsum("nii->ni", H), axis=1)
    mu = np.where(np.isfinite(mu) & (mu > 0), mu, 1e-3)
    nu = np.full(Q, 2.0)
    free = _free_mask(z, g, prob.zlo[pid], prob.zhi[pid])
    done0 = (_grad_cosine(g, H, cost, free) <= gtol) | (cost == 0)
    reason[done0 & ~bad] = "gtol"
    converged[done0 & ~bad] = True
    active = np.flatnonzero(~(bad | done0))
    eye = np.eye(p)
    while active.size:
        a = active
        pa = pid[a]
        A = H[a] + mu[a, None, None] * eye
        # the step on the free components only: a component held at its bound would otherwise
        # take part in the solve, and projecting the full step back onto the bound leaves a
        # direction that need not descend (the fit then stalls at the bound)
        fr = _free_mask(z[a], g[a], prob.zlo[pa], prob.zhi[pa])
        both = fr[:, :, None] & fr[:, None, :]
        A = np.where(both, A, eye)
        d, ok_chol = chol_solve(A, np.where(fr, -g[a], 0.0))
        zt = _project(prob, z[a] + d, pa)
        dz = zt - z[a]
        pred = -(2.0 * np.einsum("ni,ni->n", g[a], dz) + np.einsum("ni,nij,nj->n", dz, H[a], dz))
        ct, rt, gt, Ht = _evaluate(prob, pa, zt, max_sets)
        with np.errstate(invalid="ignore", divide="ignore"):
            rho = np.where(pred > 0, (cost[a] - ct) / pred, -1.0)
        acc = ok_chol & np.isfinite(ct) & (rho > 0) & (ct < cost[a])
        iterations[a] += 1
        # accepted: move, take the trial's Jacobian
        ia = a[acc]
        z[ia], cost[ia], raw[ia], g[ia], H[ia] = zt[acc], ct[acc], rt[acc], gt[acc], Ht[acc]
        if damping == "nielsen":
            mu[ia] *= np.maximum(1.0 / 3.0, 1.0 - (2.0 * rho[acc] - 1.0) ** 3)
            nu[ia] = 2.0
            ir = a[~acc]
            mu[ir] *= nu[ir]
            nu[ir] *= 2.0
        else:
            mu[ia] *= 0.5
            mu[a[~acc]] *= 2.0
        # convergence tests
        rel = _relative_change(prob, dz, zt, pa)
        rel = rel.max(axis=1) if p else np.zeros(len(a))
        free = _free_mask(z[a], g[a], prob.zlo[pa], prob.zhi[pa])
        gcos = _grad_cosine(g[a], H[a], cost[a], free)
        zero_step = ~np.any(free, axis=1)
        conv_x = acc & (rel < xtol)
        conv_g = (gcos <= gtol) | (cost[a] == 0)
        stalled = ~acc & (mu[a] > 1e16)
        capped = iterations[a] >= max_iter
        r = reason[a]
        done = np.zeros(len(a), dtype=bool)
        for mask, why, good in (
            (conv_x, "xtol", True),
            (conv_g, "gtol", True),
            (zero_step, "bound", True),
            (stalled, "stalled", None),
            (capped, "max_iterations", False),
        ):
            new = mask & ~done
            r[new] = why
            ok = (gcos[new] <= 1e-4) if good is None else np.full(new.sum(), good)
            converged[a[new]] = ok
            done |= new
        reason[a] = r
        active = a[~done]
    return LMState(z, cost, raw, g, H, iterations, reason, converged)
