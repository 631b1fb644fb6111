"""The bundled E2611 tube data processed by tawarp against the peer package's own two-load
result (tawarp/data/measured/e2611_tube: its README; the peer is
tjueterb/impedancetube, whose tests saved ``reference/transfer_matrix_*.npy``).

Convention mapping. The peer's transfer functions are ``csm[:, n, ref] / csm[:, ref, ref]``
with acoular's ``csm[i, j] = E[X_i conj(X_j)]`` of numpy FFTs: ``X_n / X_ref``, the
``exp(+i omega t)`` transfer function that tawarp's spectra give too. Its T-matrix maps the
state at the downstream face to the upstream one with the particle velocity ``u``,
``(p, u)(0) = T_peer (p, u)(d)`` (ASTM E2611 eq. 22). tawarp writes
``(p, U)(d) = T (p, U)(0)`` with the volume velocity ``U = S u`` in ``exp(-i omega t)``, so

    T = conj(M T_peer^-1 M^-1),    M = diag(1, S),  S = 0.1 m x 0.1 m.

The peer's air (impedancetube/measurement.py): 20 degC, ``c = 20.047 sqrt(273.15 + 20)``
= 343.23 m/s, ``rho = 1.290 (p / 101.325 kPa) 273.15 / 293.15`` = 1.2020 kg/m^3, and the
wavenumber ``k = (2 pi f + i 0.0194 sqrt(f) / 0.1) / c`` (ISO 10534-2 eq. 7's wall
attenuation for a 0.1 m tube, with the sign of a wave that grows downstream in
``exp(+i omega t)``; ISO writes ``k' - i k''``). Its calibration is the same switched-
microphone ``H_c = sqrt(H_I H_II)`` from the empty_* files, its cross-spectra acoular's
(symmetric Hann window; no overlap for the switched files), block 8192, 50 % overlap.

Four runs, each on the peer's bands (``reference/freqrange_*.npy``):

- ``peer_spectra_peer_air``: the peer's cross-spectral estimator (:func:`acoular_spectra`)
  and air, tawarp's calibration and method: the implementations compared alone;
- ``peer_air``: tawarp's spectra, calibration and two-load method with the peer's ``k``,
  ``rho c`` (what the comparison of the implementations needs);
- ``tawarp_air``: tawarp's own tube (Cramer's dry air at 293.15 K, Kirchhoff's losses);
- ``self_calibrated``: ``tawarp.tube.measure.measure`` on the bundled description, the
  tube fitted to the empty-tube file over all six microphones (its fit is recorded).

Measured (studies/out/e2611_peer.json): ``peer_spectra_peer_air`` agrees with the peer to
2e-7 (the float32 samples' rounding), so the convention mapping and the method are the
peer's; ``peer_air`` differs by 2-7 % in median, all of it from the estimator (the window's
symmetry, the switched files' overlap) on records of 9-11 blocks, where the random error
of each coefficient is 15-25 % (``median_sd_over_value``): the differences are 0.1-0.4 of
tawarp's sd (``median_difference_over_sd``). tawarp's own tube (0.1-0.6 sd) and the
self-calibration (0.15-0.8 sd; it finds 300.4 K and microphones up to 6 mm off their
nominal places, and lowers the empty tube's misfit from 6.9 to 1.6 noise units) move the
result further, within the same random error.

Writes studies/out/e2611_peer.json: per run, band and coefficient the median relative
difference ``|T - T_peer| / |T_peer|`` over the band's frequencies where tawarp's method is
well conditioned, and how many frequencies it left out. Run: ``python studies/e2611_peer.py``
(about a minute).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import scipy.signal

from tawarp.io import write_json
from tawarp.tube import e2611
from tawarp.tube.acoustics import plane_waves
from tawarp.tube.calibration import corrected, switched_gains
from tawarp.tube.measure import measure
from tawarp.tube.setup import load_setup
from tawarp.tube.signals import cross_spectra, read_time_signals
from tawarp.tube.spectra import CrossSpectra, independent_averages

ROOT = Path(__file__).resolve().parents[1]
SETUP = ROOT / "tawarp" / "data" / "tube" / "e2611_two_load.toml"
COEFFICIENTS = ("Tpp", "Tpu", "Tup", "Tuu")


def peer_tube(f, area):
    """The peer's wavenumber and volume-velocity impedance, ``exp(+i omega t)``."""
    c = 20.047 * np.sqrt(273.15 + 20.0)
    rho = 1.290 * 273.15 / 293.15
    k = (2 * np.pi * f + 1j * 0.0194 * np.sqrt(f) / 0.1) / c
    return k, np.full(f.shape, rho * c / area, dtype=complex)


def acoular_spectra(path, block: int, overlap: float) -> CrossSpectra:
    """Cross-spectra as the peer's acoular ``PowerSpectra`` forms them: numpy's symmetric
    Hann window (``np.hanning``), ``overlap`` of a block (the peer's switched files: none)."""
    x, rate = read_time_signals(path)
    w = np.hanning(block)
    noverlap = int(overlap * block)
    rows = []
    for i in range(x.shape[1]):
        f, g = scipy.signal.csd(x[:, i : i + 1], x, fs=rate, window=w, nperseg=block, noverlap=noverlap, axis=0)
        rows.append(g)
    blocks = 1 + (len(x) - block) // (block - noverlap)
    return CrossSpectra(f, np.stack(rows, axis=1), independent_averages(blocks, w, block - noverlap))


