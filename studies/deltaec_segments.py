"""DeltaEC's stack segments with imposed end temperatures, rebuilt in tawarp.

    python studies/deltaec_segments.py [--out studies/out/deltaec_segments.json]

DeltaEC (Ward, Clark & Swift, Los Alamos) ships example models whose segment outputs
(p1, U1 and the mean temperature at each segment's end) the open-thermoacoustics
repository (github.com/kldavis4/open-thermoacoustics, examples/validation/) copies into its
validation scripts. Three of them are stacks with a temperature gradient in helium:

* ``Hofler1`` segment 4, STKSLAB (validate_reference_full.py, validate_reference_stack.py):
  the parallel-plate stack of Hofler's refrigerator, 1 MPa, 500 Hz, 300 K -> 217.03 K;
* ``5inch`` segment 4, STKCIRC (validate_stkcirc.py): the circular-pore honeycomb stack of
  the 5-inch engine, 1.38 MPa, 121.15 Hz, 556.89 K -> 306.34 K;
* ``optr`` segment 4, STKDUCT (validate_optr_stkduct.py): the pulse tube of the orifice
  pulse-tube refrigerator, an empty duct, 3 MPa, 300 Hz, 149.90 K -> 300.20 K.

Each is rebuilt as a one-segment tawarp core: the segment's geometry (tube radius from its
area, circular pores or plates of its radius or half-gap, its porosity), the gas and mean
pressure, and the imposed linear profile from DeltaEC's start temperature to its end
temperature. DeltaEC's (p1, U1) at the segment's start, carried through tawarp's T-matrix
at DeltaEC's frequency, is compared with DeltaEC's (p1, U1) at the end: the relative error
of each complex amplitude's magnitude and the error of its phase [deg].

What differs (DeltaEC's documentation, Swift's "Thermoacoustics" ch. 4-7): DeltaEC solves
the mean temperature in a stack from its total power flow H_tot (the profile is not
linear: the temperature at each end is the same, the slope along the stack is not); it
includes the solid's heat capacity (epsilon_s, negligible for stainless steel against
helium, a few per cent of the thermal function for Hofler's Kapton-like plates); STKDUCT
uses the boundary-layer form of the thermoviscous functions, and DeltaEC its own fits of
helium's viscosity and conductivity. tawarp has none of these: a linear profile, a
solid at its own temperature, the exact pore functions, helium's power laws
(tawarp/model/gas.py).

Writes JSON (per case: inputs, DeltaEC's and tawarp's outputs, the errors) and the table
beside it (``.txt``), and prints the table.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from tawarp.io import write_json, write_text
from tawarp.model.core import core_from_dict
from tawarp.model.forward import ForwardSettings, transfer_matrices

#: Tolerances of the comparison: the magnitude of each complex amplitude [relative] and its phase [deg].
MAGNITUDE_TOLERANCE = 0.01
PHASE_TOLERANCE_DEG = 1.5


def _phasor(magnitude: float, phase_deg: float) -> complex:
    return magnitude * np.exp(1j * math.radians(phase_deg))


#: DeltaEC's segments: geometry, gas, frequency, imposed temperatures and (p1 [Pa], U1 [m^3/s])
#: as (magnitude, phase [deg]) at the segment's start and end, as the open-thermoacoustics
#: validation scripts quote DeltaEC's output.
CASES = {
    "Hofler1 STKSLAB": dict(
        source="Hofler1 segment 4 (examples/validation/validate_reference_full.py)",
        gas="helium",
        p_mean=1.0e6,
        frequency=500.0,
        area=1.134e-3,
        length=7.85e-2,
        pore_model="plates",
        pore_radius=1.8e-4,
        porosity=0.7240,
        T_start=300.0,
        T_end=217.03,
        p_start=(29570.0, -0.12971),
        U_start=(3.0568e-3, -81.875),
        p_end=(26103.0, 1.4277),
        U_end=(6.8004e-3, -87.965),
    ),
    "5inch STKCIRC": dict(
        source="5inch segment 4 (examples/validation/validate_stkcirc.py)",
        gas="helium",
        p_mean=1.38e6,
        frequency=121.15,
        area=1.2920e-2,
        length=0.2790,
        pore_model="circular",
        pore_radius=5.0e-4,
        porosity=0.8100,
        T_start=556.89,
        T_end=306.34,
        p_start=(7.1468e4, 0.39052),
        U_start=(9.6743e-2, -91.205),
        p_end=(6.5648e4, 2.7637),
        U_end=(0.15967, -85.361),
    ),
    "optr STKDUCT": dict(
        source="optr segment 4 (examples/validation/validate_optr_stkduct.py)",
        gas="helium",
        p_mean=3.0e6,
        frequency=300.0,
        area=5.687e-5,
        length=0.2,
        pore_model=None,
        pore_radius=None,
        porosity=1.0,
        T_start=149.90,
        T_end=300.20,
        p_start=(1.1527e5, -15.367),
        U_start=(1.2192e-3, -29.702),
        p_end=(1.0482e5, -44.00),
        U_end=(1.3018e-3, -51.089),
    ),
}


def case_core(case: dict):
    """A one-segment tawarp core of a DeltaEC segment with its imposed linear profile."""
    segment = dict(name="segment", length=case["length"], T_start=case["T_start"], T_end=case["T_end"])
    if case["pore_model"] is None:  # an empty duct (STKDUCT)
        segment["kind"] = "duct"
    else:
        segment.update(
            kind="porous", pore_model=case["pore_model"], pore_radius=case["pore_radius"], porosity=case["porosity"]
        )
    data = {
        "gas": {"name": case["gas"], "p_mean": case["p_mean"], "T_cold": case["T_start"]},
        "tube": {"radius": math.sqrt(case["area"] / math.pi)},
        "segment": [segment],
    }
    return core_from_dict(data, f"DeltaEC {case['source']}")


def segment_end(case: dict, device: str = "cpu") -> tuple[complex, complex]:
    """(p1 [Pa], U1 [m^3/s]) at the segment's end from DeltaEC's values at its start, both in
    DeltaEC's convention exp(+i omega t): a phasor there is the complex conjugate of tawarp's
    (exp(-i omega t), docs/physics.md)."""
    settings = ForwardSettings(tolerance=1e-9, device=device)
    T = transfer_matrices(case_core(case), [case["frequency"]], settings=settings).T[0, 0]
    start = np.conj([_phasor(*case["p_start"]), _phasor(*case["U_start"])])
    p, U = np.conj(T @ start)
    return complex(p), complex(U)


def _phase_error(ours: complex, theirs: complex) -> float:
    return math.degrees(np.angle(ours / theirs))


def compare(case: dict, device: str = "cpu") -> dict:
    """tawarp's end state against DeltaEC's: relative magnitude errors and phase errors [deg]."""
    p, U = segment_end(case, device)
    p_ref, U_ref = _phasor(*case["p_end"]), _phasor(*case["U_end"])
    out = {
        "p_end": {"magnitude_Pa": abs(p), "phase_deg": math.degrees(np.angle(p))},
        "U_end": {"magnitude_m3_per_s": abs(U), "phase_deg": math.degrees(np.angle(U))},
        "p_magnitude_error": abs(p) / abs(p_ref) - 1,
        "p_phase_error_deg": _phase_error(p, p_ref),
        "U_magnitude_error": abs(U) / abs(U_ref) - 1,
        "U_phase_error_deg": _phase_error(U, U_ref),
    }
    out["within_tolerance"] = bool(
        max(abs(out["p_magnitude_error"]), abs(out["U_magnitude_error"])) <= MAGNITUDE_TOLERANCE
        and max(abs(out["p_phase_error_deg"]), abs(out["U_phase_error_deg"])) <= PHASE_TOLERANCE_DEG
    )
    return out


def table(results: dict) -> str:
    """The comparison as a plain-text table."""
    head = f"{'segment':<18}{'|p1| err':>10}{'ph p1 [deg]':>13}{'|U1| err':>10}{'ph U1 [deg]':>13}  within"
    rows = [head, "-" * len(head)]
    for name, r in results.items():
        rows.append(
            f"{name:<18}{100 * r['p_magnitude_error']:>9.3f}%{r['p_phase_error_deg']:>13.3f}"
            f"{100 * r['U_magnitude_error']:>9.3f}%{r['U_phase_error_deg']:>13.3f}  {r['within_tolerance']}"
        )
    return "\n".join(rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="studies/out/deltaec_segments.json")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    results = {name: compare(case, args.device) for name, case in CASES.items()}
    write_json(
        Path(args.out),
        {
            "what": "DeltaEC example stack segments with imposed end temperatures, rebuilt in tawarp",
            "tolerance": {"magnitude": MAGNITUDE_TOLERANCE, "phase_deg": PHASE_TOLERANCE_DEG},
            "cases": {name: {"deltaec": CASES[name], "tawarp": r} for name, r in results.items()},
        },
    )
    write_text(Path(args.out).with_suffix(".txt"), table(results) + "\n")
    print(table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
