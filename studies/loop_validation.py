"""Validation of the loop on data the model did not make.

    python studies/loop_validation.py --cases 14 --device cpu --out studies/out/loop_validation
    python studies/loop_validation.py --cases 70 --seed0 70 --append --workers 16 --loop-workers 16 --out DIR   # in chunks
    nvidia-cuda-mps-control -d; python studies/loop_validation.py --cases 70 --device cuda --loop-workers 16 --out DIR
    python studies/loop_validation.py --cases 112 --device cuda --loop-workers 16 --together 7 --out DIR
    python studies/loop_validation.py --suite lab --cases 48 --loop-workers 16 --out studies/out/loop_validation_lab
    python studies/loop_validation.py --suite lab --split heldout --cases 48 --loop-workers 16 --out DIR   # rules frozen

Every case is a core T-matrix data set made by the independent NumPy oracle
(:mod:`tawarp.reference`: exact heat solution, DOP853 at rtol 1e-12, i.e. converged
resolution; never the Warp kernels) and given to :func:`tawarp.loop.run_loop` with a core
file that a user would have: the prior, 10-30 % off the truth (the lab suite: 10-20 %) on
every parameter of the paper's estimation (stack porosity, pore radius and tortuosity, the h
of every thermal segment; the hot exchanger's geometry is known hardware and stays exact,
and the ceramic's tortuosity is 1 as the paper fixes it).

A case (:func:`make_case`, a pure function of its seed):

* material: one of the four bundled cores; true stack geometry uniform over the paper's
  Table-1 intervals (value +- uncertainty), true h's over h_s ranges of Sect. 5.2
  (:data:`H_RANGES`), h_h 50-150, h_a 0.1-0.3 W/(m^2 K);
* 37 frequencies 40-400 Hz (ceramic 50-200 Hz); Q = 0, 20, 40 W (RVC 0, 9, 18 W);
* noise log-uniform in 0.1-1 %: complex Gaussian on each dimensionless coefficient
  (Tpp, Tpu/Zc, Tup*Zc, Tuu) with standard deviation ``noise`` times that coefficient's rms
  over the data set (a microphone noise floor, not a relative error that would make a near-zero
  coefficient infinitely precise); sigma columns in 3 of 4 cases;
* category, by seed (:data:`CATEGORIES`, cycled so that any run of 14 consecutive seeds covers
  all): ``clean`` (twice per cycle), ``effect:NAME`` for every effect of the library at a
  physically typical size (:data:`TYPICAL`), ``two`` (a pair of them, :data:`PAIRS`),
  ``outside`` (an effect outside the library, :func:`calibration_drift`), ``wrong_core``
  (data of another material fitted with this core; :func:`wrong_cores`);
* the library's ``wall_conduction`` is drawn as a real wall (:func:`_wall`, the lab suite's
  draw): lam_w A_w/S 0.2-1 W/(m K) behind the couplings h_w 100-500 W/(m^2 K) of the porous
  parts and 2.9-3.4 of the buffer tube's laminar gas, each thermal segment's
  ``wall_resistance`` = 1/h_w (:func:`wall_params`), which the reference solves as the wall's
  own temperature field (its two-field BVP); a wall in perfect contact with a laminar gas,
  the library field's ``wall_resistance`` 0, is no rig's.

The outside effect is a **frequency-dependent calibration drift**: every coefficient
multiplied by ``1 + (a + i b) (f - f_mid)/(f_max - f_min)`` with |a|, |b| in 3-5 %. It is a
property of the measurement chain (microphone sensitivities drifting across the band), not of
the core, so no core effect makes it; its mean over the band is zero, so a constant
calibration gain (the library's planned calibration effect) does not absorb it either.

Expected answer of a case (:func:`expected`): ``clean``: no claim; ``effect``/``two``: each
true effect is judged on the reference data with it alone (for a pair, computed apart and
given the case's own noise draw; :func:`effect_status`): *visible* when its own size (rms
difference of the noise-free data with and without it, docs/formats.md error) is at least
:data:`VISIBLE` x the noise floor and the base fit alone does not explain its data (chi^2 test
at 1 %, :func:`base_fits`; else *absorbed* by the base parameters); *invisible* below
:data:`INVISIBLE` x the floor; *marginal* between. A case with visible effects is right when
the loop accepts each of them, nothing that is not true, and the error after is <= 1.3 x the
noise floor (strict: each visible effect claimed alone; with groups: in an accepted group of
effects the loop cannot tell apart, every accepted group holding a true effect); a case whose
effects are all invisible is right with no claim; one absorbed and none visible: the rule of
absorbed effects below; only marginal ones: reported, not scored.
``outside`` and ``wrong_core``: flagged, i.e. the verdict one of "unexplained_residual" and
"wrong_model" (both say that nothing in the library explains the residual and locate it in
``unexplained_residual``; steps that reduce the misfit without explaining it may be listed
beside the verdict; the loop tells the two apart by the base fit's reduced chi^2 alone,
which says how large the misfit is, not what causes it).

**The lab suite** (``--suite lab``, :data:`LAB_CATEGORIES`): what a built rig adds to the
paper's core, made by the reference's own lab physics (:mod:`tawarp.reference_effects`, no
kernel code), each at a typical size (:data:`LAB`): a thermal contact resistance between
stack and hot exchanger (R_c 1e-4..1e-3 m^2 K/W); the tube wall as a second temperature
field (lam_w A_w/S 0.2-1 W/(m K), coupled by h_w 100-500 W/(m^2 K) in the porous parts and
2.9-3.4 in the buffer tube); an annular bypass gap around the stack (0.1-0.5 mm); a leak
(a 0.5-1 mm hole through a 1-2 mm wall into the room, mid-way along an end duct); a
gain/phase mismatch inside one microphone pair (2-5 %, 1-3 degrees; the far microphone of
the upstream or downstream pair, 0.1 and 0.2 m from the face); a porosity varying along the
stack (a = 0.1-0.3 end to end, limited so that phi <= 0.99); and buffer-tube convection
(the reference's nonlinear heat model, ``effect:convection``), beside clean data. The core
file is 10-20 % off (:data:`LAB_PRIOR_OFF`; ``--prior-off`` sets any range). The wall field
is the physical version of the library's ``wall_conduction``; the contact resistance, the
porosity gradient and the bypass gap are the reference's own versions (a jump in its heat
BVP; a continuous porosity law in its ODE and BVP; a slit 2-port in parallel with the stack's,
joined at its ends) of the library's ``contact_resistance``, ``porosity_gradient`` and
``bypass_gap``; convection is in the library: they are scored as those effects. The other two
(leak, microphone mismatch) are outside the library: visible, they must be flagged
(``unexplained_residual`` or ``wrong_model``; ``explained`` is wrong).

**Absorbed effects are scored, not skipped** (:func:`score`): an effect the base fit
explains (chi^2 at 1 %) must not be claimed as a false effect, and no case may be judged
``adequate`` while the fit sits more than :data:`TENSION` prior standard deviations from the
core file (:func:`tension`: the loop's own ``prior_tension`` z of the model it chose,
against its documented priors; for a report without priors :data:`PRIOR_SD` = 20 % of the
file's value). The summary adds the calibration of the loop's inclusion probabilities (of
the effects it claimed, how many are true; per bin of :data:`CALIBRATION_BINS` over every
report; ``OUT/calibration.png``).

**Held-out seeds** (``--split heldout``, seeds >= :data:`HELDOUT_SEED0`): never run while a
rule of the loop or of this study is being tuned; a tuning run refuses them.

The loop's answer goes through ONE adapter, :func:`loop_outcome`, which reads the report
contract of docs/loop.md (``accepted_effects``/``accepted_steps``, ``verdict``,
``inclusion_probabilities``, ``prior_tension``, ``parameters_after``, ...) and tolerates a
report without the newer keys.

Generation (the expensive part: one ODE integration per heated segment and frequency) runs
in ``--workers`` processes and is cached in ``OUT/cache/case_SEED_HASH.npz`` (HASH: the case
description, so a changed case is regenerated). The loops then run on ``--device`` in
``--loop-workers`` processes, on the CPU each with its share of the cores; processes that
share a GPU take turns on it unless NVIDIA's MPS daemon runs (docs/loop.md, Speed: on one
H100 host 16 processes ran 1.62 cases/s on the GPU under MPS, 0.24 without it, 0.62 on the
CPU's 16 cores); with ``--together N`` each process runs N loops at a time, the cases of one
core file together, their fits and launches batched (:func:`tawarp.fit.lockstep.run_together`;
a loop alone on a GPU host is bound by its host work); with ``--blocking-waits`` each loop
process's CUDA context waits for the GPU by blocking, not spinning, so that more processes
than cores can share the host (:func:`tawarp.distributed.wait_by_blocking`; docs/loop.md,
Speed, "Blocking waits"). Outputs, written atomically: ``OUT/loop_validation.json`` (every case and the
summary), ``OUT/loop_validation.md`` (the tables), ``OUT/confusion.png``, ``OUT/residual_ratio.png``,
``OUT/calibration.png``.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import hashlib
import itertools
import json
import math
import multiprocessing
import os
import signal
import sys
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from tawarp import reference
from tawarp.distributed import cores_shared, cuda_mps_running, require_blocking_waits
from tawarp.fit.lockstep import run_together
from tawarp.fit.problems import Families, fit_batch
from tawarp.io import atomic_path, write_json, write_text
from tawarp.loop import default_base_params, fit_base, library_for, run_loop
from tawarp.loop.report import DRIFT_P, drifting
from tawarp.loop.run import MAX_ITER, XTOL, refit_starts
from tawarp.measure import TMatrixKind
from tawarp.measure.files import TMatrixData
from tawarp.measure.synthetic import MATERIALS, PAPER_TABLE1
from tawarp.model.coefficients import denormalize, duct_impedance, normalize, rms_error
from tawarp.model.core import Core, load_core
from tawarp.model.effects import with_ambient_exchangers
from tawarp.model.forward import ForwardSettings, cpu_share
from tawarp.progress import progress_bar
from tawarp.reference_effects import LabEffects, lab_transfer_matrix

FREQS = {"ceramic": (50.0, 200.0)}  # Hz; others 40-400
N_FREQS = 37
HEAT = {"rvc_foam": (0.0, 9.0, 18.0)}  # W; others 0, 20, 40 (RVC <= 18 W: combustion)
#: true h_s ranges [W/(m^2 K)] (Sect. 5.2: ceramic >= 150, mesh ~ 50, RVC <= 10; NiCr not given)
H_RANGES = {"ceramic": (150.0, 250.0), "mesh": (35.0, 65.0), "nicr_foam": (20.0, 40.0), "rvc_foam": (4.0, 10.0)}
HOT_H, TBT_H = (50.0, 150.0), (0.1, 0.3)
NOISE = (1e-3, 1e-2)
SIGMA_FRACTION = 0.75
PRIOR_OFF = (0.10, 0.30)
#: the lab suite's core file: 10-20 % off every fitted parameter
LAB_PRIOR_OFF = (0.10, 0.20)
#: prior standard deviation, relative to the core file's value, with which the study measures how
#: far a fitted parameter has moved (the lab suite's core file is 10-20 % off: the truth lies
#: within one standard deviation); a fit more than TENSION of them away is in tension with it
PRIOR_SD, TENSION = 0.20, 3.0
#: seeds from here on are held out: run only once every rule of the loop and of this study is
#: frozen, never to tune one (``--split heldout``)
HELDOUT_SEED0 = 1000
#: visibility rule of :func:`expected`: effect size / noise floor
VISIBLE, INVISIBLE = 2.0, 0.5
#: the targets of docs/loop.md
TARGETS = {
    "right_effect": 0.95,
    "residual_ratio": 1.3,
    "clean_claims": 0.02,
    "outside_unexplained": 0.90,
    "wrong_core_flagged": 1.0,
    "outside_explained": 0.05,
    "claimed_true": 0.90,
    "adequate_in_tension": 0,
}
#: bins of the inclusion probabilities' calibration table; an effect is claimed at >= 0.95
CALIBRATION_BINS = (0.0, 0.05, 0.5, 0.95, 1.0)


def _u(rng, lo, hi):
    return float(rng.uniform(lo, hi))


def _signed(rng, lo, hi):
    return float(rng.choice((-1.0, 1.0)) * rng.uniform(lo, hi))


def _wall(rng, couplings=None) -> dict:
    """A tube wall as a temperature field of its own (:class:`tawarp.reference_effects.LabEffects`
    fields): stainless 0.5-1 mm thick on R = 16.7 mm, lam_w A_w/S = lam_w 2 t/R 0.2-1 W/(m K);
    coupled by h_w 100-500 W/(m^2 K) where the porous parts touch it (a gas film of ~0.1 mm) and
    2.9-3.4 in the buffer tube (laminar gas, Nu 3.7-4.4 over D = 33 mm). The couplings come
    from the generator ``couplings`` (default ``rng``)."""
    couplings = rng if couplings is None else couplings
    return {
        "wall_conductance": _u(rng, 0.2, 1.0),
        "wall_coupling_porous": _u(couplings, 100.0, 500.0),
        "wall_coupling_duct": _u(couplings, 2.9, 3.4),
    }


def wall_params(core: Core, wall: dict) -> dict:
    """The core fields of a :func:`_wall` draw: every thermal segment's ``wall_conductance`` and
    its ``wall_resistance`` 1/h_w (the porous parts' coupling or the ducts')."""
    out = {}
    for i in core.thermal_indices:
        s = core.segments[i]
        out[f"{s.name}.wall_conductance"] = wall["wall_conductance"]
        out[f"{s.name}.wall_resistance"] = 1.0 / wall["wall_coupling_porous" if s.is_porous else "wall_coupling_duct"]
    return out


#: Typical size of every library effect: a function rng -> {"params": {name: value}} or
#: {"ambient": geometry}, and why that size.
TYPICAL = {
    # reference planes placed to +-1-3 mm (microphone positions from a ruler)
    "plane_offsets": lambda rng: {
        "params": {
            "duct_left.length": 0.03 + _signed(rng, 1e-3, 3e-3),
            "duct_right.length": 0.03 + _signed(rng, 1e-3, 3e-3),
        }
    },
    # room temperature assumed, off by 3-6 K
    "T_cold": lambda rng: {"params": {"gas.T_cold": 293.15 + _signed(rng, 3.0, 6.0)}},
    # static pressure assumed 1 atm: weather and altitude give 2-4 %
    "p_mean": lambda rng: {"params": {"gas.p_mean": 101325.0 * (1.0 + _signed(rng, 0.02, 0.04))}},
    # JCA Lambda'/Lambda of real porous media: 1.3-2
    "thermal_radius_ratio": lambda rng: {"params": {"stack.thermal_radius_ratio": _u(rng, 1.3, 2.0)}},
    # conductivity of metals/ceramics with T: exponent 0.3-1 over 300-600 K
    "conductivity_T": lambda rng: {"params": {"stack.conductivity_exponent": _u(rng, 0.3, 1.0)}},
    # Rosseland 16 sigma T^3 / (3 beta), beta ~ 1e3 1/m at 300 K: 0.01-0.05 W/(m K)
    "radiation": lambda rng: {"params": {"stack.radiative_conductivity": _u(rng, 0.01, 0.05)}},
    # natural convection in a 10 cm tube: h_c ~ 1.3 / L^(1/4) ~ 1-3 W/(m^2 K^1.25)
    "convection": lambda rng: {"params": {"tbt.h_convection": _u(rng, 1.0, 3.0)}},
    # a conducting tube wall as a field of its own, behind the physical couplings of :func:`_wall`;
    # those from a child stream (spawning leaves the parent's stream where it is), so that the
    # case's draws after its effects (noise, sigma columns) are those of a wall in perfect contact
    "wall_conduction": lambda rng: {"wall": _wall(rng, rng.spawn(1)[0])},
    # ambient exchangers: 5-15 mm of fins or mesh, porosity 0.6-0.85, pore radius 0.3-1.2 mm
    "ambient_exchangers": lambda rng: {
        "ambient": {
            "length": _u(rng, 5e-3, 15e-3),
            "porosity": _u(rng, 0.6, 0.85),
            "pore_radius": _u(rng, 0.3e-3, 1.2e-3),
        }
    },
}
EFFECTS = tuple(TYPICAL)
#: pairs of effects at once: one geometric/ambient with one thermal, no pair known degenerate
PAIRS = (
    ("plane_offsets", "convection"),
    ("T_cold", "thermal_radius_ratio"),
    ("p_mean", "wall_conduction"),
    ("ambient_exchangers", "convection"),
    ("plane_offsets", "thermal_radius_ratio"),
)
CATEGORIES = ("clean",) + tuple(f"effect:{e}" for e in EFFECTS) + ("clean", "two", "outside", "wrong_core")


@dataclass(frozen=True)
class LabEffect:
    """A lab effect of the reference (:mod:`tawarp.reference_effects`): ``draw(rng, truth,
    core)`` its typical size as :class:`tawarp.reference_effects.LabEffects` fields, ``library``
    the loop's effect that models it (None: outside the library) and why that size."""

    draw: object
    library: str | None
    why: str


