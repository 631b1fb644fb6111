"""Porous layer with an elastic frame: the Biot-Allard model at normal incidence.

Vectorised NumPy (complex128), batched over parameter sets and frequencies: every
function takes the frequencies ``freq`` (1-D, [Hz], > 0) and the material parameters as
keyword arrays that broadcast against each other to a batch shape ``B``; results have
shape ``B + (m,)`` (``B + (m, 2, 2)`` for a transfer matrix). A loop calls them with a
dict of (n,) arrays: ``surface_impedance(freq, **values)``.

Parameters (:data:`BIOT_PARAMETERS`, SI units; names as in
:func:`tawarp.measure.files.atalla_panneton_samples` where both have them):

=============  =========  =====================================================================
name           unit       meaning
=============  =========  =====================================================================
phi            -          porosity, 0 < phi <= 1
sigma          N s/m^4    static air-flow resistivity (:func:`flow_resistivity` from a pore radius)
alpha_inf      -          tortuosity (high-frequency limit of the dynamic tortuosity), >= 1
Lambda         m          viscous characteristic length
Lambda_prime   m          thermal characteristic length
E              Pa         frame Young's modulus in vacuo (real part)
eta            -          frame loss factor: the modulus is ``E (1 - i eta)``, >= 0
nu             -          frame Poisson ratio, -1 < nu < 0.5
rho_1          kg/m^3     frame bulk density (frame mass per volume of *layer*, Allard's rho_1)
thickness      m          layer thickness d
T, P0          K, Pa      air temperature and static pressure (default 293.15 K, 101325 Pa)
=============  =========  =====================================================================

Convention. Time dependence ``exp(-i w t)`` (docs/physics.md). Allard & Atalla (*Propagation
of Sound in Porous Media*, 2nd ed., 2009) write ``exp(+j w t)``; for real ``w`` every
complex quantity here is the complex conjugate of theirs, i.e. their formulas with
``j -> -i``: the frame modulus ``E (1 + j eta)`` becomes ``E (1 - i eta)``, the JCA
dynamic tortuosity ``alpha = alpha_inf (1 + sigma phi / (j w rho0 alpha_inf) G)`` becomes
``alpha_inf (1 + i sigma phi / (w rho0 alpha_inf) G)``, and a rigid-backed equivalent
fluid layer's ``Z = -j Zc cot(k d)`` becomes ``Z = +i Zc cot(k d)`` (stiffness-like at low
frequency: ``Im Z > 0``).

Physics (Allard & Atalla ch. 5-6):

* Fluid: JCA equivalent density ``rho_eq = rho0 alpha(w) / phi`` and bulk modulus
  ``K_eq = K_f(w) / phi`` (:func:`jca_fluid`).
* Biot densities ``rho22 = phi^2 rho_eq``, ``rho12 = phi rho0 - rho22``,
  ``rho11 = rho_1 - rho12`` (viscous coupling included); incompressible solid
  (``K_s >> K_b, K_f``): ``R = phi K_f``, ``Q = (1 - phi) K_f``,
  ``P = P_hat + Q^2/R`` with the in-vacuo frame P-wave modulus
  ``P_hat = K_b + 4N/3 = E (1 - i eta)(1 - nu)/((1 + nu)(1 - 2 nu))``.
* Two compressional waves ``delta_1, delta_2`` (Allard's labels: ``delta_1^2`` takes the
  minus sign of the discriminant) with fluid/frame displacement ratios ``mu_1, mu_2``,
  and the shear wave ``delta_3`` (``mu_3 = -rho12/rho22``), which normal incidence does
  not excite (:func:`biot_waves`).

Boundary-value problem, in closed form (the normal-incidence reduction of Allard &
Atalla's ch. 11 transfer-matrix method: its 4x4 system per frequency reduces, by the
rigid backing or by the layer's mirror symmetry, to 2x2 determinants written out below;
``tests/test_biot.py`` checks them against the 4x4 system solved frequency by
frequency). The layer occupies ``0 <= x <= d``; the air is at ``x < 0`` (front); the
field is a sum of the four waves ``+-delta_1, +-delta_2``. Wave i has the frame and
fluid displacements ``(u^s_i, u^f_i)`` (:attr:`BiotWaves.modes`), velocities
``-i w u`` and, travelling along ``+-x``, stresses ``+-i w^2 S_i`` with
``S_i = (rho11 u^s + rho12 u^f, rho12 u^s + rho22 u^f) / delta_i`` (from the equations
of motion: exact given the dispersion relation, and free of the cancellation in
``P u^s + Q u^f`` when the frame is soft). Interface with air (pressure p, normal
velocity v): ``sigma^s = -(1 - phi) p``, ``sigma^f = -phi p``,
``v = (1 - phi) v^s + phi v^f`` (continuity of pressure, of total normal stress and of
volume velocity). Per wave the interface sees the stress split
``g_i = phi S^s_i - (1 - phi) S^f_i`` (zero in air) and the volume displacement
``q_i = (1 - phi) u^s_i + phi u^f_i``; with ``N = S^s_1 S^f_2 - S^s_2 S^f_1``,
``a = g_2 q_1``, ``c = g_1 q_2`` and the decays ``e_i = exp(i delta_i d)``
(``Im delta >= 0``, ``|e_i| <= 1``: only decaying exponentials, so nothing overflows
in thick or soft layers; ``1 - e^2`` by ``expm1`` for thin ones):

* :func:`surface_impedance`: rigid backing with the frame bonded to it
  (``v^s = v^f = 0`` at ``x = d``: each wave is the standing wave
  ``exp(i delta x) - e exp(i delta (d - x))``), the split and ``p`` at ``x = 0`` give
  ``Zs = p / v = w (1 + e_1^2)(1 + e_2^2) N / ((1 + e_1^2)(1 - e_2^2) c - (1 - e_1^2)(1 + e_2^2) a)``,
  normalized by ``rho0 c0``.
* :func:`transfer_matrix`: the layer in a tube between two air spaces, a 2-port
  ``(p, U)(d) = T (p, U)(0)`` (``U = S v``, the tube area ``S``; the same front-to-back
  direction as :mod:`tawarp.model.layer`). The standing waves symmetric and
  antisymmetric about the mid-plane, each with a zero split at both faces, map ``(p, v)``
  at ``x = 0`` to ``(-p, v)`` and ``(p, -v)`` at ``x = d``; with
  ``D = a e_1 (1 - e_2^2) - c e_2 (1 - e_1^2)``, in ``(p, v)``:
  ``T11 = T22 = (a (1 - e_2^2)(1 + e_1^2) - c (1 - e_1^2)(1 + e_2^2)) / (2 D)``,
  ``T12 = w (1 - e_1^2)(1 - e_2^2) N / (2 D)``,
  ``T21 = ((a - c)^2 (1 - e_1^2)(1 - e_2^2) - 4 a c (e_1 - e_2)^2) / (2 w N D)``
  (``det T = 1`` identically). **Edge condition: the frame slides freely at
  the tube wall**, so the problem is exactly 1-D (Biot at normal incidence). A frame
  clamped or glued at its edge bends and is not 1-D: it is not modelled. With free edges
  the frame can move as a rigid body, so an infinitely stiff frame of finite mass is
  *not* the rigid-frame equivalent fluid in a 2-port (it is when also infinitely heavy);
  with a rigid backing the bonded frame cannot move and ``E -> inf`` gives the rigid
  model. ``E -> 0`` gives the limp-frame model in both geometries.

At normal incidence only ``P_hat`` enters: ``E`` and ``nu`` are not separately
identifiable from such data (fix ``nu`` when fitting).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .fields import field as field_spec
from .gas import GASES
from .layer import gas_transport

#: name -> (unit, meaning) of the material parameters of the Biot layer.
BIOT_PARAMETERS: dict[str, tuple[str, str]] = {
    "phi": ("-", "porosity"),
    "sigma": ("N s/m^4", "static air-flow resistivity"),
    "alpha_inf": ("-", "tortuosity"),
    "Lambda": ("m", "viscous characteristic length"),
    "Lambda_prime": ("m", "thermal characteristic length"),
    "E": ("Pa", "frame Young's modulus (real part; complex E (1 - i eta))"),
    "eta": ("-", "frame loss factor"),
    "nu": ("-", "frame Poisson ratio"),
    "rho_1": ("kg/m^3", "frame bulk density"),
    "thickness": ("m", "layer thickness"),
}
#: Parameters of the fluid (JCA) part alone.
JCA_PARAMETERS = ("phi", "sigma", "alpha_inf", "Lambda", "Lambda_prime")

#: Each parameter's physical range is that of its row in :mod:`tawarp.model.fields` (one
#: table): the JCA lengths and the pore radius are radii, ``alpha_inf = q^2`` has q's range
#: [1, inf); the others (the moduli, the resistivity, the tube area) are only positive
#: (:func:`_check`).
_FIELD_OF = {
    "phi": "porosity",
    "alpha_inf": "tortuosity",
    "Lambda": "pore_radius",
    "Lambda_prime": "pore_radius",
    "pore_radius": "pore_radius",
    "thickness": "length",
    "eta": "frame_loss_factor",
    "nu": "poisson_ratio",
    "rho_1": "frame_density",
    "T": "gas.T_cold",
    "P0": "gas.p_mean",
}


class JCAFluid(NamedTuple):
    """Johnson-Champoux-Allard equivalent fluid, shape ``B + (m,)`` (rho0, c0: the shape of T
    and P0 + ``(1,)``, broadcasting to it).

    ``rho_eq`` [kg/m^3] = rho0 alpha(w) / phi, ``K_eq`` [Pa] = K_f(w) / phi (exp(-iwt));
    ``rho0`` [kg/m^3], ``c0`` [m/s] of the air."""

    rho_eq: np.ndarray
    K_eq: np.ndarray
    rho0: np.ndarray
    c0: np.ndarray


class BiotWaves(NamedTuple):
    """Biot coefficients and waves at normal incidence, shape ``B + (m,)``.

    ``P, Q, R`` [Pa]; ``rho11, rho12, rho22`` [kg/m^3] (viscous coupling included);
    ``delta1, delta2`` [1/m] the compressional wavenumbers (``Im >= 0``: ``exp(i delta x)``
    decays along +x), ``mu1, mu2`` the fluid/frame displacement ratios of those waves
    (``inf`` where the frame does not move); ``delta3`` [1/m] the shear wavenumber and
    ``mu3 = -rho12/rho22`` (not excited at normal incidence); ``P_hat`` [Pa] the in-vacuo
    frame P-wave modulus; ``modes`` (..., 2 waves, 2) unit (frame, fluid) displacement
    vectors of waves 1 and 2 (finite where ``mu`` is not)."""

    P: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    rho11: np.ndarray
    rho12: np.ndarray
    rho22: np.ndarray
    delta1: np.ndarray
    delta2: np.ndarray
    mu1: np.ndarray
    mu2: np.ndarray
    delta3: np.ndarray
    mu3: np.ndarray
    P_hat: np.ndarray
    modes: np.ndarray


class _Waves(NamedTuple):
    """What the boundary-value problems need of the waves (:func:`_waves`): the
    coefficients, ``det = rho11 rho22 - rho12^2``, and per compressional wave its
    wavenumber and (u^s, u^f) displacement, not normalized (the closed forms are
    homogeneous in each wave's amplitude)."""

    P: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    rho11: np.ndarray
    rho12: np.ndarray
    rho22: np.ndarray
    P_hat: np.ndarray
    det: np.ndarray
    deltas: tuple
    modes: tuple


def _check(name: str, value) -> np.ndarray:
    """``value`` as a float array, or ValueError naming ``name`` and the first bad value."""
    a = np.asarray(value, dtype=float)
    f = field_spec(_FIELD_OF[name]) if name in _FIELD_OF else None
    ok = f.check_array(a) if f is not None else np.isfinite(a) & (a > 0)
    if not ok.all():
        bad = a.reshape(-1)[np.flatnonzero(~ok.reshape(-1))[0]]
        rng = f.range_text() if f is not None else "(0, inf)"
        raise ValueError(
            f"biot: parameter {name!r} = {bad!r} outside its physical range {rng} "
            f"({BIOT_PARAMETERS.get(name, ('', name))[1]})"
        )
    return a


def _frequencies(freq) -> np.ndarray:
    f = np.asarray(freq, dtype=float)
    if f.ndim != 1 or f.size == 0 or not np.all(np.isfinite(f) & (f > 0)):
        raise ValueError(f"biot: freq must be a non-empty 1-D array of frequencies > 0 Hz, got {f!r}")
    return f


def _batch(**params) -> dict[str, np.ndarray]:
    """Checked parameters, broadcastable to one batch shape, with a trailing axis for
    frequency. Each keeps its own shape: what depends on some parameters only (the fluid,
    the waves) is computed on their batch shape, not on the whole batch's."""
    arrays = {k: _check(k, v) for k, v in params.items()}
    np.broadcast_shapes(*(a.shape for a in arrays.values()))  # a clear error if they do not broadcast
    return {k: a[..., None] for k, a in arrays.items()}


def flow_resistivity(pore_radius, phi, alpha_inf, T=293.15, gas: str = "air") -> np.ndarray:
    """Flow resistivity [N s/m^4] of circular pores of radius ``pore_radius`` [m]:
    ``sigma = 8 mu alpha_inf / (phi r^2)`` (mu of ``gas`` at ``T`` [K]); the same relation
    as :func:`tawarp.model.layer.jca_equivalent` (``alpha_inf = q^2``)."""
    r = _check("pore_radius", pore_radius)
    phi, alpha_inf, T = _check("phi", phi), _check("alpha_inf", alpha_inf), _check("T", T)
    mu = gas_transport(gas, T)[0].reshape(np.shape(T))
    return 8.0 * mu * alpha_inf / (phi * r * r)


def _jca(w, b, gas) -> JCAFluid:
    g = GASES[gas]
    mu, k = gas_transport(gas, b["T"].reshape(-1))
    mu, k = mu.reshape(b["T"].shape), k.reshape(b["T"].shape)
    rho0 = b["P0"] / (g.R_gas * b["T"])
    c0 = np.sqrt(g.gamma * g.R_gas * b["T"])
    Pr = mu * g.cp / k
    phi, sigma, a_inf = b["phi"], b["sigma"], b["alpha_inf"]
    L, Lp = b["Lambda"], b["Lambda_prime"]
    # Allard & Atalla Eqs. 5.50 and 5.52 with j -> -i (principal square roots: the
    # conjugate of theirs, since the roots commute with conjugation off the negative axis)
    G = np.sqrt(1.0 - 4j * a_inf**2 * mu * rho0 * w / (sigma**2 * L**2 * phi**2))
    alpha = a_inf * (1.0 + 1j * sigma * phi / (w * rho0 * a_inf) * G)
    Gp = np.sqrt(1.0 - 1j * rho0 * w * Pr * Lp**2 / (16.0 * mu))
    K_f = g.gamma * b["P0"] / (g.gamma - (g.gamma - 1.0) / (1.0 + 8j * mu / (Lp**2 * Pr * w * rho0) * Gp))
    return JCAFluid(rho0 * alpha / phi, K_f / phi, rho0, c0)


def jca_fluid(
    freq, *, phi, sigma, alpha_inf, Lambda, Lambda_prime, T=293.15, P0=101325.0, gas: str = "air"
) -> JCAFluid:
    """JCA equivalent fluid of a rigid frame (exp(-iwt)); see :class:`JCAFluid`."""
    f = _frequencies(freq)
    b = _batch(phi=phi, sigma=sigma, alpha_inf=alpha_inf, Lambda=Lambda, Lambda_prime=Lambda_prime, T=T, P0=P0)
    return _jca(2 * np.pi * f, b, gas)


def rigid_surface_impedance(
    freq, *, thickness, phi, sigma, alpha_inf, Lambda, Lambda_prime, T=293.15, P0=101325.0, gas: str = "air"
) -> np.ndarray:
    """``Zs / (rho0 c0)`` of a rigid-backed JCA layer with a rigid frame:
    ``i Zc cot(k d)`` with ``k = w sqrt(rho_eq/K_eq)``, ``Zc = sqrt(rho_eq K_eq)`` (exp(-iwt))."""
    fl = jca_fluid(
        freq, phi=phi, sigma=sigma, alpha_inf=alpha_inf, Lambda=Lambda, Lambda_prime=Lambda_prime, T=T, P0=P0, gas=gas
    )
    d = np.asarray(_check("thickness", thickness))[..., None]
    k = 2 * np.pi * _frequencies(freq) * np.sqrt(fl.rho_eq / fl.K_eq)
    Zc = np.sqrt(fl.rho_eq * fl.K_eq)
    return 1j * Zc / np.tan(k * d) / (fl.rho0 * fl.c0)


def _waves(w, b, fl: JCAFluid) -> _Waves:
    """The coefficients and the compressional waves (:class:`_Waves`; :func:`biot_waves`
    makes the public record)."""
    phi = b["phi"]
    rho22 = phi * phi * fl.rho_eq
    rho12 = phi * fl.rho0 - rho22
    rho11 = b["rho_1"] - rho12
    R = phi * phi * fl.K_eq
    Q = (1.0 - phi) * phi * fl.K_eq
    nu = b["nu"]
    P_hat = b["E"] * (1.0 - 1j * b["eta"]) * ((1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu)))
    P = P_hat + (1.0 - phi) ** 2 * fl.K_eq  # P_hat + Q^2/R
    # dispersion (P R - Q^2) d^4 - w^2 B d^2 + w^4 C = 0, written without the cancellations
    # of its textbook form: P R - Q^2 = P_hat R, rho11 rho22 - rho12^2 = rho_1 rho22 - phi rho0 rho12
    A = P_hat * R
    beta = (1.0 - phi) / phi  # Q / R
    Bc = P_hat * rho22 + R * (beta * beta * rho22 + rho11 - 2.0 * beta * rho12)
    C = b["rho_1"] * rho22 - phi * fl.rho0 * rho12
    s = np.sqrt(Bc * Bc - 4.0 * A * C)
    plus = Bc.real * s.real + Bc.imag * s.imag >= 0  # |Bc + s| >= |Bc - s|
    big = (Bc + np.where(plus, s, -s)) / (2.0 * A)  # the root without cancellation
    small = C / (A * big)
    x1, x2 = np.where(plus, small, big), np.where(plus, big, small)  # x1 = (B - s)/(2A): Allard's delta_1^2
    deltas, modes = [], []
    for x in (x1, x2):
        delta = w * np.sqrt(x)
        deltas.append(np.where(delta.imag < 0, -delta, delta))
        # null vector (u^s, u^f) of [[P x - rho11, Q x - rho12], [Q x - rho12, R x - rho22]] (x = d^2/w^2)
        # from its larger row: accurate when the frame or the fluid barely moves
        a11, a12, a22 = P * x - rho11, Q * x - rho12, R * x - rho22
        use1 = np.abs(a11) >= np.abs(a22)
        modes.append((np.where(use1, -a12, a22), np.where(use1, a11, -a12)))
    return _Waves(P, Q, R, rho11, rho12, rho22, P_hat, C, tuple(deltas), tuple(modes))


