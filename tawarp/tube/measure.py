"""From a measurement description to the measured T-matrix or surface impedance, with
standard deviations, as the CSV that ``tawarp fit`` and ``tawarp loop`` read.

:func:`measure` reads the description (:mod:`.setup`) and the signal files
(:mod:`.signals`), forms the averaged cross-spectra and the transfer functions from the
reference channel, corrects them by the switched-microphone calibration, fits the tube
to the empty-tube data (:mod:`.calibration`), computes the plane waves (:mod:`.acoustics`)
and runs the method (:mod:`.e2611`, :mod:`.iso10534`) for each microphone position set in
its band, or the multi-termination method (:mod:`.terminations`) at each heat input from
the impedance sensor's transfer functions (its errors: the random term alone). The
standard deviation of every output coefficient adds, as variances of the
real and of the imaginary part, three independent first-order terms:

1. the random error of the transfer functions (coherence and averages, Bendat & Piersol)
   through the method (the method's own ``sd``);
2. the switched-microphone factors' error (common to every configuration, so propagated
   here, by central differences of the whole method in the factors);
3. the self-calibration's fitted positions, temperature and wall-loss factor (their
   covariance from the fit, propagated alike).

Where the position sets' bands overlap, each frequency comes from the set whose method is
better conditioned. Frequencies where the method is ill-conditioned are left out of the
output and listed in its header (``left_out_Hz``, ``left_out_reason``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io import claim_outputs
from ..measure.files import ImpedanceData, TMatrixData, write_impedance_csv, write_tmatrix_csv
from ..measure.table import MeasurementError
from ..model.gas import GASES
from . import e2611, iso10534, terminations
from .acoustics import plane_waves
from .calibration import MicrophoneGains, SelfCalibration, corrected, self_calibrate, switched_gains
from .result import TubeResult
from .setup import PositionSet, Setup, load_setup
from .signals import cross_spectra
from .spectra import CrossSpectra, Transfers

#: Relative step of the central differences that propagate the calibration errors.
STEP = 1e-6


@dataclass
class SetResult:
    """One position set's outcome: ``result`` in its band (sd: all three error terms,
    circular equivalent), ``sd_parts`` (nf, ..., 2) sd of the real and imaginary parts,
    the self-calibration (or None) and how much it changed the result."""

    positions: PositionSet
    result: TubeResult
    sd_parts: np.ndarray
    self_calibration: SelfCalibration | None
    self_calibration_change: dict | None
    heat_input: float = 0.0


@dataclass
class Measurement:
    """What :func:`measure` returns: the description, each set's results, the combined
    output ``data`` (:class:`TMatrixData` or :class:`ImpedanceData`, valid frequencies
    only), the frequencies left out with their reasons, and a summary for the header."""

    setup: Setup
    sets: list[SetResult]
    data: TMatrixData | ImpedanceData
    left_out: dict[tuple[float, float], str]  # (heat input [W], frequency [Hz]) -> why
    summary: dict


def _spectra(setup: Setup, path: Path) -> CrossSpectra:
    s = cross_spectra(path, setup.welch, setup.sample_rate)
    if setup.reference >= s.channels:
        raise MeasurementError(f"{path}: {s.channels} channels; measurement.reference = {setup.reference} is not there")
    return s


def _geometry(setup: Setup, x):
    """The method's geometry from positions ``x`` [m] (setup module doc)."""
    if setup.method == "iso10534":
        return -x[0], -x[1]
    return e2611.FourMics(l1=-x[1], s1=x[1] - x[0], l2=x[2], s2=x[3] - x[2], thickness=setup.thickness)


def _run(setup: Setup, transfers, x, gas, loss):
    """The method on calibrated ``transfers`` with microphones at ``x`` in ``gas`` with the
    wall-loss factor ``loss``."""
    f = transfers[0].frequencies
    k, z = plane_waves(f, gas, setup.tube, loss)
    kp = np.conj(k)  # the methods work in the spectra's exp(+i omega t)
    if setup.method == "iso10534":
        g = GASES[gas.name]
        rho_c = gas.pressure * np.sqrt(g.gamma / (g.R_gas * gas.temperature))  # the impedance CSV's rho0 c0
        return iso10534.surface_impedance(transfers[0], *_geometry(setup, x), kp, np.conj(z) / rho_c)
    method = {"two_load": e2611.two_load, "one_load": e2611.one_load, "two_source": e2611.two_source}[setup.method]
    return method(*transfers, _geometry(setup, x), kp, np.conj(z) / setup.tube.area)


