"""Paper-like synthetic measurements for the four materials of Guedra et al. (2015).

>>> from tawarp.measure.synthetic import make_paper_data
>>> data = make_paper_data("mesh", noise=0.005, seed=0)      # a TMatrixData
>>> data.heat_inputs, data.frequencies.size
(array([ 0., 10., 20., 40., 60., 80.]), 60)

The truth is the bundled core of the material (``load_core(material)``): paper Table 1
geometry (porosity, pore radius, tortuosity), heat-exchange coefficients of Sect. 5.2
(``h_s`` = 150 ceramic, 50 mesh, 30 NiCr foam, 8 RVC foam; ``h_h`` = 100, ``h_a`` = 0.2
W/(m^2 K)), the hot exchanger's length of each run. ``truth=`` overrides any value.

* Frequencies: 50-200 Hz for the ceramic, 30-500 Hz otherwise (``n_freqs`` = 60 points).
* Heat inputs: 0, 10, 20, 40, 60, 80 W (RVC foam: 0, 4.5, 9, 13.5, 18 W).
* Model: :func:`tawarp.model.forward.transfer_matrices` with ``cells`` = 48 Magnus cells per
  thermal segment, more than a fit uses (default 16), so fitting is not an inverse crime.
* Noise (``noise`` = relative size, default 0.5 %): on each dimensionless coefficient
  ``Y`` (Tpp, Tpu/Zc, Tup*Zc, Tuu) at each row, complex Gaussian with independent real
  and imaginary parts of standard deviation ``noise |Y| / sqrt(2)`` each, so that
  ``E|dY|^2 = (noise |Y|)^2``. The file carries these standard deviations (raw units) as
  ``sigma_*_re/_im`` columns unless ``write_sigma=False``.
* Bias (optional, systematic): a multiplicative complex factor per coefficient, the same
  on every row (as a calibration error of the rig): ``bias`` is four complex factors, or a
  float ``b`` giving ``1 + b exp(i phase_c)`` with fixed phases (0, pi/2, pi, 3 pi/2)
  for the four coefficients. The two-step procedure (Eqs. 22-23) divides such a bias out.

:func:`scattering_measurement` turns core T-matrices (from any model) into the
four-microphone scattering matrices of a sample and of the empty tube, with the
calibration errors that :func:`tawarp.measure.scattering.calibrate_empty_tube` removes.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..model.coefficients import denormalize, duct_impedance, normalize
from ..model.core import Core, load_core
from ..model.forward import ForwardSettings, transfer_matrices
from ..rng import generator
from .files import ScatteringData, TMatrixData, transfer_to_scattering

MATERIALS = ("ceramic", "mesh", "nicr_foam", "rvc_foam")
#: Paper Table 1 (value, uncertainty) in SI, and the h's of Sect. 5.2 used as the truth.
PAPER_TABLE1 = {
    "ceramic": {
        "stack.porosity": (0.90, 0.01),
        "stack.pore_radius": (0.47e-3, 0.05e-3),
        "stack.tortuosity": (1.0, None),
    },
    "mesh": {"stack.porosity": (0.68, 0.01), "stack.pore_radius": (40e-6, 4e-6), "stack.tortuosity": (1.06, 0.03)},
    "nicr_foam": {
        "stack.porosity": (0.92, 0.01),
        "stack.pore_radius": (0.31e-3, 0.04e-3),
        "stack.tortuosity": (1.30, 0.04),
    },
    "rvc_foam": {
        "stack.porosity": (0.97, 0.01),
        "stack.pore_radius": (0.17e-3, 0.02e-3),
        "stack.tortuosity": (1.13, 0.03),
    },
}
MATERIAL_NAMES = {
    "ceramic": "ceramic catalyst 600 CPSI",
    "mesh": "stainless-steel wire mesh",
    "nicr_foam": "NiCr foam",
    "rvc_foam": "RVC foam",
}
DEFAULT_HEAT = (0.0, 10.0, 20.0, 40.0, 60.0, 80.0)
RVC_HEAT = (0.0, 4.5, 9.0, 13.5, 18.0)
BIAS_PHASES = (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi)


def paper_frequencies(material: str, n_freqs: int = 60) -> np.ndarray:
    """Frequencies [Hz] of the paper's measurements: 50-200 Hz (ceramic), else 30-500 Hz."""
    lo, hi = (50.0, 200.0) if material == "ceramic" else (30.0, 500.0)
    return np.linspace(lo, hi, n_freqs)


def paper_heat_inputs(material: str) -> np.ndarray:
    """Heat inputs [W]: 0-80 W, the RVC foam up to 18 W (combustion risk)."""
    return np.array(RVC_HEAT if material == "rvc_foam" else DEFAULT_HEAT)


