"""Synthetic impedance-tube signals: an independent model of the measurement, to check the
methods against a known specimen.

The tube is uniform with Kirchhoff's wide-tube wall losses; the specimen sits between
``x = 0`` and ``x = thickness``; each end of the tube, ``length_up`` upstream of the
specimen and ``length_down`` downstream of it, reflects waves with a reflection
coefficient and may inject a wave (the loudspeaker). The sound field is four plane-wave
amplitudes, ``p = A e^{-ikx} + B e^{ikx}`` upstream (``x`` from the upstream face) and
``p = C e^{-ikx'} + D e^{ikx'}`` downstream (``x'`` from the downstream face), fixed by one
linear system per frequency: each end's reflection and injection, and the specimen's
T-matrix joining the states on its faces. Nothing here solves a method's equations.

For the multi-termination method the core is driven by a volume-velocity source at its
upstream face (the impedance sensor) and closed by a termination impedance at its
downstream face (:func:`sensor_pressures`, :func:`sensor_signals`).

Time signals: a broadband random drive (complex Gaussian spectrum over a band), each
microphone's pressure spectrum times its gain error, inverse FFT, plus white Gaussian noise
at a given signal-to-noise ratio. Channel 0 is the drive (the reference), channels 1.. the
microphones. Internally ``exp(+i omega t)``, the convention of the DFT; the specimen is given
in tawarp's ``exp(-i omega t)`` and converted here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..rng import checked_seed, generator
from .spectra import Transfers, welch


@dataclass(frozen=True)
class Tube:
    """A uniform circular tube of gas (air at 20 C by default). radius [m], sound_speed [m/s],
    density [kg/m^3], viscosity [Pa s], gamma, prandtl."""

    radius: float = 0.025
    sound_speed: float = 343.2
    density: float = 1.204
    viscosity: float = 1.82e-5
    gamma: float = 1.4
    prandtl: float = 0.71

    @property
    def area(self) -> float:
        return np.pi * self.radius**2

    def _eps(self, f):
        # Kirchhoff: relative wall-loss correction (boundary-layer thickness over radius)
        nu = self.viscosity / self.density
        omega = 2 * np.pi * np.asarray(f, dtype=float)
        return np.sqrt(nu / (2 * omega)) / self.radius

    def wavenumber(self, f) -> np.ndarray:
        """Kirchhoff's wavenumber [1/m], exp(+i omega t): ``(w/c)(1 + (1 - i) eps (1 + (gamma-1)/sqrt(Pr)))``."""
        omega = 2 * np.pi * np.asarray(f, dtype=float)
        g = (self.gamma - 1) / np.sqrt(self.prandtl)
        return omega / self.sound_speed * (1 + (1 - 1j) * self._eps(f) * (1 + g))

    def impedance(self, f) -> np.ndarray:
        """Characteristic impedance for the volume velocity [Pa s/m^3], exp(+i omega t):
        ``(rho c / S)(1 + (1 - i) eps (1 - (gamma-1)/sqrt(Pr)))``."""
        g = (self.gamma - 1) / np.sqrt(self.prandtl)
        return self.density * self.sound_speed / self.area * (1 + (1 - 1j) * self._eps(f) * (1 - g))


@dataclass(frozen=True)
class Setup:
    """One measurement configuration. Lengths [m] from the specimen's faces to the tube ends;
    ``reflection_up``, ``reflection_down`` complex reflection coefficients of the ends
    (exp(+i omega t), outgoing over incoming wave at the end: 1 rigid, 0 anechoic);
    ``source`` 'up' or 'down': the end that injects the drive."""

    length_up: float
    length_down: float
    reflection_up: complex
    reflection_down: complex
    source: str = "up"


def porous_layer(f, thickness: float, flow_resistivity: float, tube: Tube) -> np.ndarray:
    """T-matrix (nf, 2, 2) of a rigid-frame porous layer (Delany & Bazley 1970 equivalent
    fluid) between its faces, tawarp's convention (exp(-i omega t), ``(p, U)``): reciprocal
    and symmetric. ``thickness`` [m], ``flow_resistivity`` [Pa s/m^2]."""
    f = np.asarray(f, dtype=float)
    rho_c = tube.density * tube.sound_speed
    x = tube.density * f / flow_resistivity
    # Delany & Bazley's fits, written for exp(+i omega t)
    zc = rho_c * (1 + 0.0571 * x**-0.754 - 0.087j * x**-0.732) / tube.area
    kc = 2 * np.pi * f / tube.sound_speed * (1 + 0.0978 * x**-0.700 - 0.189j * x**-0.595)
    c, s = np.cos(kc * thickness), np.sin(kc * thickness)
    t_plus = np.stack([np.stack([c, -1j * zc * s], -1), np.stack([-1j * s / zc, c], -1)], -2)
    return np.conj(t_plus)