def _parts(values) -> np.ndarray:
    return np.stack([values.real, values.imag], -1)


def _propagate(fn, n: int, cov_pairs) -> np.ndarray:
    """Variances (..., 2) of the real and imaginary parts of ``fn(delta)`` (complex) from
    ``n`` real parameters ``delta`` (zero nominal) with covariance ``cov_pairs`` (nf, n, n)
    per frequency or (n, n) for all: central differences of step :data:`STEP`."""
    cols = []
    for i in range(n):
        d = np.zeros(n)
        d[i] = STEP
        cols.append(_parts((fn(d) - fn(-d)) / (2 * STEP)))
    jac = np.stack(cols, -1)  # (nf, ..., 2, n)
    jac = np.nan_to_num(jac)
    cov = np.asarray(cov_pairs)
    if cov.ndim == 2:
        return np.einsum("...i,ij,...j->...", jac, cov, jac)
    shape = (cov.shape[0],) + (1,) * (jac.ndim - 2) + cov.shape[1:]
    return np.einsum("...i,...ij,...j->...", jac, cov.reshape(shape), jac)


def _gain_pairs(gains: MicrophoneGains) -> np.ndarray:
    """(nf, 2n, 2n) covariance of (Re dc, Im dc) of circular complex errors with
    ``E[dc_j conj(dc_k)] = C_jk``: ``E[x_j x_k] = E[y_j y_k] = Re C / 2``,
    ``E[y_j x_k] = Im C / 2``."""
    C = gains.covariance
    re, im = C.real / 2, C.imag / 2
    return np.block([[re, -im], [im, re]])


def _band_gains(gains: MicrophoneGains, channels, lo: float, hi: float) -> MicrophoneGains:
    """The factors of ``channels`` at lo <= f <= hi [Hz]."""
    g = gains.select(channels)
    keep = (g.frequencies >= lo) & (g.frequencies <= hi)
    return MicrophoneGains(g.frequencies[keep], g.channels, g.factors[keep], g.covariance[keep])


def _tube_fit(setup: Setup, direct: CrossSpectra, gains) -> tuple[SelfCalibration, list[int]]:
    """One self-calibration of the tube (:func:`tawarp.tube.calibration.self_calibrate`)
    over every microphone of every position set, ordered downstream, and the union of the
    sets' bands: one tube, one gas for all sets. Returns it and the channels in its order."""
    where = {}
    for n, s in enumerate(setup.sets):
        for c, x in zip(s.channels, s.positions):
            if c in where and where[c] != x:
                raise setup.error(
                    f"microphones[{n}].positions",
                    f"channel {c} at {x} m, at {where[c]} m in an earlier set; one microphone has one place",
                )
            where[c] = x
    channels = sorted(where, key=where.get)
    x = [where[c] for c in channels]
    if len(set(x)) != len(x):
        raise setup.error("microphones", f"two channels share a position: {dict(zip(channels, x))}")
    lo, hi = min(s.band[0] for s in setup.sets), max(s.band[1] for s in setup.sets)
    empty = direct.band(lo, hi).transfers(setup.reference, channels)
    if gains is not None:
        empty = corrected(empty, _band_gains(gains, channels, lo, hi))
    return self_calibrate(empty, x, setup.gas, setup.tube), channels


