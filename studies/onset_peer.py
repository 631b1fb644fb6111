"""Onset of the bundled standing-wave engine by tawarp and by openthermoacoustics (PyPI).

    python studies/onset_peer.py [--out studies/out/onset_peer.json]

Same geometry and gas (air, 1 atm, 293.15 K; tube radius 16.7 mm; the core of
``tawarp/data/engines/standing_wave.toml`` between a 0.73 m and a 0.23 m resonator duct,
both ends closed), circular pores of radius 0.47 mm (porosity 0.9) in the stack and the
hot exchanger. The models differ in what sets the temperature:

* tawarp: the heat input Q drives the 1-D steady heat model with lateral losses (docs/physics.md);
  the stack profile is a sum of exponentials, the buffer tube cools back to T_cold, and
  the onset is a heat input, its temperature ratio the largest temperature / T_cold.
* openthermoacoustics: the temperature is imposed: linear in the stack from T_cold to
  T_hot, uniform T_hot in the hot exchanger; the buffer tube is a ``StackDuct`` with a linear
  T_hot -> T_cold profile (tawarp's profile there is close to exponential). Its onset is the
  ratio T_hot / T_cold where Im f crosses 0 (exp(+i omega t): f_imag < 0 grows).

To separate the acoustics from the temperature assumptions, both are also compared
unheated (``isothermal``: T_hot = T_cold, Q = 0), where the two models describe the same
engine: the complex eigenfrequency of each (tawarp's exp(-i omega t) growth rate Im omega
against the peer's -2 pi Im f).

Writes JSON with both onsets, the differences, and the time for one onset prediction.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import scipy.optimize as so

from tawarp.model.onset import eigenfrequencies, onset
from tawarp.model.resonator import load_engine

ENGINE = "standing_wave"


def peer_network(eng, T_hot: float, n_points: int = 120):
    """openthermoacoustics segments of the engine with an imposed profile peaking at T_hot [K]."""
    from openthermoacoustics.geometry.circular import CircularPore
    from openthermoacoustics.segments.duct import Duct
    from openthermoacoustics.segments.heat_exchanger import HeatExchanger
    from openthermoacoustics.segments.stack import Stack
    from openthermoacoustics.segments.stkduct import StackDuct

    core = eng.core
    R = core.radius
    A = math.pi * R**2
    seg = {s.name: s for s in core.segments}
    st, hx, tbt = seg["stack"], seg["hot_hx"], seg["tbt"]
    T_c = core.gas.T_cold
    # CircularPore's "hydraulic radius" is the pore radius (f = 2 J1(z) / (z J0(z)), z = (i - 1) r / delta)
    return [
        Duct(eng.left_duct.length + seg["duct_left"].length, R),
        Stack(
            st.length,
            st.porosity,
            st.pore_radius,
            area=A,
            geometry=CircularPore(),
            solid_thermal_conductivity=st.solid_conductivity,
            T_hot=T_hot,
            T_cold=T_c,
        ),
        HeatExchanger(hx.length, hx.porosity, hx.pore_radius, T_hot, area=A, geometry=CircularPore()),
        # StackDuct runs from its T_cold at x = 0 to its T_hot at x = L: hot end first here
        StackDuct(tbt.length, A, 2 * math.pi * R, T_hot=T_c, T_cold=T_hot),
        Duct(seg["duct_right"].length + eng.right_duct.length, R),
    ]


def peer_end_velocity(segs, gas, omega: complex, T_c: float) -> complex:
    """U at the right end for p = 1 Pa, U = 0 at the closed left end (exp(+i omega t))."""
    p, U, T = 1.0 + 0j, 0j, T_c
    for s in segs:
        p, U, T = s.propagate(p, U, T, omega, gas)
    return complex(U)


def peer_eigenfrequency(eng, T_hot: float, f_guess: complex) -> complex:
    """Complex frequency f [Hz] (exp(+i omega t)) where U(end) = 0, by SciPy's secant."""
    from openthermoacoustics.gas.air import Air

    gas = Air(mean_pressure=eng.core.gas.p_mean)
    segs = peer_network(eng, T_hot)
    return so.newton(
        lambda f: peer_end_velocity(segs, gas, 2 * math.pi * f, eng.core.gas.T_cold), f_guess, tol=1e-9, maxiter=60
    )


