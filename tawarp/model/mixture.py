"""Transport properties of dilute binary gas mixtures from kinetic theory (host side).

The kernels read one transport law per gas (:mod:`tawarp.model.gas`); a mixture gets its
law by evaluating the mixing rules below on a temperature grid and fitting the law to
them (:func:`fit_transport_law`). Everything here is NumPy on plain numbers: molar masses
M [kg/mol], Lennard-Jones (12-6) parameters sigma [m] and epsilon/k_B [K], and the pure
gases' viscosities mu_i(T) [Pa s] and conductivities k_i(T) [W/(m K)] at the same T.

Viscosity, any binary pair: the first Chapman-Enskog approximation (Hirschfelder, Curtiss
& Bird, *Molecular Theory of Gases and Liquids*, 1954, Sect. 8.2), written with the pure
viscosities and the interaction viscosity mu_12 of the unlike pair::

    1/mu = (X + Y) / (1 + Z)
    X = x1^2/mu1 + 2 x1 x2/mu12 + x2^2/mu2
    Y = 3/5 A* [x1^2/mu1 M1/M2 + 2 x1 x2/mu12 (M1+M2)^2/(4 M1 M2) mu12^2/(mu1 mu2) + x2^2/mu2 M2/M1]
    Z = 3/5 A* [x1^2 M1/M2 + 2 x1 x2 ((M1+M2)^2/(4 M1 M2) (mu12/mu1 + mu12/mu2) - 1) + x2^2 M2/M1]

Conductivity of two monatomic gases: the first Chapman-Enskog approximation (same book,
Sect. 8.2) with k12 = 15/4 R mu12 (M1+M2)/(2 M1 M2), R the molar gas constant::

    1/k = (X + Y) / (1 + Z),  X = x1^2/k1 + 2 x1 x2/k12 + x2^2/k2
    Y = x1^2/k1 U1 + 2 x1 x2/k12 UY + x2^2/k2 U2,   Z = x1^2 U1 + 2 x1 x2 UZ + x2^2 U2
    U1 = 4/15 A* - 1/12 (12/5 B* + 1) M1/M2 + 1/2 (M1 - M2)^2/(M1 M2)     (U2: 1 <-> 2)
    UY = 4/15 A* (M1+M2)^2/(4 M1 M2) k12^2/(k1 k2) - 1/12 (12/5 B* + 1)
         - 5/(32 A*) (12/5 B* - 5) (M1 - M2)^2/(M1 M2)
    UZ = 4/15 A* [(M1+M2)^2/(4 M1 M2) (k12/k1 + k12/k2) - 1] - 1/12 (12/5 B* + 1)

The first approximation underestimates the conductivity of mixtures of very unlike masses:
for helium-xenon the third approximation is 1 % to 4 % higher (largest near 30 % helium;
Johnson, NASA/CR-2006-214394, after Singh 1992); viscosity's correction is below 1 %.

Conductivity with a polyatomic component (helium with nitrogen or air): Wassiljewa's form
with the coefficients of Mason & Saxena (Phys. Fluids 1:361, 1958; Poling, Prausnitz &
O'Connell, *The Properties of Gases and Liquids*, 5th ed., Sect. 10-6), which
carries the internal-energy transport of the pure gas's measured conductivity::

    k = sum_i x_i k_i / sum_j x_j Phi_ij
    Phi_ij = [1 + (mu_i/mu_j)^(1/2) (M_j/M_i)^(1/4)]^2 / [8 (1 + M_i/M_j)]^(1/2)

Interaction viscosity (HCB Sect. 8.2, the pure gas's formula at the reduced mass, with the
combining rules sigma12 = (sigma1 + sigma2)/2, eps12 = sqrt(eps1 eps2))::

    mu12 = 5/16 sqrt(2 pi m12 k_B T) / (pi sigma12^2 Omega22*(T*)),   m12 = 2 m1 m2/(m1 + m2)

Collision integrals of the Lennard-Jones (12-6) potential: Omega(1,1)* and Omega(2,2)* from
Neufeld, Janzen & Aziz (J. Chem. Phys. 57:1100, 1972; 0.1 % for 0.3 <= T* <= 100), so
A* = Omega22*/Omega11*; B* from the table of HCB (the values Johnson reproduces),
interpolated in ln T*.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

R_MOLAR = 8.314462618  # J/(mol K)
K_BOLTZMANN = 1.380649e-23  # J/K
N_AVOGADRO = 6.02214076e23  # 1/mol

# B* = (5 Omega12* - 4 Omega13*)/Omega11* of the Lennard-Jones (12-6) potential at T*
# (Hirschfelder, Curtiss & Bird 1954, as tabulated by Johnson, NASA/CR-2006-214394)
_B_STAR_T = np.array([0.3, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 10.0, 20.0, 100.0, 400.0])
_B_STAR = np.array([1.289, 1.284, 1.233, 1.192, 1.165, 1.143, 1.119, 1.106, 1.101, 1.095, 1.092, 1.094, 1.095,
                    1.095, 1.095])  # fmt: skip


def omega11(t_star):
    """Reduced collision integral Omega(1,1)* of the Lennard-Jones potential (Neufeld 1972)."""
    t = np.asarray(t_star, dtype=float)
    return (
        1.06036 / t**0.15610
        + 0.19300 * np.exp(-0.47635 * t)
        + 1.03587 * np.exp(-1.52996 * t)
        + 1.76474 * np.exp(-3.89411 * t)
    )


def omega22(t_star):
    """Reduced collision integral Omega(2,2)* of the Lennard-Jones potential (Neufeld 1972)."""
    t = np.asarray(t_star, dtype=float)
    return 1.16145 / t**0.14874 + 0.52487 * np.exp(-0.77320 * t) + 2.16178 * np.exp(-2.43787 * t)


def a_star(t_star):
    """A* = Omega22*/Omega11* [-]."""
    return omega22(t_star) / omega11(t_star)


def b_star(t_star):
    """B* [-] from the Lennard-Jones table, linear in ln T* (constant beyond its ends)."""
    return np.interp(np.log(t_star), np.log(_B_STAR_T), _B_STAR)


def lj_viscosity(T, M: float, sigma: float, eps: float):
    """Chapman-Enskog viscosity [Pa s] of a gas (or of an unlike pair with the reduced
    mass M = 2 M1 M2/(M1 + M2)) of molar mass M [kg/mol], Lennard-Jones sigma [m], eps/k_B [K]."""
    T = np.asarray(T, dtype=float)
    m = M / N_AVOGADRO
    return 5.0 / 16.0 * math.sqrt(math.pi * m * K_BOLTZMANN) * np.sqrt(T) / (math.pi * sigma**2 * omega22(T / eps))


def interaction(T, M1, M2, lj1, lj2):
    """mu12 [Pa s], A*, B* of the unlike pair at T; lj = (sigma [m], eps/k_B [K])."""
    sigma = 0.5 * (lj1[0] + lj2[0])
    eps = math.sqrt(lj1[1] * lj2[1])
    t_star = np.asarray(T, dtype=float) / eps
    return lj_viscosity(T, 2.0 * M1 * M2 / (M1 + M2), sigma, eps), a_star(t_star), b_star(t_star)


def viscosity(x1, M1, M2, mu1, mu2, mu12, A):
    """Mixture viscosity [Pa s], first Chapman-Enskog approximation (module docstring)."""
    x2 = 1.0 - x1
    m = (M1 + M2) ** 2 / (4.0 * M1 * M2)
    X = x1**2 / mu1 + 2 * x1 * x2 / mu12 + x2**2 / mu2
    Y = 0.6 * A * (x1**2 / mu1 * M1 / M2 + 2 * x1 * x2 / mu12 * m * mu12**2 / (mu1 * mu2) + x2**2 / mu2 * M2 / M1)
    Z = 0.6 * A * (x1**2 * M1 / M2 + 2 * x1 * x2 * (m * (mu12 / mu1 + mu12 / mu2) - 1.0) + x2**2 * M2 / M1)
    return (1.0 + Z) / (X + Y)


def conductivity_monatomic(x1, M1, M2, k1, k2, mu12, A, B):
    """Conductivity [W/(m K)] of a mixture of two monatomic gases, first Chapman-Enskog
    approximation (module docstring)."""
    x2 = 1.0 - x1
    m = (M1 + M2) ** 2 / (4.0 * M1 * M2)
    d = (M1 - M2) ** 2 / (M1 * M2)
    k12 = 15.0 / 4.0 * R_MOLAR * mu12 * (M1 + M2) / (2.0 * M1 * M2)
    b = (12.0 / 5.0 * B + 1.0) / 12.0
    U1 = 4.0 / 15.0 * A - b * M1 / M2 + 0.5 * d
    U2 = 4.0 / 15.0 * A - b * M2 / M1 + 0.5 * d
    UY = 4.0 / 15.0 * A * m * k12**2 / (k1 * k2) - b - 5.0 / (32.0 * A) * (12.0 / 5.0 * B - 5.0) * d
    UZ = 4.0 / 15.0 * A * (m * (k12 / k1 + k12 / k2) - 1.0) - b
    X = x1**2 / k1 + 2 * x1 * x2 / k12 + x2**2 / k2
    Y = x1**2 / k1 * U1 + 2 * x1 * x2 / k12 * UY + x2**2 / k2 * U2
    Z = x1**2 * U1 + 2 * x1 * x2 * UZ + x2**2 * U2
    return (1.0 + Z) / (X + Y)


def conductivity_mason_saxena(x1, M1, M2, k1, k2, mu1, mu2):
    """Conductivity [W/(m K)] by Wassiljewa's form with Mason & Saxena's coefficients."""
    x2 = 1.0 - x1

    def phi(mu_i, mu_j, M_i, M_j):
        return (1.0 + np.sqrt(mu_i / mu_j) * (M_j / M_i) ** 0.25) ** 2 / np.sqrt(8.0 * (1.0 + M_i / M_j))

    return x1 * k1 / (x1 + x2 * phi(mu1, mu2, M1, M2)) + x2 * k2 / (x1 * phi(mu2, mu1, M2, M1) + x2)


def fit_transport_law(T, X, T_REF: float) -> tuple[tuple[float, float, float], float]:
    """(X0, a, S) of the kernels' law X(T) = X0 (T/T_REF)^a (1 + S/T_REF)/(1 + S/T) fitted
    to X(T) by least squares in ln X (0 <= a <= 2, 0 <= S <= 2000 K, starting from
    Sutherland-like a = 0.6, S = 50 K), and the largest relative error of the fit on the grid."""
    T = np.asarray(T, dtype=float)
    lnX = np.log(np.asarray(X, dtype=float))

    def residual(p):
        ln_x0, a, s = p
        return ln_x0 + a * np.log(T / T_REF) + np.log((1.0 + s / T_REF) / (1.0 + s / T)) - lnX

    start = [float(np.interp(math.log(T_REF), np.log(T), lnX)), 0.6, 50.0]
    fit = least_squares(residual, start, bounds=([-np.inf, 0.0, 0.0], [np.inf, 2.0, 2000.0]), x_scale=[1.0, 0.1, 50.0],
                        xtol=1e-14, ftol=1e-14, gtol=1e-14)  # fmt: skip
    ln_x0, a, s = fit.x
    return (math.exp(ln_x0), float(a), float(s)), float(np.max(np.abs(np.expm1(residual(fit.x)))))