def _one_set(setup: Setup, pset: PositionSet, spectra, gains, tube_fit, progress) -> SetResult:
    """The method in ``pset``'s band; ``tube_fit`` (the self-calibration and its channels)
    or None for the description's tube."""
    lo, hi = pset.band
    ch = list(pset.channels)
    measured = [s.band(lo, hi).transfers(setup.reference, ch) for s in spectra]
    band_gains = _band_gains(gains, ch, lo, hi) if gains is not None else None
    transfers = [corrected(t, band_gains) for t in measured] if band_gains is not None else measured
    x = np.array(pset.positions)
    gas, loss, fitted = setup.gas, 1.0, None
    if tube_fit is not None:
        fitted, order = tube_fit
        idx = [order.index(c) for c in ch]
        x = np.array(fitted.positions)[idx]
        gas, loss = dataclasses.replace(setup.gas, temperature=fitted.temperature), fitted.loss
    progress()
    result = _run(setup, transfers, x, gas, loss)
    var = np.stack([result.sd**2, result.sd**2], -1)  # circular: the same for both parts
    if band_gains is not None:
        movable = [i for i, c in enumerate(ch) if c != setup.reference]
        m = len(movable)

        def with_gains(d):
            dc = np.zeros(len(ch), dtype=complex)
            dc[movable] = d[:m] + 1j * d[m:]
            scaled = dataclasses.replace(band_gains, factors=band_gains.factors * (1 + dc))
            return _run(setup, [corrected(t, scaled) for t in measured], x, gas, loss).values

        sub = band_gains.covariance[:, movable][:, :, movable]
        var = var + _propagate(with_gains, 2 * m, _gain_pairs(dataclasses.replace(band_gains, covariance=sub)))
    change = None
    if fitted is not None:
        inner = len(fitted.positions) - 2

        def with_tube(d):
            y = np.array(fitted.positions)
            y[1:-1] += d[:inner]
            shifted = dataclasses.replace(gas, temperature=gas.temperature + d[-2])
            return _run(setup, transfers, y[idx], shifted, loss + d[-1]).values

        var = var + _propagate(with_tube, inner + 2, fitted.covariance)
        nominal = _run(setup, transfers, np.array(pset.positions), setup.gas, 1.0)
        change = _change(nominal, result)
    progress()
    sd_parts = np.sqrt(var)
    sd = np.sqrt(np.mean(var, axis=-1))
    result = dataclasses.replace(result, sd=np.where(result.valid.reshape((-1,) + (1,) * (sd.ndim - 1)), sd, np.nan))
    return SetResult(pset, result, sd_parts, fitted, change, setup.heat_input)


def _terminations(setup: Setup, spectra, progress) -> list[SetResult]:
    """The multi-termination method at each heat input: the sensor's transfer functions
    from the volume-velocity channel (scaled by ``sensor.scale``) to ``p(x1)``, ``p(x6)``
    under each known termination."""
    pset = setup.sets[0]
    ch = list(pset.channels)
    out = []
    for q in sorted({t.heat_input for t in setup.terminations}):
        chosen = [i for i, t in enumerate(setup.terminations) if t.heat_input == q]
        readings = []
        for i in chosen:
            t = spectra[i].band(*pset.band).transfers(setup.reference, ch)
            a = setup.sensor_scale
            readings.append(Transfers(t.frequencies, a * t.values, a * a * t.covariance))
        f = readings[0].frequencies
        k, z = plane_waves(f, setup.gas, setup.tube)
        kp, z0 = np.conj(k), np.conj(z) / setup.tube.area  # the method's exp(+i omega t)
        loads = []
        for i in chosen:
            term = setup.terminations[i]
            if term.closed_tube is not None:
                loads.append(terminations.closed_tube(kp, z0, term.closed_tube))
            else:
                table = term.impedance
                zl = np.interp(f, table[:, 0], table[:, 1]) + 1j * np.interp(f, table[:, 0], table[:, 2])
                loads.append(np.conj(zl))
        progress()
        r = terminations.core_tmatrix(readings, loads, z0)
        progress()
        name = f"Q = {q:g} W"
        out.append(SetResult(dataclasses.replace(pset, name=name), r, np.stack([r.sd, r.sd], -1), None, None, q))
    return out


def _change(before: TubeResult, after: TubeResult) -> dict:
    """Median relative change of each coefficient where both are valid."""
    ok = before.valid & after.valid
    names = ["Zs"] if after.values.ndim == 1 else ["Tpp", "Tpu", "Tup", "Tuu"]
    a, b = after.values[ok].reshape(ok.sum(), -1), before.values[ok].reshape(ok.sum(), -1)
    if not ok.any():
        return {}
    rel = np.abs(a - b) / np.abs(a)
    return {n: float(f"{np.median(rel[:, i]):.4g}") for i, n in enumerate(names)}