def pressures(f, specimen, thickness: float, setup: Setup, tube: Tube, positions) -> np.ndarray:
    """(nf, n) complex pressures at microphone ``positions`` [m] (from the upstream face;
    none inside the specimen) per unit injected wave, exp(+i omega t)."""
    f = np.asarray(f, dtype=float)
    x = np.asarray(positions, dtype=float)
    if np.any((x > 0) & (x < thickness)):
        raise ValueError(f"microphone positions {x} fall inside the specimen (0, {thickness})")
    if setup.source not in ("up", "down"):
        raise ValueError(f"source = {setup.source!r}: expected 'up' or 'down'")
    k, z0 = tube.wavenumber(f), tube.impedance(f)
    t = np.conj(np.asarray(specimen, dtype=complex))  # exp(+i omega t)
    nf = f.size
    # unknowns (A, B, C, D): upstream waves at x = 0, downstream waves at the downstream face
    m = np.zeros((nf, 4, 4), dtype=complex)
    rhs = np.zeros((nf, 4), dtype=complex)
    eu, ed = np.exp(1j * k * setup.length_up), np.exp(1j * k * setup.length_down)
    # upstream end (x = -length_up): the wave leaving it (A) = R * arriving (B) + injection
    m[:, 0, 0], m[:, 0, 1] = eu, -setup.reflection_up / eu
    # downstream end (x' = length_down): the wave leaving it (D) = R * arriving (C) + injection
    m[:, 1, 3], m[:, 1, 2] = ed, -setup.reflection_down / ed
    rhs[:, 0 if setup.source == "up" else 1] = 1.0
    # specimen: (p, U) downstream = T (p, U) upstream, p = wave sum, U = wave difference / z0
    up_state = np.stack([np.stack([np.ones(nf), np.ones(nf)], -1), np.stack([1 / z0, -1 / z0], -1)], -2)
    m[:, 2:4, 0:2] = t @ up_state
    m[:, 2:4, 2:4] = -up_state
    a, b, c, d = np.moveaxis(np.linalg.solve(m, rhs[..., None])[..., 0], -1, 0)
    out = np.empty((nf, x.size), dtype=complex)
    for i, xi in enumerate(x):
        if xi <= 0:
            out[:, i] = a * np.exp(-1j * k * xi) + b * np.exp(1j * k * xi)
        else:
            xd = xi - thickness
            out[:, i] = c * np.exp(-1j * k * xd) + d * np.exp(1j * k * xd)
    return out


def closed_end(f, length: float, tube: Tube) -> np.ndarray:
    """Impedance ``p / U`` [Pa s/m^3] (exp(+i omega t)) at the mouth of a tube of ``length``
    [m] closed by a rigid wall: the wave returning from the wall, reflection 1, brought back
    to the mouth, ``z0 (1 + e^{-2ikL}) / (1 - e^{-2ikL})``."""
    r = np.exp(-2j * tube.wavenumber(f) * length)
    return tube.impedance(f) * (1 + r) / (1 - r)


def sensor_pressures(core, load) -> np.ndarray:
    """(nf, 2) pressures ``(p(x1), p(x6))`` per unit volume velocity ``U(x1)`` injected at the
    core's upstream face, its downstream face closed by ``load`` (nf,) [Pa s/m^3],
    exp(+i omega t); ``core`` (nf, 2, 2) in tawarp's convention."""
    t = np.conj(np.asarray(core, dtype=complex))
    nf = t.shape[0]
    # unknowns (p1, p6, U6) at U1 = 1: p6 = Tpp p1 + Tpu, U6 = Tup p1 + Tuu, p6 = ZL U6
    m = np.zeros((nf, 3, 3), dtype=complex)
    m[:, 0, 0], m[:, 0, 1] = t[:, 0, 0], -1.0
    m[:, 1, 0], m[:, 1, 2] = t[:, 1, 0], -1.0
    m[:, 2, 1], m[:, 2, 2] = 1.0, -np.asarray(load, dtype=complex)
    rhs = np.stack([-t[:, 0, 1], -t[:, 1, 1], np.zeros(nf)], -1)
    return np.linalg.solve(m, rhs[..., None])[..., 0][:, :2]