def _leak(rng, truth, core):
    # the middle of one of the two end ducts
    pos = core.positions()
    i = int(rng.choice([0, len(core.segments) - 1]))
    return {
        "leak_diameter": _u(rng, 0.5e-3, 1.0e-3),
        "leak_length": _u(rng, 1e-3, 2e-3),
        "leak_position": 0.5 * (pos[i] + pos[i + 1]),
    }


def _gradient(rng, truth, core):
    # the porosity must stay below 0.99 at the denser end: a foam of 0.97 allows 2 %
    a = _signed(rng, 0.1, 0.3)
    top = 2.0 * (0.99 / truth["stack.porosity"] - 1.0)
    return {"porosity_gradient": float(np.clip(a, -top, top))}


#: The lab effects of the lab suite, each at a physically typical size.
LAB = {
    "contact_resistance": LabEffect(
        lambda rng, truth, core: {"contact_resistance": _u(rng, 1e-4, 1e-3)},
        "contact_resistance",
        "stack pressed against the hot exchanger: contact conductance 1e3-1e4 W/(m^2 K), R_c 1e-4..1e-3 m^2 K/W",
    ),
    "wall_field": LabEffect(
        lambda rng, truth, core: _wall(rng),
        "wall_conduction",
        "stainless wall 0.5-1 mm (lam_w A_w/S 0.2-1 W/(m K)); h_w 100-500 W/(m^2 K) where the porous parts touch "
        "it, 2.9-3.4 in the buffer tube (laminar gas, Nu 3.7-4.4 over D = 33 mm)",
    ),
    "bypass_gap": LabEffect(
        lambda rng, truth, core: {"bypass_gap": _u(rng, 0.1e-3, 0.5e-3)},
        "bypass_gap",
        "stack cut or wound 0.1-0.5 mm under the tube's diameter",
    ),
    "leak": LabEffect(
        _leak, None, "an unsealed port of 0.5-1 mm diameter through a 1-2 mm wall into the room, mid-duct"
    ),
    "mic_mismatch": LabEffect(
        lambda rng, truth, core: {
            "mic_gain": 1.0 + _signed(rng, 0.02, 0.05),
            "mic_phase": math.radians(_signed(rng, 1.0, 3.0)),
            "mic_pair": str(rng.choice(["upstream", "downstream"])),
        },
        None,
        "the far microphone of one pair 2-5 % and 1-3 degrees off its partner (an uncalibrated pair; "
        "microphones 0.1 and 0.2 m from the face)",
    ),
    "porosity_gradient": LabEffect(
        _gradient,
        "porosity_gradient",
        "porosity varying linearly along the stack, a = 0.1-0.3 end to end (limited to phi <= 0.99)",
    ),
}
#: The lab suite: clean data, every lab effect, and buffer-tube convection (the reference's
#: nonlinear heat model; in the library) with the core file 10-20 % off.
LAB_CATEGORIES = ("clean",) + tuple(f"lab:{e}" for e in LAB) + ("effect:convection",)
SUITES = {"library": CATEGORIES, "lab": LAB_CATEGORIES}