def peer_onset(eng, ratio_max: float = 3.0, n_grid: int = 9) -> dict:
    """Onset temperature ratio and frequency of openthermoacoustics: Im f on a grid of
    T_hot / T_cold, then Brent's method on the first sign change."""
    T_c = eng.core.gas.T_cold
    cache = {}

    def f_at(ratio, guess):
        if ratio not in cache:
            cache[ratio] = peer_eigenfrequency(eng, ratio * T_c, guess)
        return cache[ratio]

    from openthermoacoustics.gas.air import Air

    c = Air(mean_pressure=eng.core.gas.p_mean).sound_speed(T_c)
    guess = c / (2 * eng.total_length()) + 0j
    ratios = np.linspace(1.0, ratio_max, n_grid)
    fs = []
    for r in ratios:
        guess = f_at(float(r), guess)
        fs.append(guess)
    gi = np.array([f.imag for f in fs])
    k = np.flatnonzero((gi[:-1] > 0) & (gi[1:] <= 0))
    if not k.size:
        return {"T_ratio": None, "f_Hz": None, "grid_ratio": ratios.tolist(), "grid_f_imag": gi.tolist()}
    k = int(k[0])
    r_on = so.brentq(lambda r: f_at(float(r), fs[k]).imag, ratios[k], ratios[k + 1], xtol=1e-10, rtol=1e-10)
    return {
        "T_ratio": float(r_on),
        "f_Hz": float(f_at(float(r_on), fs[k]).real),
        "grid_ratio": ratios.tolist(),
        "grid_f_imag": gi.tolist(),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="studies/out/onset_peer.json")
    args = ap.parse_args(argv)
    eng = load_engine(ENGINE)
    t0 = time.perf_counter()
    ours = onset(eng, Q_max=100.0, n_bracket=9, device="cpu")
    t_ours = time.perf_counter() - t0
    T_c = eng.core.gas.T_cold
    result = {
        "engine": ENGINE,
        "tawarp": {
            "Q_onset_W": ours.Q_onset[0],
            "f_onset_Hz": ours.f_onset[0],
            "T_hot_K": ours.T_hot[0],
            "T_ratio": ours.T_hot[0] / T_c,
            "seconds_one_prediction_cpu": t_ours,
        },
    }
    cold = eigenfrequencies(eng, 0.0, device="cpu")
    result["tawarp"]["isothermal_f_Hz"] = cold.frequency[0]
    result["tawarp"]["isothermal_growth_rate_1_per_s"] = cold.growth_rate[0]
    try:
        import openthermoacoustics as ota
    except ImportError as e:
        result["openthermoacoustics"] = {"available": False, "reason": str(e)}
    else:
        t0 = time.perf_counter()
        peer = peer_onset(eng)
        peer["seconds_one_prediction"] = time.perf_counter() - t0
        peer["version"] = getattr(ota, "__version__", "?")
        result["openthermoacoustics"] = peer
        f0 = peer_eigenfrequency(eng, T_c, cold.frequency[0] + 0j)
        peer["isothermal_f_Hz"] = f0.real
        peer["isothermal_growth_rate_1_per_s"] = -2 * math.pi * f0.imag
        result["isothermal_difference"] = {
            "f_relative": f0.real / cold.frequency[0] - 1,
            "growth_rate_relative": -2 * math.pi * f0.imag / cold.growth_rate[0] - 1,
        }
        if peer["T_ratio"] is not None:
            result["difference"] = {
                "T_ratio_relative": peer["T_ratio"] / result["tawarp"]["T_ratio"] - 1,
                "f_relative": peer["f_Hz"] / result["tawarp"]["f_onset_Hz"] - 1,
            }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2, default=float) + "\n")
    print(json.dumps({k: v for k, v in result.items()}, indent=1, default=float)[:3000])


if __name__ == "__main__":
    main()