def peer_in_tawarp(T_peer, area):
    """The peer's matrices in tawarp's convention (module doc)."""
    M = np.diag([1.0, area])
    return np.conj(M @ np.linalg.inv(T_peer) @ np.linalg.inv(M))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "studies" / "out" / "e2611_peer.json"), help="JSON output")
    args = ap.parse_args(argv)
    setup = load_setup(SETUP)
    ref_dir = setup.files[0].parent / "reference"
    area = setup.tube.area
    block = setup.welch["block"]
    spectra = {
        "tawarp": (
            [cross_spectra(p, setup.welch) for p in setup.files],
            cross_spectra(setup.calibration.direct, setup.welch),
            {c: cross_spectra(p, setup.welch) for c, p in setup.calibration.switched.items()},
        ),
        "acoular": (
            [acoular_spectra(p, block, 0.5) for p in setup.files],
            acoular_spectra(setup.calibration.direct, block, 0.5),
            {c: acoular_spectra(p, block, 0.0) for c, p in setup.calibration.switched.items()},
        ),
    }
    out = {
        "generator": "tawarp studies/e2611_peer.py",
        "data": str(setup.files[0].parent.relative_to(ROOT)),
        "convention_mapping": "T = conj(M inv(T_peer) inv(M)), M = diag(1, S), S = 0.01 m^2: the peer maps "
        "(p, u) at the downstream face to the upstream one in exp(+iwt); tawarp maps (p, U = S u) upstream "
        "to downstream in exp(-iwt)",
        "runs": {},
    }
    sets = {s.name: s for s in setup.sets}
    fitted = measure(setup)
    for run in ("peer_spectra_peer_air", "peer_air", "tawarp_air", "self_calibrated"):
        loads, direct, switched = spectra["acoular" if run.startswith("peer_spectra") else "tawarp"]
        gains = switched_gains(direct, switched, setup.reference)
        out["runs"][run] = {}
        for name in ("wide", "narrow"):
            s = sets[name]
            lo, hi = np.load(ref_dir / f"freqrange_{name}.npy")
            f_ref = np.load(ref_dir / f"freqs_{name}.npy")
            T_ref = np.load(ref_dir / f"transfer_matrix_{name}.npy")
            keep = (f_ref >= lo) & (f_ref <= hi)
            ch = list(s.channels)
            g = gains.select(ch)
            band = (f_ref[keep][0], f_ref[keep][-1])
            kb = (g.frequencies >= band[0]) & (g.frequencies <= band[1])
            gb = dataclasses.replace(
                g, frequencies=g.frequencies[kb], factors=g.factors[kb], covariance=g.covariance[kb]
            )
            tr = [corrected(sp.band(*band).transfers(setup.reference, ch), gb) for sp in loads]
            f = tr[0].frequencies
            x, gas, loss = np.array(s.positions), setup.gas, 1.0
            if run == "self_calibrated":
                r = next(m.result for m in fitted.sets if m.positions.name == name)
                r = dataclasses.replace(
                    r,
                    **{
                        a: getattr(r, a)[np.isin(r.frequencies, f)]
                        for a in ("frequencies", "values", "sd", "valid", "reason", "condition")
                    },
                )
            elif run.endswith("peer_air"):
                k, z0 = peer_tube(f, area)
            else:
                k, z = plane_waves(f, gas, setup.tube, loss)
                k, z0 = np.conj(k), np.conj(z) / area
            if run != "self_calibrated":
                mics = e2611.FourMics(l1=-x[1], s1=x[1] - x[0], l2=x[2], s2=x[3] - x[2], thickness=setup.thickness)
                r = e2611.two_load(*tr, mics, k, z0)
            peer = peer_in_tawarp(T_ref[keep], area)
            ok = r.valid
            rel = np.abs(r.values[ok] - peer[ok]) / np.abs(peer[ok])
            entry = {
                "band_Hz": [float(lo), float(hi)],
                "frequencies": int(keep.sum()),
                "left_out_ill_conditioned": int((~ok).sum()),
                "median_relative_difference": {
                    c: float(f"{np.median(rel[:, i, j]):.4g}") for c, (i, j) in zip(COEFFICIENTS, np.ndindex(2, 2))
                },
                "median_difference_over_sd": {
                    c: float(f"{np.median(np.abs(r.values[ok][:, i, j] - peer[ok][:, i, j]) / r.sd[ok][:, i, j]):.4g}")
                    for c, (i, j) in zip(COEFFICIENTS, np.ndindex(2, 2))
                },
                "median_sd_over_value": {
                    c: float(f"{np.median(r.sd[ok][:, i, j] / np.abs(r.values[ok][:, i, j])):.4g}")
                    for c, (i, j) in zip(COEFFICIENTS, np.ndindex(2, 2))
                },
            }
            out["runs"][run][name] = entry
            print(run, name, entry["median_relative_difference"], "left out", entry["left_out_ill_conditioned"])
    out["self_calibration"] = {k: v for k, v in fitted.summary.items() if k.startswith("self_calibration.")}
    path = write_json(args.out, out)  # makes the folder
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