@dataclass
class Case:
    """One validation case (everything needed to regenerate its data)."""

    seed: int
    category: str
    material: str  # the data's material
    core_material: str  # the core file the loop is given
    truth: dict  # true parameters (names of the core)
    prior: dict  # the core file's values of the fitted parameters
    effects: list  # true library effects (names)
    effect_truth: dict = field(default_factory=dict)  # per effect: its TYPICAL draw
    drift: list | None = None  # (a, b) of the outside calibration drift
    noise: float = 0.0
    with_sigma: bool = True
    freqs: list = field(default_factory=list)
    heat_inputs: list = field(default_factory=list)
    lab: dict = field(default_factory=dict)  # lab effect name -> its LabEffects fields (:data:`LAB`)

    def key(self) -> str:
        # a case without lab effects hashes as before the field existed: its cache stays valid
        d = {k: v for k, v in asdict(self).items() if k != "lab" or v}
        return hashlib.sha1(json.dumps(d, sort_keys=True).encode()).hexdigest()[:10]

    @property
    def held_out(self) -> bool:
        return self.seed >= HELDOUT_SEED0

    def true_effects(self) -> list[str]:
        """The library effects that are true in the data: the case's, and the library's name
        of an in-library lab effect."""
        return list(self.effects) + [LAB[e].library for e in self.lab if LAB[e].library]


def paper_names(material: str) -> list[str]:
    """The parameters of the paper's estimation: stack geometry (tortuosity fixed at 1 for the
    ceramic, as in the paper) and the h of every thermal segment."""
    geo = ["stack.porosity", "stack.pore_radius"] + ([] if material == "ceramic" else ["stack.tortuosity"])
    return geo + ["stack.h", "hot_hx.h", "tbt.h"]


def true_base(rng, material: str) -> dict:
    """True base parameters: Table 1 value +- its uncertainty, h's over :data:`H_RANGES`."""
    out = {}
    for name, (v, u) in PAPER_TABLE1[material].items():
        out[name] = v if u is None else _u(rng, v - u, v + u)
    out["stack.h"] = _u(rng, *H_RANGES[material])
    out["hot_hx.h"] = _u(rng, *HOT_H)
    out["tbt.h"] = _u(rng, *TBT_H)
    return out


def prior_of(rng, truth: dict, names: list[str], off_range: tuple = PRIOR_OFF) -> dict:
    """The user's core file: each parameter ``names`` off its truth by a fraction drawn in
    ``off_range``, the sign random but turned where it would leave the physical range
    (porosity <= 0.99, tortuosity >= 1)."""
    out = {}
    for name in names:
        v, off = truth[name], _signed(rng, *off_range)
        p = v * (1.0 + off)
        if (name.endswith("porosity") and p > 0.99) or (name.endswith("tortuosity") and p < 1.0):
            p = v * (1.0 - off)
        out[name] = p
    return out


def wrong_cores(material: str) -> list[str]:
    """The bundled cores that are a wrong core for ``material``'s data: another segment
    structure (lengths). The NiCr and RVC cores differ only in values the base fit estimates
    (stack geometry, h's) and in the solid conductivity, which the fitted h's absorb (seen:
    RVC data fitted with the NiCr core reach 1.06 x the noise floor): between them the other
    file is the right model with other values, not a wrong core."""
    lengths = lambda m: [s.length for s in load_core(m).segments]
    return [m for m in MATERIALS if lengths(m) != lengths(material)]


def make_case(
    seed: int,
    category: str | None = None,
    material: str | None = None,
    noise: float | None = None,
    n_freqs: int = N_FREQS,
    suite: str = "library",
    prior_off: tuple | None = None,
) -> Case:
    """The case of ``seed``: its category from the ``suite``'s categories (:data:`SUITES`,
    cycled), all else drawn from ``numpy.random.default_rng(seed)``. ``category``,
    ``material``, ``noise`` and ``n_freqs`` override (the test suite's reduced version); a
    "lab:" category is of the lab suite. ``prior_off``: the range of the core file's relative
    errors (default :data:`PRIOR_OFF`, the lab suite's :data:`LAB_PRIOR_OFF`)."""
    if suite not in SUITES:
        raise ValueError(f"suite = {suite!r}; expected one of {sorted(SUITES)}")
    rng = np.random.default_rng(seed)
    category = category or SUITES[suite][seed % len(SUITES[suite])]
    if category.startswith("lab:"):
        suite = "lab"
    if prior_off is None:
        prior_off = LAB_PRIOR_OFF if suite == "lab" else PRIOR_OFF
    drawn = str(rng.choice(MATERIALS))
    material = material or drawn
    core_material = material
    if category == "wrong_core":
        core_material = str(rng.choice(wrong_cores(material)))
    truth = true_base(rng, material)
    # the prior is the user's file of the core they think they have: for the wrong core, that
    # core's own nominal values, off by the same range
    nominal = truth if core_material == material else true_base(rng, core_material)
    prior = prior_of(rng, nominal, paper_names(core_material), prior_off)
    effects = {"two": list(PAIRS[int(rng.integers(len(PAIRS)))])}.get(category, [])
    if category.startswith("effect:"):
        effects = [category.split(":", 1)[1]]
    effect_truth = {e: TYPICAL[e](rng) for e in effects}
    lab = {}
    if category.startswith("lab:"):
        name = category.split(":", 1)[1]
        lab = {name: LAB[name].draw(rng, truth, load_core(material))}
    drift = [_signed(rng, 0.03, 0.05), _signed(rng, 0.03, 0.05)] if category == "outside" else None
    lo, hi = FREQS.get(material, (40.0, 400.0))
    drawn_noise = float(math.exp(rng.uniform(*np.log(NOISE))))
    return Case(
        seed,
        category,
        material,
        core_material,
        truth,
        prior,
        effects,
        effect_truth,
        drift,
        noise=drawn_noise if noise is None else float(noise),
        with_sigma=bool(rng.random() < SIGMA_FRACTION),
        freqs=[float(f) for f in np.linspace(lo, hi, n_freqs)],
        heat_inputs=list(HEAT.get(material, (0.0, 20.0, 40.0))),
        lab=lab,
    )


def true_core(case: Case, effects: list[str] | None = None) -> Core:
    """The core that makes the data: the material's with the true parameters and the true
    ``effects`` (default: all of the case's; [] for none, one name for it alone)."""
    core = load_core(case.material).replace(**case.truth)
    for draw in (case.effect_truth[e] for e in (case.effects if effects is None else effects)):
        if "params" in draw:
            core = core.replace(**draw["params"])
        if "wall" in draw:
            core = core.replace(**wall_params(core, draw["wall"]))
        if "ambient" in draw:
            core = with_ambient_exchangers(core, **draw["ambient"])
    return core


def calibration_drift(freqs: np.ndarray, a: float, b: float) -> np.ndarray:
    """The outside effect's factor ``1 + (a + i b)(f - f_mid)/(f_max - f_min)`` per frequency."""
    f = np.asarray(freqs, dtype=float)
    return 1.0 + (a + 1j * b) * (f - 0.5 * (f.min() + f.max())) / (f.max() - f.min())


def lab_effects(case: Case) -> LabEffects | None:
    """The case's lab effects as one :class:`tawarp.reference_effects.LabEffects`, None without."""
    return LabEffects(**{k: v for fields in case.lab.values() for k, v in fields.items()}) if case.lab else None


def _clean_Y(core: Core, case: Case, Zc: float, lab: LabEffects | None = None) -> np.ndarray:
    """Noise-free dimensionless coefficients (nQ, m, 4) from the reference, with the lab
    effects ``lab`` (:func:`tawarp.reference_effects.lab_transfer_matrix`) when given."""
    f = np.asarray(case.freqs)
    T = (
        (lambda q: reference.transfer_matrix(core, f, q))
        if lab is None
        else (lambda q: lab_transfer_matrix(core, lab, f, q))
    )
    return np.stack([normalize(T(q), Zc).reshape(f.size, 4) for q in case.heat_inputs])


def array_keys(case: Case) -> list[str]:
    """The case's arrays (:func:`generate`): raw noisy T, sigma and the noise-free
    dimensionless data; for effect cases the data without the effects (visibility); for
    several effects each effect's alone (``Y_alone_NAME``: its own visibility and whether
    the base fit absorbs it, :func:`effect_status`)."""
    keys = ["T", "sigma", "Y_clean"] + (["Y_without"] if case.effects or case.lab else [])
    return keys + ([f"Y_alone_{e}" for e in case.effects] if len(case.effects) > 1 else [])


