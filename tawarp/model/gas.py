"""Constants of the working gases: pure gases by name, and binary mixtures.

Transport properties follow ``X(T) = X0 (T/T0)^a (1 + S/T0) / (1 + S/T)`` with
``T0 = 273.15 K``: Sutherland's law is ``a = 1/2`` with its constant ``S``; ``S = 0`` is a
plain power law (used for helium, where Sutherland fits poorly). Heat capacity and the
ratio of specific heats are taken constant (ideal gas; monatomic gases exactly so). The
laws themselves live in the kernels and in the independent NumPy reference.

Sources: air as docs/physics.md (White, *Viscous Fluid Flow*, Table 1-2/1-3); nitrogen and
argon Sutherland constants from the same tables; helium power laws fitted to NIST
data over 250-800 K (viscosity 1.865e-5 Pa s and conductivity 0.1415 W/(m K) at
273.15 K, both about T^0.7), as Swift (*Thermoacoustics*, Sect. 10) recommends. Neon,
krypton and xenon: the Chapman-Enskog viscosity of their Lennard-Jones parameters
(:data:`LENNARD_JONES`) and the monatomic conductivity k = 15/4 R mu, fitted to the law
over :data:`FIT_RANGE` (:func:`kinetic_theory_gas`); molar masses are IUPAC's standard
atomic weights.

A mixture is named by its mole fractions, ``"helium=0.7,argon=0.3"`` (the ``[gas.mixture]``
table of a core file, docs/formats.md); :data:`GASES` gives its constants like a pure
gas's: molar mass and heat capacity averaged by mole, the transport law fitted to the
kinetic-theory mixing rules of :mod:`tawarp.model.mixture` over :data:`FIT_RANGE`.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator, Mapping
from dataclasses import astuple, dataclass

import numpy as np

from . import mixture

T_REF = 273.15  # K, reference temperature of the transport laws
#: K, temperatures over which a computed transport law (mixture, kinetic-theory gas) is fitted;
#: outside it the law extrapolates (docs/physics.md gives the fit errors)
FIT_RANGE = (200.0, 1000.0)
_FIT_GRID = np.geomspace(*FIT_RANGE, 81)


@dataclass(frozen=True)
class GasConstants:
    """Constants of one gas. Units: J/(kg K), J/(kg K), -, Pa s, -, K, W/(m K), -, K."""

    R_gas: float
    cp: float
    gamma: float
    mu0: float
    mu_exponent: float
    mu_sutherland: float
    k0: float
    k_exponent: float
    k_sutherland: float

    def as_tuple(self) -> tuple[float, ...]:
        """The order the kernels read (``kernels.gas``)."""
        return astuple(self)

    @property
    def molar_mass(self) -> float:
        """M = R / R_gas [kg/mol]."""
        return mixture.R_MOLAR / self.R_gas

    def transport(self, T) -> tuple[np.ndarray, np.ndarray]:
        """Viscosity [Pa s] and conductivity [W/(m K)] at T [K] by the transport laws."""
        T = np.asarray(T, dtype=float)

        def law(x0, a, s):
            return x0 * (T / T_REF) ** a * (1.0 + s / T_REF) / (1.0 + s / T)

        return law(self.mu0, self.mu_exponent, self.mu_sutherland), law(self.k0, self.k_exponent, self.k_sutherland)


#: Lennard-Jones (12-6) parameters (sigma [m], epsilon/k_B [K]) from viscosity data
#: (Hirschfelder, Curtiss & Bird 1954, Table I-A); they set the unlike pair of a mixture.
LENNARD_JONES = {
    "helium": (2.576e-10, 10.22),
    "neon": (2.789e-10, 35.7),
    "argon": (3.418e-10, 124.0),
    "krypton": (3.61e-10, 190.0),
    "xenon": (4.055e-10, 229.0),
    "nitrogen": (3.681e-10, 91.5),
    "air": (3.617e-10, 97.0),
}
MONATOMIC = frozenset({"helium", "neon", "argon", "krypton", "xenon"})


def kinetic_theory_gas(name: str, molar_mass: float) -> GasConstants:
    """A monatomic gas from its Lennard-Jones parameters: the Chapman-Enskog viscosity fitted
    to the law over :data:`FIT_RANGE`, k = 15/4 R_gas mu, cp = 5/2 R_gas."""
    R = mixture.R_MOLAR / molar_mass
    (mu0, a, s), _ = mixture.fit_transport_law(_FIT_GRID, mixture.lj_viscosity(_FIT_GRID, molar_mass,
                                                                               *LENNARD_JONES[name]), T_REF)  # fmt: skip
    return GasConstants(R, 2.5 * R, 5.0 / 3.0, mu0, a, s, 3.75 * R * mu0, a, s)


PURE_GASES: dict[str, GasConstants] = {
    "air": GasConstants(287.05, 1005.0, 1.4, 1.716e-5, 0.5, 110.4, 0.0241, 0.5, 194.0),
    "nitrogen": GasConstants(296.80, 1040.0, 1.4, 1.663e-5, 0.5, 106.7, 0.0242, 0.5, 166.0),
    "argon": GasConstants(208.13, 520.3, 5.0 / 3.0, 2.125e-5, 0.5, 144.0, 0.0163, 0.5, 170.0),
    "helium": GasConstants(2077.1, 5193.0, 5.0 / 3.0, 1.865e-5, 0.7, 0.0, 0.1415, 0.7, 0.0),
    "neon": kinetic_theory_gas("neon", 20.1797e-3),
    "krypton": kinetic_theory_gas("krypton", 83.798e-3),
    "xenon": kinetic_theory_gas("xenon", 131.293e-3),
}

_MIXTURE_EXAMPLE = "'helium=0.7,argon=0.3' (mole fractions of two gases, summing to 1)"


def mixture_fractions(name: str) -> tuple[tuple[str, float], tuple[str, float]]:
    """The two (gas, mole fraction) pairs of mixture ``name`` ("helium=0.7,argon=0.3") as
    written (their sum is 1 to 1e-6); ValueError says what is wrong."""
    parts = [p.partition("=") for p in name.split(",")]
    if any(not eq for _, eq, _ in parts):
        raise ValueError(f"gas {name!r}: expected one of {sorted(PURE_GASES)} or a binary mixture {_MIXTURE_EXAMPLE}")
    if len(parts) != 2:
        raise ValueError(f"gas {name!r}: a mixture has exactly two gases, got {len(parts)}")
    pairs = []
    for gas, _, value in parts:
        gas = gas.strip()
        if gas not in PURE_GASES:
            raise ValueError(f"gas {name!r}: unknown component {gas!r}; expected one of {sorted(PURE_GASES)}")
        try:
            x = float(value)
        except ValueError:
            raise ValueError(f"gas {name!r}: the mole fraction of {gas} is {value!r}, not a number") from None
        if not 0.0 < x < 1.0:
            raise ValueError(f"gas {name!r}: the mole fraction of {gas} must lie in (0, 1), got {x}")
        pairs.append((gas, x))
    (a, xa), (b, xb) = pairs
    if a == b:
        raise ValueError(f"gas {name!r}: {a} is named twice; a mixture has two different gases")
    if abs(xa + xb - 1.0) > 1e-6:
        raise ValueError(f"gas {name!r}: the mole fractions sum to {xa + xb}, not 1")
    return (a, xa), (b, xb)


def mixture_name(fractions: Mapping[str, float]) -> str:
    """The name of the mixture of ``fractions`` {gas: mole fraction} (a ``[gas.mixture]``
    table), checked: ValueError says what is wrong."""
    if any(not isinstance(x, (int, float)) or isinstance(x, bool) for x in fractions.values()):
        raise ValueError(f"mole fractions must be numbers, got {dict(fractions)}")
    name = ",".join(f"{gas}={float(x)!r}" for gas, x in fractions.items())
    mixture_fractions(name)
    return name


def mixture_transport(name: str, T) -> tuple[np.ndarray, np.ndarray]:
    """Viscosity [Pa s] and conductivity [W/(m K)] of mixture ``name`` at T [K] by the
    kinetic-theory mixing rules themselves (:mod:`tawarp.model.mixture`), before the fit."""
    (a, xa), (b, xb) = mixture_fractions(name)
    x1 = xa / (xa + xb)
    ga, gb = PURE_GASES[a], PURE_GASES[b]
    M1, M2 = ga.molar_mass, gb.molar_mass
    (mu1, k1), (mu2, k2) = ga.transport(T), gb.transport(T)
    mu12, A, B = mixture.interaction(T, M1, M2, LENNARD_JONES[a], LENNARD_JONES[b])
    mu = mixture.viscosity(x1, M1, M2, mu1, mu2, mu12, A)
    if a in MONATOMIC and b in MONATOMIC:
        k = mixture.conductivity_monatomic(x1, M1, M2, k1, k2, mu12, A, B)
    else:
        k = mixture.conductivity_mason_saxena(x1, M1, M2, k1, k2, mu1, mu2)
    return mu, k


@functools.lru_cache(maxsize=256)
def mixture_constants(name: str) -> tuple[GasConstants, float, float]:
    """Constants of mixture ``name`` and the largest relative errors of its fitted
    viscosity and conductivity laws over :data:`FIT_RANGE`. Ideal gas: M = sum x_i M_i,
    molar heat capacities Cp = sum x_i Cp_i and Cv = sum x_i Cp_i / gamma_i, gamma = Cp / Cv
    (5/3 for any mixture of monatomic gases)."""
    (a, xa), (b, xb) = mixture_fractions(name)
    x1, x2 = xa / (xa + xb), xb / (xa + xb)
    ga, gb = PURE_GASES[a], PURE_GASES[b]
    M = x1 * ga.molar_mass + x2 * gb.molar_mass
    R = mixture.R_MOLAR / M
    cp_molar = x1 * ga.molar_mass * ga.cp + x2 * gb.molar_mass * gb.cp
    cv_molar = x1 * ga.molar_mass * ga.cp / ga.gamma + x2 * gb.molar_mass * gb.cp / gb.gamma
    mu, k = mixture_transport(name, _FIT_GRID)
    mu_law, mu_error = mixture.fit_transport_law(_FIT_GRID, mu, T_REF)
    k_law, k_error = mixture.fit_transport_law(_FIT_GRID, k, T_REF)
    return GasConstants(R, cp_molar / M, cp_molar / cv_molar, *mu_law, *k_law), mu_error, k_error


class GasTable(Mapping):
    """The gases by name: the pure gases of :data:`PURE_GASES` (what iterating gives) and
    every binary mixture by its name (:func:`mixture_name`), computed on first use."""

    def __getitem__(self, name: str) -> GasConstants:
        if not isinstance(name, str):
            raise KeyError(
                f"gas {name!r}: expected a name, one of {sorted(PURE_GASES)} or a mixture {_MIXTURE_EXAMPLE}"
            )
        if name in PURE_GASES:
            return PURE_GASES[name]
        try:
            return mixture_constants(name)[0]
        except ValueError as e:
            raise KeyError(str(e)) from None

    def __iter__(self) -> Iterator[str]:
        return iter(PURE_GASES)

    def __len__(self) -> int:
        return len(PURE_GASES)


GASES = GasTable()


def is_mixture(name: str) -> bool:
    """Whether gas ``name`` is a mixture (not a pure gas's name)."""
    return name not in PURE_GASES