def bias_factors(bias) -> np.ndarray:
    """Four complex multiplicative factors from ``bias`` (None, a float, or 4 complex)."""
    if bias is None:
        return np.ones(4, dtype=complex)
    b = np.asarray(bias, dtype=complex)
    if b.ndim == 0:
        return 1.0 + b.real * np.exp(1j * np.array(BIAS_PHASES))
    if b.shape != (4,):
        raise ValueError(f"bias: expected a float or 4 complex factors, got shape {b.shape}")
    return b


def make_paper_data(
    material: str,
    noise: float = 0.005,
    bias=None,
    seed: int = 0,
    *,
    freqs=None,
    heat_inputs=None,
    n_freqs: int = 60,
    cells: int = 48,
    truth: dict | None = None,
    write_sigma: bool = True,
    device: str | None = None,
) -> TMatrixData:
    """Paper-like T-matrix measurements of ``material`` (module doc): a :class:`TMatrixData`
    with rows ordered by heat input then frequency, ``sigma`` (raw units) unless
    ``write_sigma=False``, and metadata naming the material, noise, bias, seed, cells and
    every true parameter value (``true.stack.porosity = 0.68``, ...)."""
    if material not in MATERIALS:
        raise KeyError(f"unknown material {material!r}; expected one of {MATERIALS}")
    if not (noise >= 0 and math.isfinite(noise)):
        raise ValueError(f"noise must be a finite number >= 0, got {noise}")
    rng = generator(seed, "make_paper_data")
    core = load_core(material)
    if truth:
        core = core.replace(**truth)
    f = paper_frequencies(material, n_freqs) if freqs is None else np.asarray(freqs, dtype=float)
    Q = paper_heat_inputs(material) if heat_inputs is None else np.asarray(heat_inputs, dtype=float)
    res = transfer_matrices(core, f, heat_input=Q, cells=cells, device=device)
    Y = res.dimensionless()  # (nQ, m, 4)
    Y = Y * bias_factors(bias)
    sd = noise * np.abs(Y) / math.sqrt(2.0)
    Yn = Y + sd * (rng.standard_normal(Y.shape) + 1j * rng.standard_normal(Y.shape))
    zc = duct_impedance(core)
    T = denormalize(Yn, zc).reshape(-1, 2, 2)
    sigma = None
    if write_sigma and noise > 0:
        s = np.abs(denormalize(sd.astype(complex), zc)).reshape(-1, 2, 2)
        sigma = np.stack([s, s], axis=-1)
    meta = {
        "generator": "tawarp.measure.synthetic.make_paper_data",
        "material": material,
        "noise": repr(noise),
        "noise_model": "complex Gaussian, std noise*|Y|/sqrt(2) per part of each dimensionless coefficient",
        "bias": "none" if bias is None else " ".join(repr(complex(x)) for x in bias_factors(bias)),
        "seed": str(seed),
        "cells": str(cells),
        "core": material,
    }
    for k in (
        "stack.porosity",
        "stack.pore_radius",
        "stack.tortuosity",
        "stack.solid_conductivity",
        "stack.h",
        "hot_hx.porosity",
        "hot_hx.pore_radius",
        "hot_hx.length",
        "hot_hx.h",
        "tbt.h",
    ):
        meta[f"true.{k}"] = repr(core.get(k))
    return TMatrixData(np.repeat(Q, f.size), np.tile(f, Q.size), T, sigma, meta, f"synthetic:{material}")


def true_values(data: TMatrixData) -> dict[str, float]:
    """The ``true.*`` metadata of a synthetic data set as {name: value}."""
    return {k[5:]: float(v) for k, v in data.metadata.items() if k.startswith("true.")}