def rig_Zc(case: Case) -> float:
    """The rig's normalisation of the case's data: the duct impedance of the nominal core."""
    return duct_impedance(load_core(case.material))


def generate(case: Case, keys: list[str] | None = None) -> dict:
    """The arrays ``keys`` (default all, :func:`array_keys`) of the case; T, sigma and
    Y_clean come together. The noise is seeded by the case, so every call draws the same."""
    keys = array_keys(case) if keys is None else keys
    Zc = rig_Zc(case)
    out = {}
    if {"T", "sigma", "Y_clean"} & set(keys):
        Y = _clean_Y(true_core(case), case, Zc, lab_effects(case))
        if case.drift:
            Y = Y * calibration_drift(case.freqs, *case.drift)[None, :, None]
        rng = np.random.default_rng([case.seed, 1])
        sd = case.noise * np.sqrt(np.mean(np.abs(Y) ** 2, axis=(0, 1))) / math.sqrt(2.0)  # per coefficient, per part
        sd = np.broadcast_to(sd, Y.shape)
        Yn = Y + sd * (rng.standard_normal(Y.shape) + 1j * rng.standard_normal(Y.shape))
        out.update(
            T=denormalize(Yn, Zc).reshape(-1, 2, 2),
            sigma=np.abs(denormalize(sd.astype(complex), Zc)).reshape(-1, 2, 2),
            Y_clean=Y,
        )
    if "Y_without" in keys:
        out["Y_without"] = _clean_Y(true_core(case, []), case, Zc)
    for e in case.effects:
        if f"Y_alone_{e}" in keys:
            out[f"Y_alone_{e}"] = _clean_Y(true_core(case, [e]), case, Zc)
    return out


def load_or_generate(case: Case, cache: Path) -> dict:
    """The case's arrays from ``cache`` (``case_SEED_HASH.npz``), the missing ones generated
    and added to the file (a cache of an earlier version of the study is completed, not
    remade)."""
    path = cache / f"case_{case.seed}_{case.key()}.npz"
    arrays = {}
    if path.exists():
        with np.load(path) as z:
            arrays = dict(z)
    missing = [k for k in array_keys(case) if k not in arrays]
    if missing:
        arrays.update(generate(case, missing))
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)
    return arrays


def measurement(case: Case, arrays: dict) -> TMatrixData:
    nf, nq = len(case.freqs), len(case.heat_inputs)
    sigma = arrays["sigma"] if case.with_sigma else None
    meta = {
        "generator": "studies/loop_validation.py (tawarp.reference)",
        "seed": str(case.seed),
        "noise": repr(case.noise),
    }
    return TMatrixData(
        np.repeat(case.heat_inputs, nf),
        np.tile(case.freqs, nq),
        arrays["T"],
        sigma,
        meta,
        f"validation case {case.seed}",
    )


def step_members(step) -> list[str]:
    """The effects of one accepted step of the report: a list of names, a name, a group
    written "a+b", or "one of {a, b} (...)"."""
    if isinstance(step, (list, tuple)):
        return [str(e) for e in step]
    if "{" in step:
        return [e.strip() for e in step[step.index("{") + 1 : step.index("}")].split(",")]
    return [e.strip() for e in step.split("+")]


def loop_outcome(report: dict) -> dict:
    """THE adapter from the loop's report (docs/loop.md, the report contract) to what the
    study scores: ``accepted_effects`` (claimed alone), ``accepted_groups`` (every accepted
    step's effects: one, or a group the data cannot tell apart; from ``accepted_steps`` when
    the report has no ``accepted_groups``), ``verdict``, ``indistinguishable`` (groups),
    ``error_before``, ``error_after``, ``noise_floor`` (from the goodness of fit where the
    data carry no sigma and the floor is estimated), ``inclusion_probabilities`` {effect:
    probability}, ``prior_tension`` [{"parameter", "z"}] and ``parameters_after`` {name:
    value}; a report without the last three gives them empty."""
    gof = report.get("goodness_of_fit_before") or {}
    groups = report.get("accepted_groups")
    if groups is None:
        groups = [step_members(s) for s in report.get("accepted_steps") or []]
    groups = [list(g) for g in groups]
    accepted = report.get("accepted_effects")
    after = report.get("parameters_after") or {}
    chosen = "+".join(report.get("best_model") or []) or "base"
    return {
        "error_before": report["error_before"],
        "error_after": report["error_after"],
        "noise_floor": report.get("noise_floor") or gof.get("noise_floor"),
        "accepted_effects": list(accepted if accepted is not None else [g[0] for g in groups if len(g) == 1]),
        "accepted_groups": groups,
        "verdict": report["verdict"],
        "indistinguishable": [step_members(g) for g in report.get("indistinguishable") or []],
        "inclusion_probabilities": {str(k): float(v) for k, v in (report.get("inclusion_probabilities") or {}).items()},
        # the tension of the model the loop chose (the report also names its rivals')
        "prior_tension": [
            {"parameter": t["parameter"], "z": float(t["z"])}
            for t in report.get("prior_tension") or []
            if t.get("model", chosen) == chosen
        ],
        "parameters_after": {k: float(v["value"] if isinstance(v, dict) else v) for k, v in after.items()},
        "has_priors": "prior_tension" in report,
    }


#: Verdicts that flag a residual nothing in the library explains.
FLAGGED = ("unexplained_residual", "wrong_model")


def base_fits(ratio_before: float, n: int) -> bool:
    """True when the base fit alone passes a chi^2 test at 1 %: reduced chi^2 ~ (error before /
    noise floor)^2 <= 1 + 2.33 sqrt(2 / n) for n real residuals (normal approximation)."""
    return ratio_before**2 <= 1.0 + 2.33 * math.sqrt(2.0 / n)


def effect_status(visibility: float, ratio_before: float, n: int) -> str:
    """One true effect judged on the data with it alone (module docstring): ``invisible``
    (< :data:`INVISIBLE` noise floors, noise-free), ``marginal`` (below :data:`VISIBLE`),
    ``absorbed`` (visible, but the base fit alone explains the data with it, :func:`base_fits`:
    no method can attribute it from such data), else ``visible``."""
    if visibility < INVISIBLE:
        return "invisible"
    if visibility < VISIBLE:
        return "marginal"
    return "absorbed" if base_fits(ratio_before, n) else "visible"


def tension(case: Case, outcome: dict) -> float:
    """How far the loop's fit sits from the core file, in prior standard deviations: the
    largest z of the loop's own ``prior_tension`` for the model it chose (its documented
    priors, docs/priors.md); for a report without priors, the study's own measure
    |after - prior| / (:data:`PRIOR_SD` |prior|) over the core file's fitted parameters
    (:func:`paper_names`); 0 when the report gives neither."""
    if outcome.get("has_priors"):
        return float(max((abs(t["z"]) for t in outcome.get("prior_tension") or []), default=0.0))
    after = outcome.get("parameters_after") or {}
    own = [abs(after[k] - v) / (PRIOR_SD * abs(v)) for k, v in case.prior.items() if k in after and v]
    return float(max(own, default=0.0))


def expected(case: Case, status: dict) -> dict:
    """What a right answer is (module docstring): {"label", "effects" (the effects a right
    answer must accept: the visible ones), "verdict", "scored"}. ``status``: per true effect
    its :func:`effect_status`. With effects, the case is scored against its visible effects
    (others of the case may be accepted too: they are true); with none visible but one
    absorbed, by the rule of absorbed effects (verdict "absorbed": no false claim, and not
    ``adequate`` while a parameter sits > :data:`TENSION` prior standard deviations away);
    with all invisible, no claim; marginal ones are reported, not scored. A lab effect
    outside the library (:data:`LAB`) that is visible must be flagged, like ``outside``."""
    if case.category == "clean":
        return {"label": "clean", "effects": [], "verdict": "adequate", "scored": True}
    if case.category == "outside":
        return {"label": "outside", "effects": [], "verdict": "unexplained_residual", "scored": True}
    if case.category == "wrong_core":
        # scored unless the data cannot show it (:func:`wrong_core_visibility` below
        # INVISIBLE; stricter than for an effect: a marginal wrong core must be flagged too)
        st = status.get("wrong_core", "visible")
        return {
            "label": "wrong_core" + (" (invisible)" if st == "invisible" else ""),
            "effects": [],
            "verdict": "wrong_model",
            "scored": st != "invisible",
        }
    names = list(case.effects) + list(case.lab)
    label = "+".join(
        ("lab:" if e in case.lab else "") + e + ("" if status[e] == "visible" else f" ({status[e]})") for e in names
    )
    library = {e: LAB[e].library if e in case.lab else e for e in names}
    visible = [e for e in names if status[e] == "visible"]
    if any(library[e] is None for e in visible):
        return {"label": label, "effects": [], "verdict": "unexplained_residual", "scored": True}
    if visible:
        return {"label": label, "effects": sorted(library[e] for e in visible), "verdict": "explained", "scored": True}
    if any(st == "absorbed" for st in status.values()):
        return {"label": label, "effects": [], "verdict": "absorbed", "scored": True}
    if all(st == "invisible" for st in status.values()):
        return {"label": label, "effects": [], "verdict": "adequate", "scored": True}
    return {"label": label, "effects": [], "verdict": "explained", "scored": False}


def _interrupt_ends_quietly() -> None:
    """A worker process's Ctrl-C ends it as SystemExit does, its files closed whole and no
    traceback of its own (the study's process says what was kept)."""
    signal.signal(signal.SIGINT, _end)


def _end(signum, frame):
    raise SystemExit(130)


