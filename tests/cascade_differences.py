"""The tangent cascade's check shared by tests/test_tangents.py and tests/test_pore_geometries.py:
dT/dz of Engine.evaluate_tangents against central differences of the plain cascade at steps
2k and k (k = 1e-3 in z), Richardson-extrapolated.

z is each parameter's fit coordinate about the point ``v0``: ``v = v0 exp(z)`` for a
log-scaled parameter (:func:`tawarp.fit.estimate.is_log`), ``v = v0 + 0.05 z`` otherwise.
"""

import numpy as np

from tawarp.fit.estimate import is_log
from tawarp.model.forward import Engine, ForwardSettings

#: frequencies [Hz] of the check: below, near and above the cores' first resonances
FREQUENCIES = np.array([35.0, 160.0, 450.0])


def assert_tangents_match_differences(core, names, v0, heat_input, scales=None):
    """dT/dz at ``v0`` (of parameters ``names``) to 1e-8 of max |dT/dz| per parameter, plus
    1e-11 of max |T| for parameters of so small an effect that rounding over the
    differences' steps (eps |T| / step) shows; 1e-7 when the heat solve iterates to its
    1e-12 tolerance (step 1e-4). The cascade's own T at v0 matches the plain one to 1e-13.
    ``scales`` {name: s}: v = v0 + s z for a linear parameter whose effect turns on a scale
    below 0.05 (default 0.05)."""
    log = np.array([is_log(k) for k in names])
    unit = np.array([(scales or {}).get(k, 0.05) for k in names])
    P = len(names)
    eng = Engine(core, FREQUENCIES, names, ForwardSettings(cells=6, device="cpu", cpu_threads=1))

    def table(zs):
        return np.stack([np.r_[heat_input, np.where(log, v0 * np.exp(z), v0 + unit * z)] for z in zs], axis=1)

    step = eng.tangent_step
    tol = 1e-8 if not eng.nonlinear else 1e-7
    zs = [np.zeros(P)] + [s * step * e for e in np.eye(P) for s in (1, -1)]
    out, tangent = (a.numpy() for a in eng.evaluate_tangents(table(zs), np.full((1, P), step), P))
    k = 1e-3
    ref = [np.zeros(P)] + [s * c * k * e for e in np.eye(P) for c in (2, 1) for s in (1, -1)]
    T = eng.evaluate(table(ref))[0].numpy()
    np.testing.assert_allclose(out[0], T[0], rtol=0, atol=1e-13 * np.abs(T[0]).max())
    for a in range(P):
        d2 = (T[1 + 4 * a] - T[2 + 4 * a]) / (4 * k)
        d1 = (T[3 + 4 * a] - T[4 + 4 * a]) / (2 * k)
        want = (4 * d1 - d2) / 3
        err = np.abs(tangent[0, a] - want).max()
        assert err < tol * np.abs(want).max() + 1e-11 * np.abs(T[0]).max(), (names[a], err / np.abs(want).max())