def measure(
    setup: Setup | str | Path,
    *,
    method: str | None = None,
    self_calibration: bool | None = None,
    progress: bool = False,
    data_dir: str | Path | None = None,
) -> Measurement:
    """Run the description ``setup`` (a :class:`Setup`, its TOML path or a bundled
    description's name); ``method`` and ``self_calibration`` override the description's
    (module doc); ``data_dir``: the folder its file names are relative to (default: the
    description's)."""
    from ..progress import progress_bar

    if not isinstance(setup, Setup):
        setup = load_setup(setup, data_dir)
    if method is not None and method != setup.method:
        raise setup.error("measurement.method", f"is {setup.method!r}; --method {method!r} needs a description for it")
    cal = setup.calibration
    self_cal = cal.self_calibration if self_calibration is None else self_calibration and cal.direct is not None
    n_files = len(setup.files) + (cal.direct is not None) + len(cal.switched)
    n_runs = len({t.heat_input for t in setup.terminations}) or len(setup.sets)
    with progress_bar(n_files + 2 * n_runs, f"measure {Path(setup.source).name}", progress) as bar:

        def read(p):
            s = _spectra(setup, p)
            bar.update()
            return s

        spectra = [read(p) for p in setup.files]
        for p, s in zip(setup.files[1:], spectra[1:]):
            if s.frequencies.shape != spectra[0].frequencies.shape or not np.allclose(
                s.frequencies, spectra[0].frequencies
            ):
                raise MeasurementError(f"{p}: frequencies differ from {setup.files[0]}'s: same sample rate and block")
        direct = read(cal.direct) if cal.direct is not None else None
        gains = None
        if cal.switched:
            switched = {c: read(p) for c, p in cal.switched.items()}
            gains = switched_gains(direct, switched, setup.reference, {c: str(p) for c, p in cal.switched.items()})
        if direct is not None and not np.allclose(direct.frequencies, spectra[0].frequencies):
            raise MeasurementError(
                f"{cal.direct}: frequencies differ from {setup.files[0]}'s: same sample rate and block"
            )
        tube_fit = _tube_fit(setup, direct, gains) if self_cal else None
        if setup.method == "terminations":
            sets = _terminations(setup, spectra, bar.update)
        else:
            sets = [_one_set(setup, s, spectra, gains, tube_fit, bar.update) for s in setup.sets]
    return _combine(setup, sets, gains is not None, tube_fit)


def _combine(setup: Setup, sets: list[SetResult], switched: bool, tube_fit) -> Measurement:
    """One row per (heat input, frequency): the valid set of lowest condition; the others
    left out."""
    best: dict[tuple[float, float], tuple] = {}
    reasons: dict[tuple[float, float], str] = {}
    for s in sets:
        r = s.result
        for i, f in enumerate(r.frequencies):
            key = (s.heat_input, float(f))
            if not r.valid[i]:
                reasons.setdefault(key, f"{s.positions.name}: {r.reason[i]}")
                continue
            if key not in best or r.condition[i] < best[key][0]:
                best[key] = (r.condition[i], r.values[i], s.sd_parts[i], s.positions.name)
    left_out = {key: why for key, why in sorted(reasons.items()) if key not in best}
    if not best:
        raise MeasurementError(f"{setup.source}: the method is ill-conditioned at every frequency of every band")
    keys = sorted(best)
    heat = np.array([q for q, _ in keys])
    freqs = np.array([f for _, f in keys])
    values = np.stack([best[key][1] for key in keys])
    sd = np.stack([best[key][2] for key in keys])
    g = setup.gas
    summary = {
        "generator": "tawarp measure",
        "description": str(Path(setup.source).resolve()),
        "method": setup.method,
        "tube": f"{setup.tube.shape} {setup.tube.width:g} x {setup.tube.height:g} m, area {setup.tube.area:.6g} m^2",
        "gas": f"{g.name}, {g.temperature:g} K, {g.pressure:g} Pa, humidity {g.humidity:g} %",
        **_layout(setup, sets),
        "calibration": ", ".join(
            [p for p, on in (("switched microphones", switched), ("empty-tube self-calibration", tube_fit)) if on]
        )
        or "none",
        "sigma": "random error of the transfer functions (Bendat & Piersol)"
        + (" + switched-microphone factors" if switched else "")
        + (" + self-calibrated tube" if tube_fit is not None else "")
        + ", first order",
        "welch": ", ".join(f"{k} {v}" for k, v in setup.welch.items()),
    }
    if tube_fit is not None:
        fit, channels = tube_fit
        summary["self_calibration.channels"] = channels
        for k, v in fit.summary().items():
            summary[f"self_calibration.{k}"] = v
        for s in sets:
            summary[f"self_calibration.median_change.{s.positions.name}"] = s.self_calibration_change
    several = len({q for q, _ in keys}) > 1
    where = lambda q, f: f"{q:g} W {f:g}" if several else f"{f:g}"  # noqa: E731
    summary["left_out_Hz"] = ", ".join(where(q, f) for q, f in left_out) or "none"
    if left_out:
        summary["left_out_reason"] = "; ".join(f"{where(q, f)} Hz: {why}" for (q, f), why in left_out.items())
    meta = {k: str(v) for k, v in summary.items() if k != "generator"}
    meta["generator"] = "tawarp measure"
    if setup.method == "iso10534":
        data = ImpedanceData(freqs, values, setup.thickness, g.temperature, g.pressure, meta, setup.source, sigma=sd)
    else:
        data = TMatrixData(heat, freqs, values, sd, meta, setup.source)
    return Measurement(setup, sets, data, left_out, summary)