def _loop_worker_start(device: str | None) -> None:
    """A loop process's start: :func:`_interrupt_ends_quietly`, and where ``device`` is
    given (``--blocking-waits``) its CUDA context there waits by blocking."""
    _interrupt_ends_quietly()
    if device is not None:
        require_blocking_waits(device)


class StudyInterrupted(Exception):
    """Ctrl-C in a phase of the study; the message says what it kept."""


@contextlib.contextmanager
def _kept_on_interrupt(kept):
    """A Ctrl-C inside becomes :class:`StudyInterrupted` with ``kept()``, what the phase has
    written (asked when it happens: the phase's records so far)."""
    try:
        yield
    except KeyboardInterrupt:
        raise StudyInterrupted(kept()) from None


def run_case(
    case: Case,
    arrays: dict,
    device: str = "cpu",
    base: str = "loop",
    cells: int | None = None,
    cpu_threads: int | None = None,
) -> dict:
    """The loop on one case; the record of the study (JSON-ready). ``base``: "loop" (its
    default parameters) or "paper" (:func:`paper_names`); ``cells``: fixed cells of the
    forward model (default: the package's adaptive setting); ``cpu_threads``: the threads a
    CPU launch splits over (default: every core; a process's share of them where several
    run loops)."""
    core = load_core(case.core_material).replace(**case.prior)
    settings = ForwardSettings(device=device, cells=cells, cpu_threads=cpu_threads)
    prob = TMatrixKind(measurement(case, arrays), core, settings)
    floor = noise_floor(arrays, rig_Zc(case))
    names = paper_names(case.core_material) if base == "paper" else None
    t0 = time.perf_counter()
    report = run_loop(prob, default_base_params(prob, names) if names else None)
    wall = time.perf_counter() - t0
    got = loop_outcome(report)
    present = list(case.effects) + list(case.lab)
    rec = {
        "seed": case.seed,
        "category": case.category,
        "material": case.material,
        "core": case.core_material,
        "noise": case.noise,
        "with_sigma": case.with_sigma,
        "effects": case.effects,
        "visibility": (float(rms_error(arrays["Y_clean"], arrays["Y_without"])) / floor) if present else None,
        "outcome": got,
        "noise_floor_true": floor,
        "ratio_after": got["error_after"] / floor,
        "ratio_before": got["error_before"] / floor,
        "wall_s": wall,
        # the h's of the final model that change with the heat input (p < DRIFT_P)
        "drifting": drifting(report.drift[1]) if report.drift else {},
        "case": asdict(case),
    }
    if case.category == "wrong_core":
        rec["visibility"] = wrong_core_visibility(case, arrays, core, settings, names)
        rec["per_effect"] = {"wrong_core": {"visibility": rec["visibility"], "ratio_before": rec["ratio_before"]}}
    else:
        rec["per_effect"] = (
            {present[0]: {"visibility": rec["visibility"], "ratio_before": rec["ratio_before"]}}
            if len(present) == 1
            else {e: effect_alone(case, arrays, e, core, settings, names) for e in case.effects}
        )
    return score(rec)


def run_cases(cases: list[Case], arrays: list[dict], **kw) -> list[dict]:
    """:func:`run_case` of each of ``cases`` (its options ``kw``), their loops run together:
    every fit and prediction of theirs batched with the others'
    (:func:`tawarp.fit.lockstep.run_together`; each loop decides as alone, to the fits'
    stopping rules)."""
    got = run_together([functools.partial(run_case, c, arr, **kw) for c, arr in zip(cases, arrays)], Families())
    for case, g in zip(cases, got):
        if isinstance(g, Exception):
            g.add_note(f"in the case of seed {case.seed}")
            raise g
    return got


def noise_floor(arrays: dict, Zc: float) -> float:
    """The noise floor of the case's data, whether or not the file carries sigma (the
    definition of MeasurementKind.noise_floor: docs/formats.md error of data off by the noise):
    the yardstick of every ratio of the study."""
    Yn = normalize(arrays["T"], Zc)
    s = arrays["sigma"] * np.array([[1.0, 1.0 / Zc], [Zc, 1.0]])
    return float(np.sqrt(np.mean(2 * s**2) / np.mean(np.abs(Yn) ** 2)))


def effect_alone(
    case: Case, arrays: dict, effect: str, core: Core, settings: ForwardSettings, names: list[str] | None
) -> dict:
    """One effect of a case with several, judged on its own data: the reference data with that
    effect alone plus the case's own noise draw. ``visibility``: its noise-free size in noise
    floors; ``ratio_before``: the loop's base fit on those data (error / noise floor), for
    :func:`effect_status`."""
    Zc = rig_Zc(case)
    noise = normalize(arrays["T"], Zc).reshape(arrays["Y_clean"].shape) - arrays["Y_clean"]
    alone = arrays[f"Y_alone_{effect}"]
    own = dict(arrays, T=denormalize(alone + noise, Zc).reshape(-1, 2, 2))
    floor = noise_floor(own, Zc)
    prob = TMatrixKind(measurement(case, own), core, settings)
    base = fit_base(prob, default_base_params(prob, names))
    return {
        "visibility": float(rms_error(alone, arrays["Y_without"])) / floor,
        "ratio_before": float(base.rms_error[0]) / floor,
    }


def wrong_core_visibility(
    case: Case, arrays: dict, core: Core, settings: ForwardSettings, names: list[str] | None
) -> float:
    """How far the data of a wrong-core case lie from what the loop can make of the core
    file, in noise floors: the smallest misfit (docs/formats.md error) to the noise-free data of
    the base fit alone, with each library effect (from every one of its refit starts, the
    base part at the base solution and at the core file's values, as the loop's refits), and
    with each pair of them (the loop compares sets of up to :data:`tawarp.loop.run.MAX_EFFECTS`; a pair
    from the base solution and every pair of the two effects' refit starts). Below
    :data:`INVISIBLE` (:func:`effect_status`) the core file with library effects makes these
    data to a fraction of the noise, so that no method can flag the core from them, and the
    case is not scored; marginal ones are (ceramic data fitted with the NiCr core and plane
    offsets came within 0.15 floors at 0.8 % noise; the same case at 0.1 % noise is flagged,
    tests/test_loop_validation.py::test_wrong_core_flagged_when_the_data_can_show_it)."""
    Zc = rig_Zc(case)
    clean = dict(arrays, T=denormalize(arrays["Y_clean"], Zc).reshape(-1, 2, 2))
    prob = TMatrixKind(measurement(case, clean), core, settings)
    params = default_base_params(prob, names)
    base = fit_base(prob, params)
    at_core = np.zeros_like(base.x[0])
    lib = library_for(prob)
    specs = [
        (params + list(e.params), e if e.transform is not None else None, np.concatenate([x, start]))
        for e in lib
        for start in refit_starts(e)
        for x in (base.x[0], at_core)
    ]
    # two structural effects do not combine (nor does the loop combine them)
    specs += [
        (
            params + list(a.params) + list(b.params),
            a if a.transform is not None else b if b.transform is not None else None,
            np.concatenate([base.x[0], sa, sb]),
        )
        for i, a in enumerate(lib)
        for b in lib[i + 1 :]
        if a.transform is None or b.transform is None
        for sa in refit_starts(a)
        for sb in refit_starts(b)
    ]
    fits = fit_batch(prob, specs, max_iter=MAX_ITER, xtol=XTOL)
    best = min([float(base.rms_error[0])] + [float(f.rms_error[0]) for f in fits])
    return best / noise_floor(arrays, Zc)


def score(rec: dict) -> dict:
    """``rec`` with its expected answer (:func:`expected`, each true effect judged by
    :func:`effect_status` on its own data), ``right`` (strict: every visible effect claimed
    alone, nothing claimed that is not true, error after <= 1.3 x the floor),
    ``right_group`` (the same with the loop's groups of effects it cannot tell apart: every
    visible effect in an accepted step, every accepted step containing a true effect),
    ``named`` (every visible effect accepted or named in an indistinguishable group) and
    ``tension`` (:func:`tension`). Whatever the case, ``adequate`` with the fit more than
    :data:`TENSION` prior standard deviations from the core file is wrong: an effect absorbed
    by moving a base parameter is never scored as nothing to report."""
    case = Case(**rec["case"])
    n = 2 * 4 * len(case.freqs) * len(case.heat_inputs)
    status = {e: effect_status(v["visibility"], v["ratio_before"], n) for e, v in rec["per_effect"].items()}
    exp = expected(case, status)
    got = rec["outcome"]
    steps = got["accepted_groups"]
    tens = tension(case, got)
    calm = not (got["verdict"] == "adequate" and tens > TENSION)
    true = set(case.true_effects())
    if exp["verdict"] in FLAGGED:
        # flagged: the verdict says the library does not explain the data (steps that only
        # reduce the misfit may be listed beside it)
        right = right_group = got["verdict"] in FLAGGED
    elif exp["verdict"] == "absorbed":
        # no method can attribute it, but none may claim a false effect or call the fit
        # adequate while a parameter has moved far from the core file to absorb it
        right = all(set(g) <= true for g in steps) and calm
        right_group = all(set(g) & true for g in steps) and calm
    elif exp["effects"]:
        at_floor = rec["ratio_after"] <= TARGETS["residual_ratio"]
        right = (
            set(exp["effects"]) <= set(got["accepted_effects"])
            and all(set(g) <= true for g in steps)
            and at_floor
            and calm
        )
        right_group = (
            all(any(e in g for g in steps) for e in exp["effects"])
            and all(set(g) & true for g in steps)
            and at_floor
            and calm
        )
    else:  # clean or invisible effects: nothing claimed and the base fit judged adequate
        right = right_group = not steps and got["verdict"] == "adequate" and calm
    named = bool(exp["effects"]) and all(any(e in g for g in steps + got["indistinguishable"]) for e in exp["effects"])
    return dict(
        rec, status=status, expected=exp, right=bool(right), right_group=bool(right_group), named=named, tension=tens
    )