def biot_waves(
    freq, *, phi, sigma, alpha_inf, Lambda, Lambda_prime, E, eta, nu, rho_1, T=293.15, P0=101325.0, gas: str = "air"
) -> BiotWaves:
    """Biot coefficients and the three waves (see :class:`BiotWaves`)."""
    f = _frequencies(freq)
    b = _batch(
        phi=phi,
        sigma=sigma,
        alpha_inf=alpha_inf,
        Lambda=Lambda,
        Lambda_prime=Lambda_prime,
        E=E,
        eta=eta,
        nu=nu,
        rho_1=rho_1,
        T=T,
        P0=P0,
    )
    w = 2 * np.pi * f
    fl = _jca(w, b, gas)
    wv = _waves(w, b, fl)
    modes = np.stack([np.stack(m, axis=-1) for m in wv.modes], axis=-2)
    modes = modes / np.linalg.norm(modes, axis=-1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        mu = [np.where(m[..., 0] != 0, m[..., 1] / m[..., 0], np.inf) for m in (modes[..., 0, :], modes[..., 1, :])]
    N = b["E"] * (1.0 - 1j * b["eta"]) / (2.0 * (1.0 + b["nu"]))
    delta3 = w * np.sqrt(wv.det / (N * wv.rho22))
    delta3 = np.where(delta3.imag < 0, -delta3, delta3)
    out = (wv.P, wv.Q, wv.R, wv.rho11, wv.rho12, wv.rho22, *wv.deltas, *mu, delta3, -wv.rho12 / wv.rho22, wv.P_hat)
    shape = np.broadcast_shapes(*(a.shape for a in b.values()))[:-1] + (f.size,)
    return BiotWaves(*(np.broadcast_to(a, shape) for a in out), np.broadcast_to(modes, shape + (2, 2)))


def _interface(w, b, fl: JCAFluid):
    """What the air interface sees of the two compressional waves (module doc): ``N``,
    ``a``, ``c`` times ``delta_1 delta_2`` (the closed forms are homogeneous in them),
    and ``(delta_1, delta_2)``, on the batch shape of the fluid and frame parameters (the
    thickness enters only through the decays). ``N = (rho11 rho22 - rho12^2)
    (u^s_1 u^f_2 - u^s_2 u^f_1) / (delta_1 delta_2)`` and ``g_i = ((phi rho_1 - rho12) u^s_i
    + (phi^2 rho0 - rho22) u^f_i) / delta_i`` are the module doc's, expanded."""
    wv = _waves(w, b, fl)
    phi = b["phi"]
    (us1, uf1), (us2, uf2) = wv.modes
    split_s, split_f = phi * b["rho_1"] - wv.rho12, phi * phi * fl.rho0 - wv.rho22
    g1, g2 = split_s * us1 + split_f * uf1, split_s * us2 + split_f * uf2  # times delta_i
    q1, q2 = (1.0 - phi) * us1 + phi * uf1, (1.0 - phi) * us2 + phi * uf2
    delta1, delta2 = wv.deltas
    return wv.det * (us1 * uf2 - us2 * uf1), g2 * q1 * delta1, g1 * q2 * delta2, wv.deltas


def _params(freq, **params):
    """Angular frequencies (m,) and the checked, broadcast parameters."""
    return 2 * np.pi * _frequencies(freq), _batch(**params)


def surface_impedance(
    freq,
    *,
    thickness,
    phi,
    sigma,
    alpha_inf,
    Lambda,
    Lambda_prime,
    E,
    eta,
    nu,
    rho_1,
    T=293.15,
    P0=101325.0,
    gas: str = "air",
) -> np.ndarray:
    """Normalized surface impedance ``Zs / (rho0 c0)`` (exp(-iwt)) of a rigid-backed Biot
    layer, frame bonded to the backing; shape ``B + (m,)``. Comparable directly with
    :attr:`tawarp.measure.files.ImpedanceData.Zs`."""
    w, b = _params(
        freq,
        thickness=thickness,
        phi=phi,
        sigma=sigma,
        alpha_inf=alpha_inf,
        Lambda=Lambda,
        Lambda_prime=Lambda_prime,
        E=E,
        eta=eta,
        nu=nu,
        rho_1=rho_1,
        T=T,
        P0=P0,
    )
    return _surface_impedance(w, b, _jca(w, b, gas))


def fluid_surface_impedance(freq, fluid: JCAFluid, *, thickness, phi, E, eta, nu, rho_1) -> np.ndarray:
    """:func:`surface_impedance` of a frame in any equivalent fluid ``fluid`` (its
    ``rho_eq``, ``K_eq`` of shape ``B + (m,)``, ``rho0``, ``c0`` broadcasting to it): the
    elastic frame on top of another rigid-frame model, e.g. the kernels' pore functions
    (:func:`tawarp.measure.impedance.ImpedanceKind.predict`)."""
    w, b = _params(freq, thickness=thickness, phi=phi, E=E, eta=eta, nu=nu, rho_1=rho_1)
    return _surface_impedance(w, b, fluid)


def _decays(i_delta_d) -> tuple[np.ndarray, np.ndarray]:
    """``(e, 1 - e^2)`` with ``e = exp(i delta d)`` (``Im delta >= 0``): ``1 - e^2`` by
    ``expm1`` where ``|delta d| < 1/4`` (a thin layer or a low frequency, where ``1 - e^2``
    would cancel), from ``e`` elsewhere (one transcendental pass instead of two)."""
    e = np.exp(i_delta_d)
    u = 1.0 - e * e
    thin = np.abs(i_delta_d) < 0.25
    if thin.any():
        u[thin] = -np.expm1(2.0 * i_delta_d[thin])
    return e, u


def _surface_impedance(w, b, fl: JCAFluid) -> np.ndarray:
    N, a, c, (delta1, delta2) = _interface(w, b, fl)
    i_d = 1j * b["thickness"]
    u1, u2 = _decays(i_d * delta1)[1], _decays(i_d * delta2)[1]  # 1 - e_i^2
    s1, s2 = 2.0 - u1, 2.0 - u2  # 1 + e_i^2
    return (w / (fl.rho0 * fl.c0)) * N * (s1 * s2) / ((s1 * u2) * c - (s2 * u1) * a)


def transfer_matrix(
    freq,
    *,
    thickness,
    phi,
    sigma,
    alpha_inf,
    Lambda,
    Lambda_prime,
    E,
    eta,
    nu,
    rho_1,
    area=1.0,
    T=293.15,
    P0=101325.0,
    gas: str = "air",
) -> np.ndarray:
    """2-port ``(p, U)(d) = T (p, U)(0)`` of a Biot layer in a tube of cross-section ``area``
    [m^2] (``U = area v`` [m^3/s]; the default 1 m^2 gives the specific (p, v) matrix),
    air on both faces, frame sliding freely at the wall (1-D); shape ``B + (m, 2, 2)``,
    exp(-iwt). Passive and reciprocal: ``det T = 1``."""
    w, b = _params(
        freq,
        thickness=thickness,
        phi=phi,
        sigma=sigma,
        alpha_inf=alpha_inf,
        Lambda=Lambda,
        Lambda_prime=Lambda_prime,
        E=E,
        eta=eta,
        nu=nu,
        rho_1=rho_1,
        area=area,
        T=T,
        P0=P0,
    )
    return _transfer_matrix(w, b, _jca(w, b, gas))


def fluid_transfer_matrix(freq, fluid: JCAFluid, *, thickness, phi, E, eta, nu, rho_1, area=1.0) -> np.ndarray:
    """:func:`transfer_matrix` of a frame in any equivalent fluid ``fluid`` (as
    :func:`fluid_surface_impedance`)."""
    w, b = _params(freq, thickness=thickness, phi=phi, E=E, eta=eta, nu=nu, rho_1=rho_1, area=area)
    return _transfer_matrix(w, b, fluid)


def _transfer_matrix(w, b, fl: JCAFluid) -> np.ndarray:
    N, a, c, (delta1, delta2) = _interface(w, b, fl)
    i_d = 1j * b["thickness"]
    (e1, u1), (e2, u2) = _decays(i_d * delta1), _decays(i_d * delta2)  # e_i, 1 - e_i^2
    # +-(e1 - e2) without the cancellation of a thin layer: the slower decay factored out
    slow = delta1.imag <= delta2.imag
    lead, other = np.where(slow, delta1, delta2), np.where(slow, delta2, delta1)
    e_diff = np.exp(i_d * lead) * np.expm1(i_d * (other - lead))
    D2 = 2.0 * (a * e1 * u2 - c * e2 * u1)
    area = b["area"]
    T11 = (a * u2 * (2.0 - u1) - c * u1 * (2.0 - u2)) / D2
    T12 = w * u1 * u2 * N / (D2 * area)
    T21 = ((a - c) ** 2 * (u1 * u2) - 4.0 * (a * c) * e_diff**2) * area / (w * N * D2)
    T = np.empty(np.broadcast_shapes(T11.shape, T12.shape, T21.shape) + (2, 2), dtype=complex)
    T[..., 0, 0] = T[..., 1, 1] = T11
    T[..., 0, 1], T[..., 1, 0] = T12, T21
    return T


#: Thickness [m] of the slice whose 2-port gives the layer's equivalent fluid: |k d| << 1
#: at the frequencies of use, so arcsin takes its principal branch.
FLUID_SLICE = 1e-4
#: Poisson ratio of the elastic frame (normal incidence sees only E (1 - nu)/((1 + nu)(1 - 2 nu))).
FRAME_POISSON_RATIO = 0.3


def equivalent_fluid(T: np.ndarray, thickness: float, omega: np.ndarray, area: float) -> tuple[np.ndarray, np.ndarray]:
    """(rho_eq, K_eq) [kg/m^3, Pa] of a uniform layer from its 2-port T (..., m, 2, 2) over
    ``thickness`` [m] (``(p, U)``, tube ``area`` [m^2]): with T = [[cos kd, i Zc sin kd],
    [i sin kd / Zc, cos kd]], the specific impedance ``z = Zc area = sqrt(Tpu/Tup) area``
    and ``k d = arcsin(-i Tup Zc)`` (principal branch: a thin slice), then
    ``rho_eq = k z / w`` and ``K_eq = w z / k`` (Darcy velocity U/area, exp(-iwt))."""
    Zc = np.sqrt(T[..., 0, 1] / T[..., 1, 0])
    Zc = np.where(Zc.real < 0, -Zc, Zc)
    k = np.arcsin(-1j * T[..., 1, 0] * Zc) / thickness
    z = Zc * area
    return k * z / omega, omega * z / k