def _layout(setup: Setup, sets: list[SetResult]) -> dict:
    """The header lines that say where the microphones were (or the sensor and its loads)."""
    if setup.method != "terminations":
        return {
            "position_sets": "; ".join(
                f"{s.positions.name}: channels {list(s.positions.channels)} at {list(s.positions.positions)} m, "
                f"{s.positions.band[0]:.6g}-{s.positions.band[1]:.6g} Hz"
                for s in sets
            )
        }
    p = setup.sets[0]
    return {
        "sensor": f"channels {list(p.channels)} = p(x1), p(x6) over channel {setup.reference} = U(x1), scale "
        f"{setup.sensor_scale:g}, {p.band[0]:.6g}-{p.band[1]:.6g} Hz",
        "terminations": "; ".join(
            f"{t.file.name} at {t.heat_input:g} W: "
            + (f"closed tube {t.closed_tube:g} m" if t.closed_tube is not None else "tabulated impedance")
            for t in setup.terminations
        ),
    }


def write_measurement(m: Measurement, path: str | Path, figure: bool = True) -> list[Path]:
    """Write the output CSV ``path`` (and ``STEM_measure.png`` beside it); returns the files."""
    path = Path(path)
    png = path.with_name(f"{path.stem}_measure.png")
    if figure:
        claim_outputs(png, why="the figure of tawarp measure")
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(m.data, ImpedanceData):
        write_impedance_csv(path, m.data)
    else:
        write_tmatrix_csv(path, m.data)
    out = [path]
    if figure:
        out.append(plot_measurement(m, png))
    return out


def plot_measurement(m: Measurement, path: str | Path) -> Path:
    """Each coefficient (real and imaginary part) of every position set with its
    one-sd band, and the method's condition number (log scale)."""
    import matplotlib.pyplot as plt

    from ..plots import save

    impedance = m.setup.method == "iso10534"
    names = ["Zs / (rho0 c0)"] if impedance else ["Tpp", "Tpu / z0", "Tup z0", "Tuu"]
    fig, axes = plt.subplots(1, len(names) + 1, figsize=(4 * (len(names) + 1), 3.6))
    z0 = 1.0
    for s in m.sets:
        r = s.result
        f = r.frequencies
        vals = r.values.reshape(len(f), -1)
        sds = s.sd_parts.reshape(len(f), -1, 2)
        if not impedance:
            g = m.setup.gas
            from .acoustics import density, sound_speed

            z0 = density(g) * sound_speed(g) / m.setup.tube.area
            scale = np.array([1.0, 1 / z0, z0, 1.0])
            vals, sds = vals * scale, sds * scale[None, :, None]
        for c, name in enumerate(names):
            ax = axes[c]
            for part, style in ((0, "-"), (1, "--")):
                v = vals[:, c].real if part == 0 else vals[:, c].imag
                line = ax.plot(f, v, style, lw=1, label=f"{s.positions.name} {'Re' if part == 0 else 'Im'}")[0]
                ax.fill_between(f, v - sds[:, c, part], v + sds[:, c, part], color=line.get_color(), alpha=0.25, lw=0)
            ax.set_title(name)
            ax.set_xlabel("frequency [Hz]")
        axes[-1].semilogy(f, r.condition, lw=1, label=s.positions.name)
    axes[0].legend(fontsize=7)
    axes[-1].set_title("condition number")
    axes[-1].set_xlabel("frequency [Hz]")
    axes[-1].legend(fontsize=7)
    fig.suptitle(f"{Path(m.setup.source).name}: {m.setup.method}, one-sd bands (exp(-iwt))")
    fig.tight_layout()
    return save(fig, path)