def outcome_label(rec: dict) -> str:
    """The loop's answer as one column of the confusion matrix: its accepted steps (a group
    of effects it cannot tell apart as "A|B"), or its verdict when none; a flagging verdict
    beside steps is appended ("plane_offsets, unexplained_residual"), so that a flagged
    case is never read as a claim; ``adequate`` with the fit more than :data:`TENSION` prior
    standard deviations from the core file reads "adequate, in tension"."""
    steps = rec["outcome"]["accepted_groups"]
    verdict = rec["outcome"]["verdict"]
    if not steps:
        return "adequate, in tension" if verdict == "adequate" and rec.get("tension", 0.0) > TENSION else verdict
    label = "+".join(sorted("|".join(g) for g in steps))
    return f"{label}, {verdict}" if verdict in FLAGGED else label


def summarize(records: list[dict], by_split: bool = True) -> dict:
    """Confusion matrix and the rates of the targets; with the tuning and held-out splits
    both present (``by_split``), the same for each apart under ``by_split``."""

    def rate(sel, key="right"):
        sel = list(sel)
        return {
            "n": len(sel),
            "k": int(sum(r[key] for r in sel)),
            "rate": (sum(r[key] for r in sel) / len(sel)) if sel else None,
        }

    rows = sorted({r["expected"]["label"] for r in records})
    cols = sorted({outcome_label(r) for r in records})
    confusion = {
        a: {b: sum(1 for r in records if r["expected"]["label"] == a and outcome_label(r) == b) for b in cols}
        for a in rows
    }

    def lab_library(r):
        return LAB[r["category"].split(":", 1)[1]].library if r["category"].startswith("lab:") else None

    eff = [r for r in records if r["category"].startswith("effect:") or r["category"] == "two" or lab_library(r)]
    visible = [r for r in eff if r["expected"]["scored"] and r["expected"]["effects"]]
    clean = [r for r in records if r["category"] == "clean"]
    outside_lab = [r for r in records if r["category"].startswith("lab:") and not lab_library(r)]
    absorbed = [r for r in records if r["expected"]["verdict"] == "absorbed"]
    walls = [r["wall_s"] for r in records]
    return {
        "n_cases": len(records),
        "held_out_cases": sum(1 for r in records if r["seed"] >= HELDOUT_SEED0),
        "right_effect": rate(visible),
        "right_effect_single": rate(r for r in visible if r["category"] != "two"),
        "right_effect_two": rate(r for r in visible if r["category"] == "two"),
        "right_effect_group": rate(visible, "right_group"),
        "right_effect_group_single": rate((r for r in visible if r["category"] != "two"), "right_group"),
        "right_effect_group_two": rate((r for r in visible if r["category"] == "two"), "right_group"),
        "named_incl_indistinguishable": rate(visible, "named"),
        "invisible_no_claim": rate(
            r for r in records if r["category"] != "clean" and r["expected"]["verdict"] == "adequate"
        ),
        "marginal_cases": sum(1 for r in records if not r["expected"]["scored"]),
        "absorbed_right": rate(absorbed),
        "adequate_in_tension": sum(
            1 for r in records if r["outcome"]["verdict"] == "adequate" and r.get("tension", 0.0) > TENSION
        ),
        "outside_lab_flagged": rate(r for r in outside_lab if r["expected"]["verdict"] in FLAGGED),
        "outside_lab_explained": rate(
            (
                {"explained": r["outcome"]["verdict"] == "explained"}
                for r in outside_lab
                if r["expected"]["scored"] and r["expected"]["verdict"] != "adequate"
            ),
            "explained",
        ),
        "clean_claims": rate(({"claim": bool(r["outcome"]["accepted_groups"])} for r in clean), "claim"),
        "clean_not_adequate": rate(({"flag": r["outcome"]["verdict"] != "adequate"} for r in clean), "flag"),
        "outside_unexplained": rate(r for r in records if r["category"] == "outside"),
        "wrong_core_flagged": rate(r for r in records if r["category"] == "wrong_core" and r["expected"]["scored"]),
        "wrong_core_flagged_all": rate(r for r in records if r["category"] == "wrong_core"),
        "ratio_after_visible_median": float(np.median([r["ratio_after"] for r in visible])) if visible else None,
        "confusion": confusion,
        "drifting": {
            c: rate(({"flag": bool(r["drifting"])} for r in records if r["category"] == c and "drifting" in r), "flag")
            | {
                "by_verdict": dict(
                    Counter(r["outcome"]["verdict"] for r in records if r["category"] == c and r.get("drifting"))
                )
            }
            for c in sorted({r["category"] for r in records if "drifting" in r})
        },
        "calibration": calibration(records),
        "loop_wall_s": {"mean": float(np.mean(walls)), "median": float(np.median(walls)), "max": float(np.max(walls))},
        "targets": TARGETS,
    } | (
        {
            "by_split": {
                "tuning": summarize([r for r in records if r["seed"] < HELDOUT_SEED0], False),
                "heldout": summarize([r for r in records if r["seed"] >= HELDOUT_SEED0], False),
            }
        }
        if by_split and 0 < sum(r["seed"] >= HELDOUT_SEED0 for r in records) < len(records)
        else {}
    )


def calibration(records: list[dict]) -> dict:
    """Calibration of the loop's inclusion probabilities over ``records``: per bin of
    :data:`CALIBRATION_BINS`, how many (effect, case) probabilities fall in it, their mean
    and the fraction of those effects that are true in the case (:meth:`Case.true_effects`;
    nothing is true in clean, outside and wrong-core data); ``claimed``: of the effects at
    >= 0.95 that the loop claimed (alone: its verdict passed the checks), how many are true;
    ``groups``: of the accepted steps, how many hold a true effect. The bins hold every case's
    probabilities, those of reports whose verdict says the library does not explain the data
    too (there the probabilities are conditional on a library that cannot make the data, and
    nothing is claimed)."""
    pairs, groups, claimed = [], [], []
    for r in records:
        true = set(Case(**r["case"]).true_effects())
        pairs += [(p, e in true) for e, p in (r["outcome"].get("inclusion_probabilities") or {}).items()]
        groups += [bool(set(g) & true) for g in r["outcome"]["accepted_groups"]]
        claimed += [e in true for e in r["outcome"]["accepted_effects"]]
    bins = []
    edges = CALIBRATION_BINS
    for lo, hi in itertools.pairwise(edges):
        # the last bin closed above: a probability summed from the models' can round past 1
        sel = [(p, t) for p, t in pairs if lo <= p < hi or (hi == edges[-1] and p >= hi)]
        bins.append(
            {
                "low": lo,
                "high": hi,
                "n": len(sel),
                "true": sum(t for _, t in sel),
                "mean_probability": float(np.mean([p for p, _ in sel])) if sel else None,
                "fraction_true": (sum(t for _, t in sel) / len(sel)) if sel else None,
            }
        )
    return {
        "bins": bins,
        "claimed": {"n": len(claimed), "k": sum(claimed), "rate": (sum(claimed) / len(claimed)) if claimed else None},
        "groups": {"n": len(groups), "k": sum(groups), "rate": (sum(groups) / len(groups)) if groups else None},
    }


def _fmt_rate(d: dict) -> str:
    return "-" if not d["n"] else f"{d['k']}/{d['n']} ({100 * d['rate']:.0f} %)"