def synthetic_tmatrix(
    core: Core,
    truth: dict | None = None,
    freqs=None,
    heat_inputs=(0.0, 40.0, 80.0),
    noise: float = 0.002,
    seed: int = 0,
    ambient_exchangers: dict | None = None,
    settings: ForwardSettings | None = None,
) -> TMatrixData:
    """Core T-matrices made by the forward model with parameters ``truth`` (any names,
    effects included) plus complex Gaussian noise of standard deviation ``noise`` times
    the rms of the dimensionless coefficients (per re/im part); sigma columns carry it.
    ``ambient_exchangers`` {label: value} of the library's ambient-exchanger effect
    (``ambient_hx.length``, ``.porosity``, ``.pore_radius``; {} its typical size): made with them."""
    from ..model.effects import ambient_exchanger_effect

    rng = generator(seed, "synthetic_tmatrix")
    freqs = np.linspace(50.0, 500.0, 12) if freqs is None else np.asarray(freqs, dtype=float)
    truth = dict(truth or {})
    model = core
    if ambient_exchangers is not None:
        effect = ambient_exchanger_effect(core)
        model = effect.transform(core)
        truth.update({k: float(v) for k, v in effect.model_values({**effect.typical, **ambient_exchangers}).items()})
    nq = len(heat_inputs)
    settings = settings or ForwardSettings(device="cpu", cells=8)
    res = transfer_matrices(
        model, freqs, list(heat_inputs), params={k: np.full(nq, v) for k, v in truth.items()}, settings=settings
    )
    T = res.T.reshape(-1, 2, 2)
    Zc = duct_impedance(core)
    s = noise * np.sqrt(np.mean(np.abs(normalize(T, Zc)) ** 2))
    scale = np.array([[1.0, Zc], [1.0 / Zc, 1.0]])
    Tn = T + s * scale * (rng.standard_normal(T.shape) + 1j * rng.standard_normal(T.shape))
    sigma = np.broadcast_to(s * scale, T.shape).copy()
    meta = {"generator": "tawarp.measure.synthetic.synthetic_tmatrix", "noise": str(noise), "seed": str(seed)}
    return TMatrixData(np.repeat(heat_inputs, len(freqs)), np.tile(freqs, nq), Tn, sigma, meta, "<synthetic>")


def scattering_measurement(
    T,
    freqs,
    *,
    tube_radius: float,
    plane_upstream: float,
    plane_downstream: float,
    length: float,
    T_ambient: float = 293.15,
    p_ambient: float = 101325.0,
    gas: str = "air",
    gain=None,
    tube_wavenumber=None,
    tube_impedance=None,
    noise: float = 0.0,
    seed: int = 0,
    write_sigma: bool = True,
    heat_input: float = 0.0,
    source: str = "<synthetic>",
) -> tuple[ScatteringData, ScatteringData]:
    """Scattering matrices of a sample with core T-matrices ``T`` (m, 2, 2) [SI] at
    ``freqs`` (m,) [Hz], and of the empty tube, as a four-microphone rig would measure them.

    Planes: signed ``plane_upstream`` from face x1 and ``plane_downstream`` from face x6
    [m] (:class:`ScatteringData`); ``length`` [m] the sample's (x1 to x6), so the empty
    tube spans ``D = length + plane_downstream - plane_upstream``. The metadata's
    ``T_ambient`` [K], ``p_ambient`` [Pa], ``gas`` and ``tube_radius`` [m] are written as
    metadata. Calibration errors: ``gain`` (m,) or scalar complex gain of the downstream
    microphone pair (``S12 / g``, ``S21 g``; default 1); ``tube_wavenumber`` (m,) complex
    [1/m] and ``tube_impedance`` (m,) complex [Pa s/m^3] of the actual tube (default the
    metadata's lossless ``w / c0`` and ``rho0 c0 / S``). Noise:
    complex Gaussian of standard deviation ``noise / sqrt(2)`` per part on every entry
    of both matrices (independent streams from ``seed``), written as sigma columns unless
    ``write_sigma=False``. Returns ``(sample, empty)``.
    """
    rng = generator(seed, "scattering_measurement")
    f = np.asarray(freqs, dtype=float)
    meta = {"generator": "tawarp.measure.synthetic.scattering_measurement", "noise": repr(noise), "seed": str(seed)}
    base = ScatteringData(
        f,
        np.zeros((f.size, 2, 2)),
        plane_upstream,
        plane_downstream,
        tube_radius,
        T_ambient,
        p_ambient,
        gas,
        heat_input,
        None,
        None,
        meta,
        source,
    )
    k = base.k if tube_wavenumber is None else np.asarray(tube_wavenumber, dtype=complex)
    g = np.broadcast_to(np.asarray(1.0 if gain is None else gain, dtype=complex), f.shape)
    Zc = base.Zc if tube_impedance is None else np.asarray(tube_impedance, dtype=complex)
    S = transfer_to_scattering(T, k, Zc, -plane_upstream, plane_downstream)
    e = np.exp(1j * k * (length + plane_downstream - plane_upstream))
    SE = np.zeros_like(S)
    SE[:, 0, 1], SE[:, 1, 0] = e, e
    out = []
    for M, name in ((S, source), (SE, f"{source}:empty")):
        M = M.copy()
        M[:, 0, 1] /= g
        M[:, 1, 0] *= g
        M = M + noise / math.sqrt(2.0) * (rng.standard_normal(M.shape) + 1j * rng.standard_normal(M.shape))
        sigma = np.full(M.shape + (2,), noise / math.sqrt(2.0)) if write_sigma and noise > 0 else None
        out.append(dataclasses.replace(base, S=M, sigma=sigma, metadata=dict(meta), source=name))
    return out[0], out[1]
