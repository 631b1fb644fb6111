"""The package's one least-squares engine: batched Levenberg-Marquardt.

:func:`levenberg_marquardt` runs Q independent problems in lockstep on any
:class:`LMProblems` (scaled variables z, bounds, one ``evaluate`` per iteration that
returns the cost, ``g = J^T r`` and ``H = J^T J`` of every active problem). Problems that
converge leave the active set, so later evaluations (forward launches) only contain the
problems still iterating. Damping, stopping rule and reasons: :mod:`tawarp.fit.estimate`'s
module doc. Two implementations of :class:`LMProblems` exist: the T-matrix problems of
:class:`tawarp.fit.estimate.Problems` reduce residuals to (cost, g, H) on the device
(:mod:`tawarp.kernels.lm`); :class:`tawarp.fit.problems.KindProblems` does it on the host
for any measurement kind (:mod:`tawarp.measure`).

The iteration's arithmetic (damped Cholesky step, projection onto the bounds, acceptance,
damping, stopping tests) runs on the problems' device in the kernels of
:mod:`tawarp.kernels.lm_step`, one thread per problem: with 1e5 problems the NumPy
bookkeeping of (n, p, p) arrays cost the host more than the device's evaluations (issue
#11). The host launches, calls ``evaluate`` and compacts the active set from the done flags.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import warp as wp

from ..kernels import lm_step
from ..progress import progress_bar

#: names of the reason codes of :mod:`tawarp.kernels.lm_step` (code 0: still iterating)
REASONS = ("", "xtol", "gtol", "bound", "stalled", "max_iterations", "invalid")


@dataclass
class LMState:
    """Per problem: final z, cost, raw (unweighted misfit), g, H, iterations, reason, converged."""

    z: np.ndarray
    cost: np.ndarray
    raw: np.ndarray
    g: np.ndarray
    H: np.ndarray
    iterations: np.ndarray
    reason: np.ndarray
    converged: np.ndarray


class LMProblems(Protocol):
    """What :func:`levenberg_marquardt` needs of a batch of least-squares problems in scaled
    variables z (:class:`tawarp.fit.estimate.Problems`, :class:`tawarp.fit.problems.KindProblems`).

    ``zlo``, ``zhi`` (N, p): bounds of z per problem (+-inf for none); every z the LM tries
    is clipped onto them. ``device`` (optional, default the CPU): where the iteration runs.
    ``evaluate(pid, z, max_sets)``: ``(cost, raw, g, H)`` of problems ``pid`` (n,) at z
    (n, p) (NumPy), cost (n,) the weighted sum of squared residuals ``r^T r`` (inf where the
    model fails; a non-finite cost, g or H makes it so), raw (n,) its unweighted
    counterpart (passed through), ``g = J^T r`` (n, p), ``H = J^T J`` (n, p, p), J the
    Jacobian in z; NumPy arrays or Warp arrays on ``device``.
    ``change_rule()``: ``(kind (p,), scale (N, p), offset (N, p))``, how the size of a step
    dz that ended at z is measured against ``xtol`` (:mod:`tawarp.kernels.lm_step`:
    ``CHANGE_LINEAR`` ``s |dz| / |o + s z|``, ``CHANGE_LOG`` ``|expm1(dz)|``,
    ``CHANGE_ABSOLUTE`` ``|dz|``).
    """

    zlo: np.ndarray
    zhi: np.ndarray

    def evaluate(self, pid: np.ndarray, z: np.ndarray, max_sets: int = ...) -> tuple: ...

    def change_rule(self) -> tuple: ...


def _on_device(arrays, device, own=False):
    """The evaluation's arrays as float64 Warp arrays on ``device`` (NumPy ones copied there;
    ``own``: Warp ones too, for the state the kernels overwrite)."""
    return [
        (wp.clone(a) if own else a)
        if isinstance(a, wp.array)
        else wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=wp.float64, device=device)
        for a in arrays
    ]


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
    ``prob``: any :class:`LMProblems`."""
    if damping not in ("nielsen", "paper"):
        raise ValueError(f"damping = {damping!r}; expected 'nielsen' or 'paper'")
    Q, p = z0.shape
    if p == 0:
        raise ValueError("levenberg_marquardt: no free parameters")
    dev = wp.get_device(getattr(prob, "device", "cpu"))
    init, propose, update = lm_step.step_kernels(p)
    pid = np.asarray(pid)

    def put(a, dtype=wp.float64):
        return wp.array(np.ascontiguousarray(a), dtype=dtype, device=dev)

    kind, scale, offset = prob.change_rule()
    w_pid = put(pid.astype(np.int32), wp.int32)
    w_zlo, w_zhi = put(np.asarray(prob.zlo, dtype=float)), put(np.asarray(prob.zhi, dtype=float))
    w_kind, w_scale, w_offset = put(np.asarray(kind, dtype=np.int32), wp.int32), put(scale), put(offset)
    z = np.clip(np.array(z0, dtype=float), prob.zlo[pid], prob.zhi[pid])
    w_z = put(z)
    w_cost, w_raw, w_g, w_H = _on_device(prob.evaluate(pid, z, max_sets), dev, own=True)
    w_mu, w_nu = wp.empty(Q, dtype=wp.float64, device=dev), wp.empty(Q, dtype=wp.float64, device=dev)
    w_it = wp.zeros(Q, dtype=wp.int32, device=dev)
    w_reason, w_conv = wp.empty(Q, dtype=wp.int32, device=dev), wp.empty(Q, dtype=wp.int32, device=dev)
    w_done = wp.empty(Q, dtype=wp.int32, device=dev)
    wp.launch(
        init,
        dim=Q,
        device=dev,
        inputs=[
            w_pid,
            w_zlo,
            w_zhi,
            float(tau),
            float(gtol),
            w_z,
            w_cost,
            w_g,
            w_H,
            w_mu,
            w_nu,
            w_reason,
            w_conv,
            w_done,
        ],
    )
    active = np.flatnonzero(w_done.numpy() == 0)
    bar = progress_bar(Q, "fits", progress, unit="fit")
    bar.update(Q - active.size)
    damp = lm_step.DAMP_NIELSEN if damping == "nielsen" else lm_step.DAMP_PAPER
    while active.size:
        n = active.size
        w_act = put(active.astype(np.int32), wp.int32)
        w_zt, w_dz = wp.empty((n, p), dtype=wp.float64, device=dev), wp.empty((n, p), dtype=wp.float64, device=dev)
        w_pred, w_ok = wp.empty(n, dtype=wp.float64, device=dev), wp.empty(n, dtype=wp.int32, device=dev)
        wp.launch(
            propose,
            dim=n,
            device=dev,
            inputs=[w_act, w_pid, w_zlo, w_zhi, w_z, w_g, w_H, w_mu, w_zt, w_dz, w_pred, w_ok],
        )
        ct, rt, gt, Ht = _on_device(prob.evaluate(pid[active], w_zt.numpy(), max_sets), dev)
        done = wp.empty(n, dtype=wp.int32, device=dev)
        wp.launch(
            update,
            dim=n,
            device=dev,
            inputs=[
                w_act,
                w_pid,
                w_zlo,
                w_zhi,
                w_kind,
                w_scale,
                w_offset,
                w_zt,
                w_dz,
                w_pred,
                w_ok,
                ct,
                rt,
                gt,
                Ht,
                damp,
                float(xtol),
                float(gtol),
                int(max_iter),
                w_z,
                w_cost,
                w_raw,
                w_g,
                w_H,
                w_mu,
                w_nu,
                w_it,
                w_reason,
                w_conv,
                done,
            ],
        )
        finished = done.numpy() != 0
        active = active[~finished]
        bar.update(int(finished.sum()))
    bar.close()
    return LMState(
        w_z.numpy(),
        w_cost.numpy(),
        w_raw.numpy(),
        w_g.numpy(),
        w_H.numpy(),
        w_it.numpy().astype(int),
        np.array(REASONS, dtype=object)[w_reason.numpy()],
        w_conv.numpy() != 0,
    )