def markdown(summary: dict, records: list[dict], meta: dict) -> str:
    s = summary
    seeds = [r["seed"] for r in records]
    # an interrupted run's file records its cases alone (meta {"partial": true})
    run = (
        f"base `{meta['base']}`, device {meta['device']}; last run `{meta['command']}`"
        if "command" in meta
        else "the cases an interrupted run finished"
    )
    lines = [
        f"Validation of the loop on data made by `tawarp.reference` ({s['n_cases']} cases, seeds "
        f"{min(seeds)}-{max(seeds)}, {s['held_out_cases']} of them held out (seeds >= {HELDOUT_SEED0}), "
        f"{run}).",
        "",
        "| measure | result | target |",
        "| --- | --- | --- |",
        f"| right effect(s), error after <= 1.3 x noise floor (visible effects; strict: each named alone) | "
        f"{_fmt_rate(s['right_effect'])} | >= 95 % |",
        f"| ... one effect | {_fmt_rate(s['right_effect_single'])} | |",
        f"| ... two effects (scored against their visible, non-absorbed effects) | {_fmt_rate(s['right_effect_two'])} | |",
        f"| right effect(s), a group of indistinguishable effects counting when it contains the true one | "
        f"{_fmt_rate(s['right_effect_group'])} | >= 95 % |",
        f"| ... one effect | {_fmt_rate(s['right_effect_group_single'])} | |",
        f"| ... two effects | {_fmt_rate(s['right_effect_group_two'])} | |",
        f"| true effect(s) accepted or named as indistinguishable | {_fmt_rate(s['named_incl_indistinguishable'])} | |",
        f"| invisible effect (< {INVISIBLE:g} x floor): no claim | {_fmt_rate(s['invisible_no_claim'])} | |",
        f"| cases not scored (marginal visibility) | {s['marginal_cases']} | |",
        f"| effect absorbed by the base fit: no false claim, not `adequate` with a parameter > {TENSION:g} prior "
        f"sd ({100 * PRIOR_SD:g} % of the core file's value) away | {_fmt_rate(s['absorbed_right'])} | |",
        f"| any case `adequate` with a parameter > {TENSION:g} prior sd away | {s['adequate_in_tension']} | 0 |",
        f"| lab effect outside the library, visible: flagged | {_fmt_rate(s['outside_lab_flagged'])} | |",
        f"| lab effect outside the library, visible or absorbed: `explained` | "
        f"{_fmt_rate(s['outside_lab_explained'])} | <= 5 % |",
        f"| effects claimed (inclusion probability >= 0.95, the checks passed) that are true | "
        f"{_fmt_rate(s['calibration']['claimed'])} | >= 90 % |",
        f"| accepted steps (an effect or a group) holding a true effect | {_fmt_rate(s['calibration']['groups'])} | |",
        f"| claim on clean data | {_fmt_rate(s['clean_claims'])} | <= 2 % |",
        f"| clean data judged not adequate (no claim, but a residual flagged) | {_fmt_rate(s['clean_not_adequate'])} | |",
        f"| outside the library: unexplained residual flagged | {_fmt_rate(s['outside_unexplained'])} | >= 90 % |",
        f"| wrong core flagged (scored unless invisible: the core file with one library effect within "
        f"{INVISIBLE:g} floors of the noise-free data) | {_fmt_rate(s['wrong_core_flagged'])} | all |",
        f"| ... every wrong-core case, visible or not | {_fmt_rate(s['wrong_core_flagged_all'])} | |",
        f"| median error after / noise floor (visible effects) | {s['ratio_after_visible_median'] or float('nan'):.2f} | <= 1.3 |",
        f"| loop wall time per case (mean / max) | {s['loop_wall_s']['mean']:.1f} / {s['loop_wall_s']['max']:.1f} s | |",
    ]
    if "cases_per_s" in meta:
        lines.append(
            f"| cases per second (last run, loop only; its generation {meta['generation_s']:.0f} s, cached) | "
            f"{meta['cases_per_s']:.3g} | |"
        )
    for name, sub in (s.get("by_split") or {}).items():
        lines.append(
            f"| {name} seeds only: right effect(s) strict / outside-lab `explained` / claims at >= 0.95 "
            f"true / `adequate` in tension | {_fmt_rate(sub['right_effect'])} / "
            f"{_fmt_rate(sub['outside_lab_explained'])} / {_fmt_rate(sub['calibration']['claimed'])} / "
            f"{sub['adequate_in_tension']} | |"
        )
    lines += ["", "Confusion matrix (rows: truth; columns: accepted effects, or the verdict when none):", ""]
    cols = sorted({c for row in s["confusion"].values() for c in row})
    lines += ["| truth \\ loop | " + " | ".join(cols) + " |", "| --- |" + " --- |" * len(cols)]
    for a, row in s["confusion"].items():
        lines.append(f"| {a} | " + " | ".join(str(row[c]) if row[c] else "." for c in cols) + " |")
    if s.get("drifting"):
        lines += [
            "",
            f"Cases whose final model has an h that changes with the heat input (drift p < {DRIFT_P:g}, "
            "docs/loop.md; their verdicts):",
            "",
            "| category | cases | verdicts |",
            "| --- | --- | --- |",
        ]
        for c, d in s["drifting"].items():
            lines.append(
                f"| {c} | {_fmt_rate(d)} | {', '.join(f'{v} {n}' for v, n in d['by_verdict'].items()) or '-'} |"
            )
    lab = sorted({r["category"].split(":", 1)[1] for r in records if r["category"].startswith("lab:")})
    if lab:
        lines += ["", "Lab effects (tawarp.reference_effects) and their sizes:", ""]
        where = {e: f"the library's `{LAB[e].library}`" if LAB[e].library else "outside the library" for e in lab}
        lines += [f"* `{e}` ({where[e]}): {LAB[e].why}" for e in lab]
    lines += [
        "",
        "Calibration of the inclusion probabilities (every effect of every case's report; true: the "
        "effect is in the data):",
        "",
        "| probability | effects | mean probability | true | fraction true |",
        "| --- | --- | --- | --- | --- |",
    ]
    for b in s["calibration"]["bins"]:
        frac = "-" if b["fraction_true"] is None else f"{b['fraction_true']:.2f}"
        mean = "-" if b["mean_probability"] is None else f"{b['mean_probability']:.2f}"
        lines.append(f"| {b['low']:g}-{b['high']:g} | {b['n']} | {mean} | {b['true']} | {frac} |")
    lines += [
        "",
        "Cases (visibility: of all the case's effects; per effect with several; right: strict / with groups):",
        "",
        "| seed | category | material / core | noise | sigma | visibility | before/floor | "
        "after/floor | loop | right | s |",
        "| --- |" + " --- |" * 10,
    ]
    yes = lambda ok: "yes" if ok else "**no**"
    right = lambda r: f"{yes(r['right'])} / {yes(r['right_group'])}" if r["expected"]["scored"] else "not scored"
    for r in records:
        vis = "-" if r["visibility"] is None else f"{r['visibility']:.1f}"
        if len(r["per_effect"]) > 1:
            vis += " (" + ", ".join(f"{v['visibility']:.1f}" for v in r["per_effect"].values()) + ")"
        lines.append(
            f"| {r['seed']} | {r['category']} | {r['material']} / {r['core']} | {100 * r['noise']:.2f} % | "
            f"{'yes' if r['with_sigma'] else 'no'} | {vis} | {r['ratio_before']:.2f} | {r['ratio_after']:.2f} | "
            f"{outcome_label(r)} | {right(r)} | {r['wall_s']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def figures(summary: dict, records: list[dict], out: Path) -> None:
    from tawarp.plots import plt, save

    conf = summary["confusion"]
    rows, cols = list(conf), sorted({c for row in conf.values() for c in row})
    M = np.array([[conf[a][b] for b in cols] for a in rows], dtype=float)
    fig, ax = plt.subplots(figsize=(1.0 + 0.6 * len(cols), 1.0 + 0.4 * len(rows)))
    ax.imshow(M / np.maximum(M.sum(1, keepdims=True), 1), cmap="Blues", vmin=0, vmax=1)
    for i in range(len(rows)):
        for j in range(len(cols)):
            if M[i, j]:
                frac = M[i, j] / max(M[i].sum(), 1)
                ax.text(j, i, f"{M[i, j]:.0f}", ha="center", va="center", fontsize=8, color="w" if frac > 0.5 else "k")
    ax.set_xticks(range(len(cols)), cols, rotation=60, ha="right", fontsize=8)
    ax.set_yticks(range(len(rows)), rows, fontsize=8)
    ax.set_xlabel("loop: accepted effects (or verdict)")
    ax.set_ylabel("truth")
    save(fig, out / "confusion.png")

    bins = [b for b in summary["calibration"]["bins"] if b["n"]]
    if bins:
        fig, ax = plt.subplots(figsize=(4, 4))
        ax.plot([0, 1], [0, 1], color="0.6", lw=0.8, ls="--")
        ax.plot([b["mean_probability"] for b in bins], [b["fraction_true"] for b in bins], "o-")
        for b in bins:
            ax.annotate(
                f"{b['n']}",
                (b["mean_probability"], b["fraction_true"]),
                textcoords="offset points",
                xytext=(4, -10),
                fontsize=8,
            )
        ax.set_xlabel("inclusion probability (bin mean)")
        ax.set_ylabel("fraction of those effects that are true")
        ax.set_title("calibration (labels: effects per bin)", fontsize=9)
        save(fig, out / "calibration.png")

    fig, ax = plt.subplots(figsize=(8, 3.5))
    cats = sorted({r["category"] for r in records})
    for i, c in enumerate(cats):
        sel = [r for r in records if r["category"] == c]
        x = i + np.linspace(-0.2, 0.2, len(sel)) if len(sel) > 1 else np.array([i])
        ax.scatter(x, [r["ratio_before"] for r in sel], marker="v", color="0.6", s=14)
        ax.scatter(
            x,
            [r["ratio_after"] for r in sel],
            s=16,
            c=[
                "0.6"
                if not r["expected"]["scored"]
                else "tab:green"
                if r["right"]
                else "tab:orange"
                if r["right_group"]
                else "tab:red"
                for r in sel
            ],
        )
    ax.axhline(TARGETS["residual_ratio"], color="k", lw=0.8, ls="--")
    ax.set_yscale("log")
    ax.set_xticks(range(len(cats)), cats, rotation=45, ha="right", fontsize=8)
    ax.set_ylabel("error / noise floor")
    ax.set_title(
        "triangle: before; dot: after (green right, orange right as a group, red wrong, grey not scored); dashed: 1.3",
        fontsize=8,
    )
    save(fig, out / "residual_ratio.png")


def seed_list(text: str) -> list[int]:
    """``--seeds``: comma-separated integers ("13,27,41")."""
    try:
        return [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"comma-separated integer seeds expected, got {text!r}") from None


def fraction_range(text: str) -> tuple[float, float]:
    """``--prior-off``: "LOW,HIGH" relative errors, 0 <= LOW <= HIGH < 1 ("0.1,0.2")."""
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"two comma-separated fractions expected, got {text!r}") from None
    if not 0.0 <= lo <= hi < 1.0:
        raise argparse.ArgumentTypeError(f"need 0 <= LOW <= HIGH < 1, got {text!r}")
    return lo, hi