def sensor_signals(core_of_f, load_of_f, sample_rate, samples, band, snr_db, seed=0) -> np.ndarray:
    """(samples, 3) time signals of the multi-termination method: the sensor's volume velocity
    ``U(x1)`` (channel 0, noise-free, the reference), ``p(x1)`` and ``p(x6)`` with white noise
    at ``snr_db``. ``core_of_f``, ``load_of_f``: functions of frequencies (nf,) [Hz] giving the
    core's T-matrix (tawarp's convention) and the termination's impedance (exp(+i omega t))."""
    rng = generator(seed, "sensor_signals")
    f, on, drive = _drive(sample_rate, samples, band, rng)
    spectra = np.zeros((f.size, 3), dtype=complex)
    spectra[:, 0] = drive
    spectra[on, 1:] = sensor_pressures(core_of_f(f[on]), load_of_f(f[on])) * drive[on, None]
    out = np.fft.irfft(spectra, samples, axis=0)
    return _add_noise(out, snr_db, rng)


def sensor_measurement(
    core_of_f,
    lengths,
    tube: Tube,
    band: tuple[float, float],
    snr_db: float = 30.0,
    seed: int = 0,
    sample_rate: float = 1024.0,
    block: int = 1024,
    blocks: int = 33,
) -> tuple[list[Transfers], list[np.ndarray]]:
    """The multi-termination measurement simulated and averaged: for each closed tube of
    ``lengths`` [m] on x6, :func:`sensor_signals` (drive up to 0.49 ``sample_rate``) and
    Welch's transfer functions ``(Zin, Z61)`` on the lines within ``band`` [Hz], with the
    terminations' impedances there (exp(+i omega t)). ``blocks`` non-overlapping block
    lengths of signal (~2 ``blocks`` averages at 50 % overlap); 1 Hz lines by default, fine
    enough for the closed tubes' resonances."""
    checked_seed(seed, "sensor_measurement", integer=True)
    drive = (0.5 * band[0], 0.49 * sample_rate)
    readings, loads = [], []
    for j, length in enumerate(lengths):
        x = sensor_signals(
            core_of_f,
            lambda f, length=length: closed_end(f, length, tube),
            sample_rate,
            block * blocks,
            drive,
            snr_db,
            seed=1000 * seed + j,
        )
        readings.append(welch(x, sample_rate, block).band(*band).transfers(0, [1, 2]))
        loads.append(closed_end(readings[-1].frequencies, length, tube))
    return readings, loads


def _drive(sample_rate: float, samples: int, band: tuple[float, float], rng):
    """The drive's spectrum on the FFT lines ``f`` [Hz] of ``samples`` at ``sample_rate``:
    complex Gaussian on the lines ``on`` within ``band`` [Hz], zero elsewhere."""
    f = np.fft.rfftfreq(samples, 1.0 / sample_rate)
    on = (f >= band[0]) & (f <= band[1])
    drive = np.zeros(f.size, dtype=complex)
    drive[on] = rng.standard_normal(on.sum()) + 1j * rng.standard_normal(on.sum())
    return f, on, drive


def _add_noise(out: np.ndarray, snr_db: float, rng) -> np.ndarray:
    """White Gaussian noise on every channel but the reference (0), ``snr_db`` below each one's power."""
    noise_sd = np.sqrt(np.var(out[:, 1:], axis=0) * 10 ** (-snr_db / 10))
    out[:, 1:] += noise_sd * rng.standard_normal((out.shape[0], out.shape[1] - 1))
    return out


def signals(
    specimen_of_f,
    thickness: float,
    setup: Setup,
    tube: Tube,
    positions,
    sample_rate: float,
    samples: int,
    band: tuple[float, float],
    snr_db: float,
    gains=None,
    seed: int = 0,
) -> np.ndarray:
    """(samples, 1 + n) time signals: the drive (channel 0, noise-free) and the microphones
    at ``positions``. ``specimen_of_f``: a function of frequencies (nf,) [Hz] returning the
    specimen's T-matrix (nf, 2, 2) in tawarp's convention. The drive's spectrum is complex
    Gaussian over ``band`` [Hz] and zero elsewhere; ``gains`` (n,) complex microphone gain
    errors (exp(+i omega t): a microphone reads ``g p``; None: 1); each microphone gets white
    Gaussian noise of variance ``10^(-snr_db/10)`` times its signal's."""
    rng = generator(seed, "signals")
    f, on, drive = _drive(sample_rate, samples, band, rng)
    n = len(positions)
    spectra = np.zeros((f.size, n), dtype=complex)
    p = pressures(f[on], specimen_of_f(f[on]), thickness, setup, tube, positions)
    g = np.ones(n) if gains is None else np.asarray(gains, dtype=complex)
    spectra[on] = p * g[None, :] * drive[on, None]
    out = np.empty((samples, 1 + n))
    out[:, 0] = np.fft.irfft(drive, samples)
    out[:, 1:] = np.fft.irfft(spectra, samples, axis=0)
    return _add_noise(out, snr_db, rng)
