"""Independent NumPy/SciPy reference of engine networks (:mod:`tawarp.model.network`):
segment transfer matrices at complex omega, the network's boundary determinant, complex
eigenfrequencies, onset in the hot temperature with the mode followed continuously, and
the power flows along the network.

Written from the equations (Rott's acoustics as in :mod:`tawarp.reference`, Swift,
*Thermoacoustics: A Unifying Perspective*, ASA 2002, Chs. 4-7); it shares no code with the
kernels. float64 / complex128 throughout; accuracy first.

Conventions: exp(-i omega t) (a mode grows when Im omega > 0); on each branch the state is
``(p, U)``, pressure [Pa] and volume flow [m^3/s] positive from the branch's ``from`` node to
its ``to`` node; ``(p, U)(end) = M (p, U)(start)``.

* **Segments**: ``dp/dx = a12 U``, ``dU/dx = a21 p + a22 U``
  (:func:`tawarp.reference.rott_coefficients`), closed form where the temperature and the
  section are uniform, DOP853 on the complex 2x2 fundamental matrix otherwise. Ducts are
  one circular pore of the local radius. A compliance of volume V (mass conservation,
  adiabatic core): ``U_out = U_in + i omega V (1 + (gamma - 1) f_k) p / (gamma p_m)``,
  f_k = (1 + i) delta_k A_surface / (2 V) (boundary layer on its inner surface); an
  inertance of length l and section S: ``p_out = p_in + a12 l U`` (a12 of a circular tube).
* **Ends**: ``p = Z U`` with U flowing out of the network. Closed: U = 0. Open: the radiation
  impedance of a pipe end of radius a at low ka, ``Z = (rho c / S) ((ka)^2/4 - 0.6133 i ka)``
  unflanged (Levine & Schwinger, Phys. Rev. 73, 383 (1948)) or ``((ka)^2/2 - 0.8216 i ka)``
  flanged (Rayleigh's baffled piston; Kinsler et al., *Fundamentals of Acoustics*),
  written for exp(-i omega t) (a mass end correction is -i omega M). Impedance:
  the table of :func:`tawarp.model.resonator.read_impedance_csv`, linear in frequency. Load:
  ``Z = R + i / (omega C)``, ``C = V / (gamma p_m)`` (a resistance into a closed volume).
* **Junctions**: equal pressure on every branch end that meets there, the volume flows into
  the node sum to zero.

The unknowns are ``(p, Zs U)`` at every branch's start (Zs = rho c / S of the first
segment at T_cold, so that all entries are O(1)); every branch end gives one row (an end
its condition, a junction of d branch ends d - 1 pressure equalities and one flow
balance): a square matrix whose determinant, analytic in omega, vanishes at the network's
eigenfrequencies.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize as so
from scipy.integrate import solve_ivp

from ..reference import gas_properties, rott_coefficients, thermoviscous_function
from .network import Network, NetworkSegment

#: Low-ka radiation of a pipe end: (resistance coefficient of (ka)^2, end correction / a)
RADIATION = {"unflanged": (0.25, 0.6133), "flanged": (0.5, 0.8216)}


# ======================================================================================
# Segments
# ======================================================================================
def _pore(seg: NetworkSegment, area):
    """(phi, r, q, pore model) at section ``area`` [m^2]: a duct or inertance is one
    circular pore of its radius."""
    if seg.kind == "porous":
        return seg.porosity, seg.pore_radius, seg.tortuosity, seg.pore_model
    return 1.0, np.sqrt(area / math.pi), 1.0, "circular"


def _profile(seg: NetworkSegment, T0: float, T1: float):
    """x -> (T, dT/dx, S) along the segment (linear temperature, linear radius)."""
    L = seg.length
    r0, r1 = math.sqrt(seg.area / math.pi), math.sqrt(seg.area_end / math.pi)

    def at(x):
        s = x / L
        r = r0 + (r1 - r0) * s
        return T0 + (T1 - T0) * s, (T1 - T0) / L, math.pi * r * r

    return at


def _A(net: Network, seg: NetworkSegment, w, T, dTdx, S):
    phi, r, q, model = _pore(seg, S)
    return rott_coefficients(net.gas.name, net.gas.p_mean, w, T, dTdx, phi, S, r, q, model)


def _compliance_admittance(net: Network, seg: NetworkSegment, w, T: float):
    """i omega V (1 + (gamma - 1) f_k) / (gamma p_m) [m^3/(Pa s)]."""
    g = gas_properties(net.gas.name, T, net.gas.p_mean)
    fk = 0.0
    if seg.surface_area > 0:
        d_k = np.sqrt(2.0 * g.k / (g.rho * g.cp * w))
        fk = (1.0 + 1.0j) * d_k * seg.surface_area / (2.0 * seg.volume)
    return 1j * w * seg.volume * (1.0 + (g.gamma - 1.0) * fk) / (g.gamma * net.gas.p_mean)


def segment_matrix(net: Network, seg: NetworkSegment, omega: complex, T_hot: float, rtol: float = 1e-11) -> np.ndarray:
    """Transfer matrix (2, 2) of ``seg`` at complex ``omega`` [rad/s] with the hot
    temperature ``T_hot`` [K]: ``(p, U)(out) = M (p, U)(in)``."""
    w = complex(omega)
    T0, T1 = seg.temperatures(net.gas.T_cold, T_hot)
    if seg.kind == "compliance":
        return np.array([[1.0, 0.0], [_compliance_admittance(net, seg, w, T0), 1.0]], dtype=complex)
    if seg.kind == "inertance":
        a12, _, _ = _A(net, seg, w, T0, 0.0, seg.area)
        return np.array([[1.0, a12 * seg.length], [0.0, 1.0]], dtype=complex)
    if T0 == T1 and seg.area == seg.area_end:
        a12, a21, _ = _A(net, seg, w, T0, 0.0, seg.area)
        k = np.sqrt(-a12 * a21)
        k = -k if k.imag < 0 else k
        Zc = a12 / (1j * k)
        kL = k * seg.length
        return np.array([[np.cos(kL), 1j * Zc * np.sin(kL)], [1j * np.sin(kL) / Zc, np.cos(kL)]])
    return _ode_matrix(net, seg, w, T0, T1, rtol)


def _integrate(net: Network, seg: NetworkSegment, w: complex, T0: float, T1: float, y0, rtol: float, t_eval=None):
    """DOP853 on d(p, Zs U)/dx = A_s(x) (p, Zs U) along the segment, the state scaled by
    Zs = rho c / S at its start so that the entries are O(1) and one absolute tolerance fits
    all; ``y0`` (2, k) columns of start states. Returns (solution, Zs)."""
    prof = _profile(seg, T0, T1)
    g0 = gas_properties(net.gas.name, T0, net.gas.p_mean)
    Zs = float(g0.rho * g0.c) / seg.area
    k = y0.shape[1]

    def rhs(x, y):
        T, dT, S = prof(x)
        a12, a21, a22 = _A(net, seg, w, T, dT, S)
        A = np.array([[0.0, a12 / Zs], [a21 * Zs, a22]], dtype=complex)
        return (A @ y.reshape(2, k)).ravel()

    atol = rtol * 1e-2 * np.abs(y0).max()
    sol = solve_ivp(rhs, (0.0, seg.length), y0.ravel(), "DOP853", t_eval=t_eval, rtol=rtol, atol=atol)
    if not sol.success:
        raise RuntimeError(f"segment {seg.name!r}, omega = {w}: {sol.message}")
    return sol, Zs


def _ode_matrix(net: Network, seg: NetworkSegment, w: complex, T0: float, T1: float, rtol: float) -> np.ndarray:
    """dM/dx = A(x) M, M(0) = I (:func:`_integrate` on the identity's two columns)."""
    sol, Zs = _integrate(net, seg, w, T0, T1, np.eye(2, dtype=complex), rtol)
    Ms = sol.y[:, -1].reshape(2, 2)
    # back to (p, U): M = D^-1 Ms D with D = diag(1, Zs)
    return np.array([[Ms[0, 0], Ms[0, 1] * Zs], [Ms[1, 0] / Zs, Ms[1, 1]]])


def branch_matrix(net: Network, b: int, omega: complex, T_hot: float) -> np.ndarray:
    """Transfer matrix of branch ``b``: the product of its segments', first on the right."""
    M = np.eye(2, dtype=complex)
    for seg in net.branches[b].segments:
        M = segment_matrix(net, seg, omega, T_hot) @ M
    return M


# ======================================================================================
# Ends and the boundary determinant
# ======================================================================================
def end_segment(net: Network, b: int, side: str) -> NetworkSegment:
    """The segment with a cross-section nearest ``side`` ("start" or "end") of branch ``b``:
    what an end there sees (a compliance has no section)."""
    segs = net.branches[b].segments
    for seg in segs if side == "start" else segs[::-1]:
        if seg.kind != "compliance":
            return seg
    raise ValueError(f"{net.source}: branch {net.branches[b].name!r} has no segment with a cross-section")


def end_impedance(net: Network, name: str, omega: complex, area: float, T: float) -> complex:
    """Z = p / U [Pa s/m^3] of end ``name`` (U flowing out of the network) for a pipe of
    section ``area`` [m^2] with gas at ``T`` [K]; ``inf`` for a closed end."""
    e = net.ends[name]
    w = complex(omega)
    g = gas_properties(net.gas.name, T, net.gas.p_mean)
    if e.kind == "closed":
        return complex(math.inf)
    if e.kind == "open":
        res, corr = RADIATION[e.flange]
        ka = w / g.c * math.sqrt(area / math.pi)
        return complex(g.rho * g.c / area * (res * ka**2 - 1j * corr * ka))
    if e.kind == "load":
        return e.resistance + 1j * g.gamma * net.gas.p_mean / (w * e.volume)
    t = e.impedance
    if len(t) == 1:
        return complex(t[0, 1], t[0, 2])
    f = w / (2 * math.pi)
    j = int(np.clip(np.searchsorted(t[:, 0], f.real) - 1, 0, len(t) - 2))
    za, zb = complex(t[j, 1], t[j, 2]), complex(t[j + 1, 1], t[j + 1, 2])
    return za + (zb - za) * (f - t[j, 0]) / (t[j + 1, 0] - t[j, 0])


def reference_impedance(net: Network) -> float:
    """Zs = rho c / S [Pa s/m^3] of the first branch's first section, at T_cold."""
    area = end_segment(net, 0, "start").area
    g = gas_properties(net.gas.name, net.gas.T_cold, net.gas.p_mean)
    return float(g.rho * g.c) / area


def boundary_matrix(net: Network, omega: complex, T_hot: float | None = None, mats=None) -> np.ndarray:
    """The (2B, 2B) matrix of the end and junction conditions acting on every branch's
    start state ``(p, Zs U)`` (module docstring); ``mats`` the branch matrices if known."""
    T_hot = net.T_hot if T_hot is None else T_hot
    B = len(net.branches)
    Zs = reference_impedance(net)
    mats = mats if mats is not None else [branch_matrix(net, b, omega, T_hot) for b in range(B)]

    def rows(b: int, side: str) -> tuple[np.ndarray, np.ndarray]:
        """(p row, Zs U row) of branch b at its start or end."""
        p, u = np.zeros(2 * B, complex), np.zeros(2 * B, complex)
        if side == "start":
            p[2 * b], u[2 * b + 1] = 1.0, 1.0
        else:
            M = mats[b]
            p[2 * b : 2 * b + 2] = M[0, 0], M[0, 1] / Zs
            u[2 * b : 2 * b + 2] = Zs * M[1, 0], M[1, 1]
        return p, u

    out = []
    for node, inc in net.nodes().items():
        if node in net.ends:
            b, side = inc[0]
            p, u = rows(b, side)
            u_out = u if side == "end" else -u  # flow out of the network into the end
            seg = end_segment(net, b, side)
            T0, T1 = seg.temperatures(net.gas.T_cold, T_hot)
            area, T = (seg.area, T0) if side == "start" else (seg.area_end, T1)
            Z = end_impedance(net, node, omega, area, T)
            out.append(u_out if math.isinf(Z.real) else p - (Z / Zs) * u_out)
            continue
        ps, flow = [], np.zeros(2 * B, complex)
        for b, side in inc:
            p, u = rows(b, side)
            ps.append(p)
            flow += u if side == "end" else -u  # into the node
        out += [ps[0] - pk for pk in ps[1:]] + [flow]
    return np.array(out)


def determinant(net: Network, omega: complex, T_hot: float | None = None) -> complex:
    """det of :func:`boundary_matrix`: zero at an eigenfrequency, analytic in omega."""
    return complex(np.linalg.det(boundary_matrix(net, omega, T_hot)))


# ======================================================================================
# Eigenfrequencies, mode following, onset
# ======================================================================================
def muller(f, guess: complex, rtol: float = 1e-11, maxiter: int = 100, spread: float = 1e-3) -> complex:
    """A root of the analytic ``f`` near ``guess`` by Muller's method (parabola through the
    last three iterates; Muller, Math. Tables Aids Comput. 10, 208 (1956)), started
    from ``guess (1 -+ spread)`` and ``guess``. Raises RuntimeError unless the step falls
    below ``rtol |omega|`` within ``maxiter`` steps."""
    x = [complex(guess) * (1 - spread), complex(guess) * (1 + spread), complex(guess)]
    y = [f(v) for v in x]
    for _ in range(maxiter):
        if y[2] == 0:
            return x[2]
        q = (x[2] - x[1]) / (x[1] - x[0])
        A = q * y[2] - q * (1 + q) * y[1] + q * q * y[0]
        B = (2 * q + 1) * y[2] - (1 + q) ** 2 * y[1] + q * q * y[0]
        C = (1 + q) * y[2]
        disc = np.sqrt(B * B - 4 * A * C)
        den = B + disc if abs(B + disc) >= abs(B - disc) else B - disc
        if den == 0:
            raise RuntimeError(f"Muller's method stalled at omega = {x[2]}")
        step = -(x[2] - x[1]) * 2 * C / den
        x = [x[1], x[2], x[2] + step]
        y = [y[1], y[2], f(x[2])]
        if abs(step) < rtol * abs(x[2]):
            return x[2]
    raise RuntimeError(f"no root within {maxiter} Muller steps from omega = {guess}; last {x[2]}")


def eigenfrequency(net: Network, guess: complex, T_hot: float | None = None, rtol: float = 1e-11) -> complex:
    """The complex omega [rad/s] near ``guess`` where :func:`determinant` vanishes
    (:func:`muller`)."""
    return muller(lambda w: determinant(net, w, T_hot), guess, rtol)


def real_axis_modes(
    net: Network, f_min: float, f_max: float, n: int = 400, T_hot: float | None = None
) -> list[complex]:
    """Start values: the local minima of |det| on n real frequencies in [f_min, f_max] [Hz],
    each refined by :func:`eigenfrequency`; sorted by Re omega, duplicates dropped."""
    f = np.linspace(f_min, f_max, n)
    d = np.array([abs(determinant(net, 2 * math.pi * fk, T_hot)) for fk in f])
    out: list[complex] = []
    for k in np.flatnonzero((d[1:-1] < d[:-2]) & (d[1:-1] < d[2:])) + 1:
        try:
            w = eigenfrequency(net, 2 * math.pi * f[k], T_hot)
        except RuntimeError:
            continue
        if w.real > 0 and all(abs(w - o) > 1e-6 * abs(w) for o in out):
            out.append(w)
    return sorted(out, key=lambda w: w.real)


@dataclass
class ModeJump:
    """The followed root moved from ``omega_before`` at ``T_before`` to ``omega_after`` at
    ``T_after`` [K] by more than the jump tolerance although the step was refined to
    ``T_after - T_before``: another mode, or a mode that changes abruptly."""

    T_before: float
    T_after: float
    omega_before: complex
    omega_after: complex


@dataclass
class ModePath:
    """omega (n,) [rad/s] at the temperatures T (n,) [K] of a followed mode; ``jumps``."""

    T: np.ndarray
    omega: np.ndarray
    jumps: list = field(default_factory=list)


def follow(root_at, T_values, omega0: complex, jump_tol: float = 0.05, min_step: float | None = None) -> ModePath:
    """Follow a root of ``root_at(T, guess) -> omega`` along increasing ``T_values``
    starting from ``omega0`` at ``T_values[0]``. Each step is predicted linearly from the
    two previous points; where the converged root lies farther than ``jump_tol * |omega|``
    from the prediction, the step is halved (down to ``min_step``, default 1/64 of the
    grid step) and the jump is recorded (:class:`ModeJump`) if it persists; the path goes on
    from the new root."""
    T_values = np.asarray(T_values, dtype=float)
    min_step = min_step if min_step is not None else np.min(np.diff(T_values)) / 64 if len(T_values) > 1 else 1.0
    Ts, ws, jumps = [T_values[0]], [root_at(T_values[0], omega0)], []
    since_jump = [1]  # points on the path since the last jump: the predictor uses only those

    def predict(T):
        if since_jump[0] < 2:
            return ws[-1]
        return ws[-1] + (ws[-1] - ws[-2]) * (T - Ts[-1]) / (Ts[-1] - Ts[-2])

    out_T, out_w = [Ts[0]], [ws[0]]
    for T_target in T_values[1:]:
        while Ts[-1] < T_target:
            step = T_target - Ts[-1]
            while True:
                T = Ts[-1] + step
                pred = predict(T)
                w = root_at(T, pred)
                if abs(w - pred) <= jump_tol * abs(ws[-1]):
                    break
                if step / 2 < min_step:
                    jumps.append(ModeJump(Ts[-1], T, ws[-1], w))
                    since_jump[0] = 0
                    break
                step /= 2
            Ts.append(T)
            ws.append(w)
            since_jump[0] += 1
        out_T.append(Ts[-1])
        out_w.append(ws[-1])
    return ModePath(np.array(out_T), np.array(out_w), jumps)


@dataclass
class NetworkOnset:
    """Onset of a network in its hot temperature: ``T_onset`` [K] (NaN: Im omega does not
    cross 0 from below on the searched range), ``ratio`` T_onset / T_cold, ``omega`` at
    onset [rad/s] (real to the root tolerance), ``frequency`` [Hz]; ``path`` the followed
    mode (:class:`ModePath`), whose ``jumps`` list the discontinuities met."""

    T_onset: float
    ratio: float
    omega: complex
    path: ModePath

    @property
    def frequency(self) -> float:
        return self.omega.real / (2 * math.pi)


def onset(
    net: Network,
    guess: complex,
    T_max: float,
    n: int = 25,
    T_min: float | None = None,
    xtol: float = 1e-9,
    jump_tol: float = 0.05,
    det=None,
) -> NetworkOnset:
    """Onset temperature of the mode starting at ``guess`` [rad/s] (at ``T_min``, default
    T_cold): the mode is followed on ``n`` hot temperatures in [T_min, T_max] [K]
    (:func:`follow`); the first crossing of Im omega from < 0 to >= 0 is refined by Brent's
    method on T_hot, each evaluation a root started from the path's linear interpolation.
    ``det(omega, T_hot)``: the characteristic function (default :func:`determinant`; a
    peer's segment matrices go in here)."""
    T_min = net.gas.T_cold if T_min is None else T_min
    if not (math.isfinite(T_max) and T_max > T_min):
        raise ValueError(f"T_max [K] must be finite and above T_min = {T_min:g} K, got {T_max}")
    if n < 2:
        raise ValueError(f"n must be >= 2, got {n}")
    det = det if det is not None else (lambda w, T: determinant(net, w, T))

    def root_at(T, w):
        return muller(lambda v: det(v, T), w)

    path = follow(root_at, np.linspace(T_min, T_max, n), guess, jump_tol)
    im = path.omega.imag
    cross = np.flatnonzero((im[:-1] < 0) & (im[1:] >= 0))
    if not len(cross):
        return NetworkOnset(math.nan, math.nan, complex(math.nan, math.nan), path)
    k = cross[0]
    Ta, Tb, wa, wb = path.T[k], path.T[k + 1], path.omega[k], path.omega[k + 1]

    def growth(T):
        return root_at(T, wa + (wb - wa) * (T - Ta) / (Tb - Ta)).imag

    T_on = so.brentq(growth, Ta, Tb, xtol=xtol * Tb, rtol=4 * np.finfo(float).eps)
    w_on = root_at(T_on, wa + (wb - wa) * (T_on - Ta) / (Tb - Ta))
    return NetworkOnset(float(T_on), float(T_on / net.gas.T_cold), w_on, path)


def onset_newton(
    net: Network, omega: float, T_hot: float, det=None, rtol: float = 1e-10, max_iter: int = 30, T_range=None
) -> tuple[float, float]:
    """Onset ``(omega [rad/s], T_hot [K])`` by Newton's method on det(omega, T_hot) = 0 with
    omega real (two real equations, two real unknowns), started from a nearby onset (a
    design's nominal one, for its perturbed draws), omega first moved to the real part of
    the design's own root at that T_hot (:func:`muller`): the omega-derivative is complex (det is
    analytic), the T-derivative a forward difference. Raises RuntimeError unless the steps
    fall below ``rtol`` relative within ``max_iter``, or where an iterate leaves ``T_range``
    [K] (default T_cold to 10 T_cold) or moves half of omega away (another mode)."""
    det = det if det is not None else (lambda w, T: determinant(net, w, T))
    T_lo, T_hi = T_range if T_range is not None else (net.gas.T_cold, 10 * net.gas.T_cold)
    T = float(T_hot)
    try:  # this design's own mode at T_hot first: its real part starts Newton
        w = muller(lambda v: det(v, T), complex(omega), rtol=1e-10).real
    except RuntimeError:
        w = float(omega)
    for _ in range(max_iter):
        F = det(w, T)
        hw, hT = 1e-7 * w, 1e-7 * T
        dw = (det(w + hw, T) - F) / hw
        dT = (det(w, T + hT) - F) / hT
        J = np.array([[dw.real, dT.real], [dw.imag, dT.imag]])
        step = np.linalg.solve(J, [-F.real, -F.imag])
        # damped: never more than a tenth of omega or of T_hot per step
        scale = min(1.0, 0.1 * w / max(abs(step[0]), 1e-300), 0.1 * T / max(abs(step[1]), 1e-300))
        w, T = w + scale * step[0], T + scale * step[1]
        if not (T_lo <= T <= T_hi) or abs(w - omega) > 0.5 * omega:
            break
        if abs(step[0]) < rtol * w and abs(step[1]) < rtol * T:
            return w, T
    raise RuntimeError(f"{net.source}: Newton's onset did not converge from omega = {omega}, T_hot = {T_hot}")


# ======================================================================================
# Mode shape and power flows
# ======================================================================================
def mode_start_states(net: Network, omega: complex, T_hot: float | None = None, node: str | None = None) -> np.ndarray:
    """(B, 2) complex ``(p, U)`` at every branch's start for the mode at ``omega`` (the null
    vector of :func:`boundary_matrix`, by SVD), scaled to p = 1 Pa (phase 0) at ``node``
    (default: the first branch's start)."""
    T_hot = net.T_hot if T_hot is None else T_hot
    Zs = reference_impedance(net)
    _, _, vh = np.linalg.svd(boundary_matrix(net, omega, T_hot))
    x = vh[-1].conj().reshape(-1, 2)
    x[:, 1] /= Zs
    if node is None:
        return x / x[0, 0]
    b, side = net.nodes()[node][0]
    p = x[b, 0] if side == "start" else (branch_matrix(net, b, omega, T_hot) @ x[b])[0]
    return x / p


def segment_entry(net: Network, name: str, omega: complex, T_hot: float, starts: np.ndarray) -> np.ndarray:
    """(p, U) entering segment ``name`` given the branches' start states ``starts``."""
    b, s = net.segment(name)
    state = starts[b].copy()
    for seg in net.branches[b].segments[:s]:
        state = segment_matrix(net, seg, omega, T_hot) @ state
    return state


@dataclass
class BranchProfile:
    """Along one branch, at positions ``x`` [m] from its start: ``p``, ``U`` complex [Pa],
    [m^3/s]; ``T`` [K]; ``Edot`` acoustic power 1/2 Re(p conj U) [W]; ``Htot`` total power
    [W] (Swift 2002, Ch. 7: the total power of a pore with an ideal solid); ``segment`` the segment name at each point.
    A lumped segment shows as two points at the same x."""

    branch: str
    x: np.ndarray
    p: np.ndarray
    U: np.ndarray
    T: np.ndarray
    Edot: np.ndarray
    Htot: np.ndarray
    segment: list


def total_power(net: Network, seg: NetworkSegment, w: float, p, U, T, dTdx, S):
    """Htot [W] at points of ``seg`` (Swift 2002, Ch. 7, with T beta = 1 and an ideal
    solid, eps_s = 0, written for exp(-i omega t)): ``1/2 Re[p U* (1 - (f_k - f_nu*) /
    ((1 + Pr)(1 - f_nu*)))] - rho cp |U|^2 / (2 A w (1 - Pr) |1 - f_nu|^2) Im[f_nu* +
    (f_k - f_nu*) / (1 + Pr)] dT/dx - (A k + A_solid k_solid) dT/dx``, A = phi S the gas area.
    A lumped segment carries Edot."""
    if seg.lumped:
        return 0.5 * np.real(p * np.conj(U))
    phi, r, q, model = _pore(seg, S)
    g = gas_properties(net.gas.name, T, net.gas.p_mean)
    d_nu = np.sqrt(2.0 * g.mu / (g.rho * w))
    d_k = np.sqrt(2.0 * g.k / (g.rho * g.cp * w))
    f_nu, _ = thermoviscous_function(model, r, d_nu)
    f_k, _ = thermoviscous_function(model, r, d_k)
    A = phi * S
    s = g.Pr
    fn_c = np.conj(f_nu)
    h_pu = 0.5 * np.real(p * np.conj(U) * (1.0 - (f_k - fn_c) / ((1.0 + s) * (1.0 - fn_c))))
    h_uu = -(
        g.rho
        * g.cp
        * np.abs(U) ** 2
        / (2 * A * w * (1 - s) * np.abs(1 - f_nu) ** 2)
        * np.imag(fn_c + (f_k - fn_c) / (1 + s))
    )
    return h_pu + h_uu * dTdx - (A * g.k + (1 - phi) * S * seg.solid_conductivity) * dTdx


def profiles(
    net: Network,
    omega: complex,
    T_hot: float | None = None,
    amplitude: float = 1.0,
    points: int = 41,
    node: str | None = None,
) -> list[BranchProfile]:
    """p, U, T, Edot and Htot along every branch for the mode at ``omega`` [rad/s], scaled so
    that |p| = ``amplitude`` [Pa] at ``node`` (default the first branch's start;
    :func:`mode_start_states`).
    Linear theory: the powers are exact second-order quantities at a real omega (the onset);
    at a complex root they are evaluated with Re omega. ``points`` per distributed segment."""
    if not (math.isfinite(amplitude) and amplitude > 0):
        raise ValueError(f"amplitude [Pa] must be finite and > 0, got {amplitude}")
    T_hot = net.T_hot if T_hot is None else T_hot
    starts = mode_start_states(net, omega, T_hot, node) * amplitude
    w = complex(omega)
    out = []
    for b, br in enumerate(net.branches):
        state = starts[b].copy()
        xs, ps, us, Ts, Hs, names = [], [], [], [], [], []
        x0 = 0.0
        for seg in br.segments:
            T0, T1 = seg.temperatures(net.gas.T_cold, T_hot)
            if seg.lumped:
                new = segment_matrix(net, seg, w, T_hot) @ state
                pts = [(x0, state, T0), (x0 + seg.extent, new, T0)]
                for x, st, T in pts:
                    xs.append(x)
                    ps.append(st[0])
                    us.append(st[1])
                    Ts.append(T)
                    Hs.append(float(total_power(net, seg, w.real, st[0], st[1], T, 0.0, math.nan)))
                    names.append(seg.name)
                state = new
            else:
                xk = np.linspace(0.0, seg.length, points)
                prof = _profile(seg, T0, T1)
                st = _states(net, seg, w, T_hot, state, xk)
                T, dT, S = (np.array(v) for v in zip(*(prof(x) for x in xk), strict=True))
                H = total_power(net, seg, w.real, st[:, 0], st[:, 1], T, dT, S)
                xs += list(x0 + xk)
                ps += list(st[:, 0])
                us += list(st[:, 1])
                Ts += list(T)
                Hs += list(H)
                names += [seg.name] * points
                state = st[-1]
            x0 += seg.extent
        p, U = np.array(ps), np.array(us)
        out.append(
            BranchProfile(br.name, np.array(xs), p, U, np.array(Ts), 0.5 * np.real(p * np.conj(U)), np.array(Hs), names)
        )
    return out


def _states(net: Network, seg: NetworkSegment, w: complex, T_hot: float, state: np.ndarray, xk: np.ndarray, rtol=1e-11):
    """(len(xk), 2) states ``(p, U)`` at positions ``xk`` [m] of a distributed segment entered
    with ``state``: closed form where uniform, DOP853 with output at ``xk`` otherwise."""
    T0, T1 = seg.temperatures(net.gas.T_cold, T_hot)
    if T0 == T1 and seg.area == seg.area_end:
        return np.array([segment_matrix(net, dataclasses.replace(seg, length=x), w, T_hot) @ state for x in xk])
    g0 = gas_properties(net.gas.name, T0, net.gas.p_mean)
    y0 = np.array([[state[0]], [float(g0.rho * g0.c) / seg.area * state[1]]], dtype=complex)
    sol, Zs = _integrate(net, seg, w, T0, T1, y0, rtol, t_eval=xk)
    return np.stack([sol.y[0], sol.y[1] / Zs], axis=1)


@dataclass
class PowerBudget:
    """Acoustic power budget of one segment [W] (Swift 2002, Ch. 5: dissipation and source terms): ``viscous`` =
    -int r_nu |U|^2 / 2 dx, ``thermal`` = -int |p|^2 / (2 r_k) dx (both <= 0), ``production``
    = int Re(g p* U) / 2 dx (the thermoacoustic source, zero without a temperature gradient);
    ``total`` their sum, Edot(out) - Edot(in)."""

    viscous: float
    thermal: float
    production: float

    @property
    def total(self) -> float:
        return self.viscous + self.thermal + self.production


def power_budget(
    net: Network, seg: NetworkSegment, omega: float, T_hot: float, p_in: complex, U_in: complex, points: int = 801
) -> PowerBudget:
    """:class:`PowerBudget` of the distributed segment ``seg`` entered by ``(p_in, U_in)`` at
    real ``omega`` [rad/s]: with ``dp/dx = a12 U`` and ``dU/dx = a21 p + a22 U``,
    d(1/2 Re p U*)/dx = 1/2 [Re(a12) |U|^2 + Re(a21) |p|^2 + Re(a22 p* U)], the three terms
    being the viscous loss, the thermal-relaxation loss and the production (Simpson's rule
    on ``points`` points)."""
    from scipy.integrate import simpson

    T0, T1 = seg.temperatures(net.gas.T_cold, T_hot)
    xk = np.linspace(0.0, seg.length, points)
    st = _states(net, seg, complex(omega), T_hot, np.array([p_in, U_in]), xk)
    T, dT, S = (np.array(v) for v in zip(*(_profile(seg, T0, T1)(x) for x in xk), strict=True))
    a12, a21, a22 = _A(net, seg, float(omega), T, dT, S)
    p, U = st[:, 0], st[:, 1]
    terms = (np.real(a12) * np.abs(U) ** 2, np.real(a21) * np.abs(p) ** 2, np.real(a22 * np.conj(p) * U))
    return PowerBudget(*(0.5 * float(simpson(t, x=xk)) for t in terms))
