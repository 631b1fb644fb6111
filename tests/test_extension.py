"""Extension points used from outside the package: a measurement kind defined here (the
reflection coefficient of the core terminated anechoically), registered with
:func:`tawarp.measure.register_kind`, loaded from its own CSV and fitted by the package's
estimator."""

import numpy as np
import pytest

from tawarp import reference
from tawarp.fit.problems import fit_kind
from tawarp.measure import MeasurementKind, get_engine, load_measurement, register_kind
from tawarp.model.coefficients import duct_impedance
from tawarp.model.core import load_core
from tawarp.model.forward import ForwardSettings

CORE = load_core("ceramic")
TRUTH = {"stack.porosity": CORE.get("stack.porosity"), "stack.pore_radius": CORE.get("stack.pore_radius")}
NOISE = 2e-3  # standard deviation of Re R and Im R


def reflection(T, Zc):
    """R at x1 of the core (T (..., 2, 2)) with an anechoic end at x6 (p6 = Zc U6):
    input impedance Z1 = (Zc Tuu - Tpu) / (Tpp - Zc Tup), R = (Z1 - Zc) / (Z1 + Zc)."""
    Z1 = (Zc * T[..., 1, 1] - T[..., 0, 1]) / (T[..., 0, 0] - Zc * T[..., 1, 0])
    return (Z1 - Zc) / (Z1 + Zc)


class ReflectionKind(MeasurementKind):
    """Unheated core, one observable R per frequency, with known sigma."""

    name = "reflection"
    group_name = "Q_W"
    coef_names = ("R",)

    def __init__(self, freq, R, sigma, core, settings=None):
        self.core, self.settings = core, settings or ForwardSettings(device="cpu")
        self.freqs = self.freq = np.asarray(freq, dtype=float)
        self.y = np.asarray(R, dtype=complex)
        self.group = np.zeros(self.y.size)
        self.coef = np.zeros(self.y.size, dtype=int)
        self.w = np.full((self.y.size, 2), 1.0 / sigma)
        self.has_sigma = True
        self.Zc = duct_impedance(core)

    @classmethod
    def from_file(cls, path, core=None, settings=None):
        rows = np.loadtxt(path, delimiter=",", comments="#", skiprows=1)
        return cls(rows[:, 0], rows[:, 1] + 1j * rows[:, 2], rows[0, 3], core or CORE, settings)

    def default_names(self):
        return list(TRUTH)

    def predict(self, values, n, effect=None):
        names = sorted(values)
        eng = get_engine(self.core, self.freqs, names, self.settings)
        table = np.vstack([np.zeros(n)] + [np.broadcast_to(np.asarray(values[k], dtype=float), (n,)) for k in names])
        out, _, _ = eng.evaluate(table)
        T = out.numpy().view(np.complex128).reshape(n, self.freqs.size, 2, 2)
        return reflection(T, self.Zc)


register_kind("reflection", ReflectionKind, lambda cols: "R_re" in cols)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_toy_measurement_kind(tmp_path, seed):
    # data from the independent NumPy reference (exact matrix exponentials at Q = 0) plus
    # noise of known sigma; starts 10-30 % off the truth
    f = np.linspace(50.0, 500.0, 16)
    R = reflection(reference.transfer_matrix(CORE, f, 0.0), duct_impedance(CORE))
    rng = np.random.default_rng(seed)
    R = R + NOISE * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size))
    path = tmp_path / "reflection.csv"
    rows = (f"{float(a)!r},{float(b.real)!r},{float(b.imag)!r},{NOISE!r}\n" for a, b in zip(f, R))
    path.write_text("freq_Hz,R_re,R_im,sigma\n" + "".join(rows))
    kind = load_measurement(path)
    assert isinstance(kind, ReflectionKind)
    off = rng.uniform(0.1, 0.3, size=2) * rng.choice([-1.0, 1.0], size=2)
    start = {k: v * (1 + o) for (k, v), o in zip(TRUTH.items(), off)}
    start["stack.porosity"] = min(start["stack.porosity"], 0.99)
    res = fit_kind(kind, start=start)
    assert res.converged[0], res.reason
    for k, v in TRUTH.items():
        got, std = res.value_dict()[k], res.std_dict()[k]
        assert abs(got - v) < 3 * std, (k, got, v, std)
        assert std < 0.05 * v  # the fit determines the parameter
    # with sigma known, chi^2 / dof ~ 1 (2 m - p = 30 dof: 99.9 % range 0.4..2.1)
    assert 0.4 < res.cost[0] / res.dof < 2.1