def study_seeds(seed0: int, cases: int, seeds: list[int] | None, split: str) -> list[int]:
    """The seeds of a run: ``seeds``, or ``cases`` of them from ``seed0``, counted from
    :data:`HELDOUT_SEED0` for the held-out split. A tuning run never touches the held-out split."""
    chosen = seeds or list(range(seed0, seed0 + cases))
    if split == "heldout" and not seeds:
        chosen = [HELDOUT_SEED0 + s for s in chosen]
    crossing = [s for s in chosen if (s >= HELDOUT_SEED0) != (split == "heldout")]
    if crossing:
        raise ValueError(
            f"seeds {crossing[:5]} are {'not ' if split == 'heldout' else ''}held out (held out: seeds >= "
            f"{HELDOUT_SEED0}); pass --split {'tuning' if split == 'heldout' else 'heldout'} for them"
        )
    return chosen


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument("--cases", type=int, default=14, help="number of cases (seeds SEED0 .. SEED0 + CASES - 1)")
    ap.add_argument(
        "--suite",
        choices=tuple(SUITES),
        default="library",
        help="the library's effects (with pairs, outside and wrong core) or the lab effects of "
        "tawarp.reference_effects (core file 10-20 %% off)",
    )
    ap.add_argument(
        "--split",
        choices=("tuning", "heldout"),
        default="tuning",
        help=f"tuning seeds (< {HELDOUT_SEED0}) or held-out ones (SEED0 counted from {HELDOUT_SEED0}): "
        "run the held-out split only once the rules are frozen",
    )
    ap.add_argument(
        "--prior-off",
        type=fraction_range,
        default=None,
        help="LOW,HIGH relative errors of the core file; none: 0.1,0.3 (the lab suite: 0.1,0.2)",
    )
    ap.add_argument("--seed0", type=int, default=0, help="first seed")
    ap.add_argument(
        "--seeds",
        type=seed_list,
        default=None,
        help="comma-separated seeds instead of SEED0 .. SEED0 + CASES - 1 (with --append: run again)",
    )
    ap.add_argument(
        "--category",
        choices=tuple(dict.fromkeys(CATEGORIES + LAB_CATEGORIES)),
        default=None,
        help="every case of this category (default: cycled by seed, so the study mixes them all)",
    )
    ap.add_argument("--device", default="cpu", help="device of the loop's fits (cpu, cuda, cuda:N)")
    ap.add_argument("--out", default="studies/out/loop_validation", help="output folder (cache in OUT/cache)")
    ap.add_argument("--loop-workers", type=int, default=1, help="processes running the loops")
    ap.add_argument(
        "--together",
        type=int,
        default=1,
        help="loops a loop process runs together, their fits and launches batched (tawarp.loop.run_loops): "
        "on a GPU host, where a loop alone is bound by its host work",
    )
    ap.add_argument(
        "--blocking-waits",
        action="store_true",
        help="on a GPU: each loop process's CUDA context waits by blocking, not spinning, so that more "
        "processes than cores share the host",
    )
    ap.add_argument(
        "--workers",
        type=int,
        default=max(1, min(4, (os.cpu_count() or 1))),
        help="processes generating the reference data",
    )
    ap.add_argument(
        "--base",
        choices=("loop", "paper"),
        default="loop",
        help="base parameters: the loop's default, or the paper's full set passed explicitly",
    )
    ap.add_argument(
        "--rescore",
        action="store_true",
        help="no new runs: score OUT/loop_validation.json's cases again and rewrite the tables and figures",
    )
    ap.add_argument(
        "--append",
        action="store_true",
        help="keep the cases of other seeds already in OUT/loop_validation.json (a study run in chunks "
        "of seeds, e.g. one GPU job per --seed0) and summarize them all",
    )
    ap.add_argument("--quiet", action="store_true")
    a = ap.parse_args(argv)
    for option, value in (("--workers", a.workers), ("--loop-workers", a.loop_workers)):
        if value < 1:
            ap.error(f"{option}: {value}; expected a positive number of processes")
    if a.together < 1:
        ap.error(f"--together: {a.together}; expected a positive number of loops")
    if a.blocking_waits and not a.device.startswith("cuda"):
        ap.error(f"--blocking-waits: sets how loop processes wait for a GPU; --device is {a.device!r}")
    out = Path(a.out)
    results = out / "loop_validation.json"
    try:
        # read before any work: a file that is not a study's stops the run at once
        old = read_results(results) if a.rescore or (a.append and results.exists()) else None
    except ValueError as e:
        ap.error(f"{'--rescore' if a.rescore else '--append'}: {e}")
    if a.rescore:
        report(out, [score(r) for r in old["cases"]], old["meta"], a.quiet)
        return 0
    cache = out / "cache"
    try:
        seeds = study_seeds(a.seed0, a.cases, a.seeds, a.split)
    except ValueError as e:
        ap.error(str(e))
    cases = [make_case(s, a.category, suite=a.suite, prior_off=a.prior_off) for s in seeds]
    t0 = time.perf_counter()
    bar = progress_bar(len(cases), "generating (reference)", not a.quiet, unit="case")
    arrays = {}
    # spawned (cores_shared: a forked process would keep this one's linear-algebra threads)
    spawn = multiprocessing.get_context("spawn")
    with (
        _kept_on_interrupt(lambda: f"no loop had run; the reference data made are in {cache}, each file whole"),
        cores_shared(a.workers),
        ProcessPoolExecutor(a.workers, mp_context=spawn, initializer=_interrupt_ends_quietly) as pool,
    ):
        for case, arr in zip(cases, pool.map(load_or_generate, cases, [cache] * len(cases))):
            arrays[case.seed] = arr
            bar.update(1)
    bar.close()
    t_gen = time.perf_counter() - t0
    seeds = {c.seed for c in cases}
    earlier = [r for r in old["cases"] if r["seed"] not in seeds] if old else []
    records = []
    bar = progress_bar(len(cases), "closing the loop", not a.quiet, unit="case")
    t1 = time.perf_counter()
    # each case's loop is independent: with --loop-workers they run in processes of their own
    # (each its own Warp context, on the CPU or sharing the GPU), on the CPU each with its
    # share of the cores, their linear algebra's threads too (cores_shared)
    threads = cpu_share(a.loop_workers) if a.device == "cpu" else None
    if a.device != "cpu" and a.loop_workers > 1 and not cuda_mps_running():
        print(
            f"note: {a.loop_workers} loop processes share the GPU without NVIDIA's MPS daemon and take turns "
            "on it (docs/loop.md, Speed: nvidia-cuda-mps-control -d, or --device cpu)",
            file=sys.stderr,
        )

    def kept() -> str:
        done = (
            f"{len(records)} finished case{'s' if len(records) > 1 else ''} in {results} (marked partial)"
            if records
            else "no case had finished, so no result was written"
        )
        return f"{done}; the reference data made are in {cache}, each file whole"

    with (
        _kept_on_interrupt(kept),
        cores_shared(a.loop_workers),
        ProcessPoolExecutor(
            a.loop_workers,
            mp_context=spawn,
            initializer=_loop_worker_start,
            initargs=(a.device if a.blocking_waits else None,),
        ) as pool,
    ):
        loop = functools.partial(run_cases, device=a.device, base=a.base, cpu_threads=threads)
        # the cases of one core file together: their launches are shared (one family of kinds)
        ordered = sorted(cases, key=lambda c: c.core_material) if a.together > 1 else cases
        groups = [ordered[k : k + a.together] for k in range(0, len(ordered), a.together)]
        runs = pool.map(loop, groups, [[arrays[c.seed] for c in g] for g in groups])
        for group, recs in zip(groups, runs):
            for case, rec in zip(group, recs):
                records.append(rec)
                bar.set_postfix_str(f"{case.category}: {outcome_label(rec)}")
                bar.update(1)
            # the cases so far, so that an interrupted run keeps them
            write_json(results, {"meta": {"partial": True}, "cases": earlier + records})
    bar.close()
    t_loop = time.perf_counter() - t1
    meta = {
        "command": " ".join(["python studies/loop_validation.py"] + (sys.argv[1:] if argv is None else list(argv))),
        "seed0": a.seed0,
        "suite": a.suite,
        "split": a.split,
        "device": a.device,
        "base": a.base,
        "workers": a.workers,
        "loop_workers": a.loop_workers,
        "together": a.together,
        "generation_s": t_gen,
        "loop_s": t_loop,
        "cases_per_s": len(cases) / t_loop,
        "cases_this_run": len(cases),
    }
    report(out, sorted(earlier + records, key=lambda r: r["seed"]), meta, a.quiet)
    return 0


def read_results(path: Path) -> dict:
    """A study's JSON (its ``meta`` and ``cases``); ValueError naming the file where it is
    missing or not such a file."""
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file (a study run with --out {path.parent} writes it)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not readable as a study's JSON ({e})") from None
    if not (isinstance(data, dict) and isinstance(data.get("meta"), dict) and isinstance(data.get("cases"), list)):
        raise ValueError(f'{path}: not a study\'s JSON (expected its "meta" and "cases")')
    return data


def report(out: Path, records: list[dict], meta: dict, quiet: bool) -> None:
    """Summary, JSON, markdown and figures of ``records``."""
    summary = summarize(records)
    write_json(out / "loop_validation.json", {"meta": meta, "summary": summary, "cases": records})
    write_text(out / "loop_validation.md", markdown(summary, records, meta))
    figures(summary, records, out)
    if not quiet:
        print(markdown(summary, records, meta).split("\n\nCases:")[0])


if __name__ == "__main__":
    # every file is written whole (tawarp.io.atomic_path), which a traceback would hide
    try:
        sys.exit(main())
    except StudyInterrupted as e:
        print(f"loop_validation.py: interrupted; {e}", file=sys.stderr)
        sys.exit(130)
    except KeyboardInterrupt:
        print("loop_validation.py: interrupted; every file written is whole", file=sys.stderr)
        sys.exit(130)
