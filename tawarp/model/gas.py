"""Constants of the working gases (no physics code: the laws live in the kernels and
in the independent NumPy reference).

Transport properties follow ``X(T) = X0 (T/T0)^a (1 + S/T0) / (1 + S/T)`` with
``T0 = 273.15 K``: Sutherland's law is ``a = 1/2`` with its constant ``S``; ``S = 0`` is a
plain power law (used for helium, where Sutherland fits poorly). Heat capacity and the
ratio of specific heats are taken constant (ideal gas; monatomic gases exactly so).

Sources: air as docs/physics.md (White, *Viscous Fluid Flow*, Table 1-2/1-3); nitrogen and
argon Sutherland constants from the same tables; helium power laws fitted to NIST
data over 250-800 K (viscosity 1.865e-5 Pa s and conductivity 0.1415 W/(m K) at
273.15 K, both about T^0.7), as Swift (*Thermoacoustics*, Sect. 10) recommends.
"""

from __future__ import annotations

from dataclasses import astuple, dataclass

T_REF = 273.15  # K, reference temperature of the transport laws


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


GASES: dict[str, GasConstants] = {
    "air": GasConstants(287.05, 1005.0, 1.4, 1.716e-5, 0.5, 110.4, 0.0241, 0.5, 194.0),
    "nitrogen": GasConstants(296.80, 1040.0, 1.4, 1.663e-5, 0.5, 106.7, 0.0242, 0.5, 166.0),
    "argon": GasConstants(208.13, 520.3, 5.0 / 3.0, 2.125e-5, 0.5, 144.0, 0.0163, 0.5, 170.0),
    "helium": GasConstants(2077.1, 5193.0, 5.0 / 3.0, 1.865e-5, 0.7, 0.0, 0.1415, 0.7, 0.0),
}
