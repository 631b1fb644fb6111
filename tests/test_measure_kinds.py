"""Measurement kinds (tawarp.measure): each kind's predictions against the independent
NumPy reference, the scattering kind against the T-matrix kind, the registry, and the
fit cell counts (tawarp.measure.kind.fit_cells) against the cascade kernel's own rule."""

import numpy as np
import pytest

from tawarp import reference
from tawarp.measure import (
    ImpedanceData,
    ImpedanceKind,
    MeasurementError,
    ScatteringKind,
    TMatrixData,
    TMatrixKind,
    kind_of,
    load_measurement,
    transfer_to_scattering,
    write_tmatrix_csv,
)
from tawarp.measure.kind import fit_cells
from tawarp.model.coefficients import duct_impedance, normalize
from tawarp.model.core import load_core
from tawarp.model.forward import ForwardSettings, transfer_matrices
from tawarp.model.gas import GASES
from tawarp.model.layer import layer_core, surface_impedance_from_T

CPU = ForwardSettings(device="cpu")
CORE = load_core("ceramic")
F = np.linspace(60.0, 480.0, 6)


def tmatrix_data(core, freqs, Qs):
    T = transfer_matrices(core, freqs, list(Qs), device="cpu").T.reshape(-1, 2, 2)
    return TMatrixData(np.repeat(Qs, len(freqs)), np.tile(freqs, len(Qs)), T, None, {}, "<test>")


def test_tmatrix_kind_predicts_the_reference():
    # model values at other parameters than the data's, against the NumPy reference's
    # dimensionless coefficients (DOP853 rtol 1e-12 in the heated parts; forward error ~1e-6)
    kind = TMatrixKind(tmatrix_data(CORE, F, (0.0, 40.0)), CORE, CPU)
    vals = {"stack.porosity": np.array([0.85, 0.9]), "stack.h": np.array([80.0, 200.0])}
    Y = kind.predict(vals, 2)
    for i in range(2):
        core = CORE.replace(**{k: float(v[i]) for k, v in vals.items()})
        ref = np.concatenate(
            [normalize(reference.transfer_matrix(core, F, q), duct_impedance(CORE)) for q in (0.0, 40.0)]
        )
        assert np.max(np.abs(Y[i] - ref.reshape(-1))) <= 2e-5 * np.max(np.abs(ref))
    # the rows: (heat input, frequency) x the four coefficients
    assert kind.coef.tolist()[:8] == [0, 1, 2, 3, 0, 1, 2, 3] and kind.group[-1] == 40.0 and kind.freq[4] == F[1]


def test_heated_rows_on_a_passive_core_are_refused():
    # a passive core's model reads no heat input: rows at 0, 20 and 40 W were fitted as one
    # problem, silently
    passive = load_core("foam_sample")
    data = tmatrix_data(passive, F, (0.0,))
    T3 = np.tile(data.T, (3, 1, 1))
    heated = TMatrixData(np.repeat([0.0, 20.0, 40.0], F.size), np.tile(F, 3), T3, None, {}, "lab.csv")
    with pytest.raises(
        MeasurementError, match=r"lab.csv: rows at Q = 20, 40 W, but the core .*foam_sample\.toml has no"
    ):
        TMatrixKind(heated, passive, CPU)
    assert TMatrixKind(data, passive, CPU).y.size == 4 * F.size  # Q = 0 alone: as before


def test_tmatrix_kind_computes_only_the_heat_inputs_of_the_rows_asked_for():
    # a set whose rows are the Q = 0 ones alone gets no heated T-matrix (NaN at Q = 40 W):
    # its Q = 0 values, and every value of a set that asks for all rows, are those of the
    # full prediction bit for bit (each column is computed on its own)
    kind = TMatrixKind(tmatrix_data(CORE, F, (0.0, 40.0)), CORE, CPU)
    vals = {"stack.porosity": np.array([0.85, 0.9, 0.88]), "stack.h": np.array([80.0, 200.0, 120.0])}
    cold = kind.first_step_rows()
    full = kind.predict(vals, 3)
    part = kind.predict(vals, 3, rows=[cold, None, cold])
    heated = np.flatnonzero(kind.group > 0)
    np.testing.assert_array_equal(part[:, cold], full[:, cold])
    np.testing.assert_array_equal(part[1], full[1])
    assert np.isnan(part[[0, 2]][:, heated]).all() and np.isfinite(full).all()


def test_impedance_kind_predicts_the_reference(tmp_path):
    # Zs = -Tuu/Tup S/(rho0 c0) of the reference's one-segment layer, two thicknesses
    data = [ImpedanceData(F, np.ones(F.size), L, 293.15, 101325.0, {}, f"<{L}>") for L in (0.02, 0.05)]
    kind = ImpedanceKind(data, CPU)
    vals = {
        "layer.porosity": np.array([0.97]),
        "layer.pore_radius": np.array([1e-4]),
        "layer.tortuosity": np.array([1.3]),
        "layer.length_offset": np.array([1e-3]),
    }
    Y = kind.predict(vals, 1)[0]
    for k, L in enumerate((0.02, 0.05)):
        core = layer_core(L + 1e-3, 0.97, 1e-4, 1.3)
        ref = surface_impedance_from_T(reference.transfer_matrix(core, F), core)
        assert np.max(np.abs(Y[k * F.size : (k + 1) * F.size] - ref)) <= 1e-9 * np.max(np.abs(ref))
    assert kind.group_name == "thickness_m" and set(kind.group) == {0.02, 0.05}
    # unit weights make the cost the docs/formats.md error squared times the residual count
    d = Y - kind.y
    cost = np.sum((d.real * kind.w[:, 0]) ** 2 + (d.imag * kind.w[:, 1]) ** 2)
    assert abs(cost / kind.y.size - kind.error(Y) ** 2) <= 1e-12 * cost


def test_scattering_kind_is_the_converted_tmatrix_kind(tmp_path):
    T = transfer_matrices(CORE, F, 0.0, device="cpu").T[0]
    g = GASES["air"]
    c0 = np.sqrt(g.gamma * g.R_gas * CORE.gas.T_cold)
    S = transfer_to_scattering(T, 2 * np.pi * F / c0, duct_impedance(CORE), 0.05, 0.04)
    lines = [
        f"# tube_radius = {CORE.radius}",
        f"# T_ambient = {CORE.gas.T_cold}",
        f"# p_ambient = {CORE.gas.p_mean}",
        "# ref_upstream = 0.05",
        "# ref_downstream = 0.04",
        "freq_Hz," + ",".join(f"S{ij}_{p}" for ij in ("11", "12", "21", "22") for p in ("re", "im")),
    ]
    lines += [
        f"{float(f)!r}," + ",".join(f"{float(v.real)!r},{float(v.imag)!r}" for v in S[k].reshape(-1))
        for k, f in enumerate(F)
    ]
    path = tmp_path / "s.csv"
    path.write_text("\n".join(lines) + "\n")
    kind = load_measurement(path, "ceramic", CPU)
    assert isinstance(kind, ScatteringKind) and kind.name == "scattering"
    ref = TMatrixKind(tmatrix_data(CORE, F, (0.0,)), CORE, CPU)
    assert np.max(np.abs(kind.y - ref.y)) <= 1e-10 * np.max(np.abs(ref.y))


def test_registry_picks_the_kind_from_the_header(tmp_path):
    path = tmp_path / "t.csv"
    write_tmatrix_csv(path, tmatrix_data(CORE, F[:2], (0.0,)), {"core": "ceramic"})
    assert kind_of(path).name == "tmatrix"
    kind = load_measurement(path, settings=CPU)  # the core from the '# core = ...' line
    assert isinstance(kind, TMatrixKind) and kind.core == CORE
    bad = tmp_path / "bad.csv"
    bad.write_text("# a comment\nfreq_Hz,X_re,X_im\n100,1,2\n")
    with pytest.raises(MeasurementError, match=r"bad\.csv.*freq_Hz,X_re,X_im.*no measurement kind"):
        load_measurement(bad)
    no_core = tmp_path / "nocore.csv"
    write_tmatrix_csv(no_core, tmatrix_data(CORE, F[:2], (0.0,)))
    with pytest.raises(MeasurementError, match="nocore.csv.*core"):
        load_measurement(no_core)


@pytest.mark.parametrize(
    "values", [{}, {"tbt.wall_conductance": 5.0, "stack.wall_conductance": 2.0}, {"stack.h": 900.0, "hot_hx.h": 20.0}]
)
def test_fit_cells_are_the_kernels_adaptive_counts(values):
    # with k_factor = 1 the counts are the cascade's adaptive rule's at the density its error
    # estimate picks (wall conductance included), on the uniform grid of fixed cells (the
    # forward model's own grid is graded to the excess: fewer cells in the stack for the same
    # error): fixing them gives the adaptive model's T-matrices to the estimate's tolerance
    f = np.array([480.0])
    cells = fit_cells(CORE, 480.0, values, CPU, heat_input=40.0)
    fixed = {s.name: int(n) for s, n in zip(CORE.segments, cells) if s.thermal}
    params = {k: np.array([v]) for k, v in values.items()}
    Zc = duct_impedance(CORE)
    Y_adaptive = normalize(transfer_matrices(CORE, f, 40.0, params=params, device="cpu").T[0], Zc)
    Y_fixed = normalize(transfer_matrices(CORE, f, 40.0, params=params, device="cpu", cells=fixed).T[0], Zc)
    assert (np.abs(Y_fixed - Y_adaptive).max(-1) / np.abs(Y_adaptive).max(-1)).max() < CPU.tolerance
    # the fit's counts leave room for k twice as large
    assert np.all(fit_cells(CORE, 480.0, values, CPU, k_factor=2.0, heat_input=40.0) >= cells)


def test_engine_cache_lets_the_least_recently_used_go(monkeypatch):
    """get_engine keeps ENGINES_KEPT engines and lets the least recently used go, not all
    of them at once: a loop cycling through its models keeps the ones it uses."""
    from tawarp.measure import kind

    monkeypatch.setattr(kind, "ENGINES_KEPT", 3)
    monkeypatch.setattr(kind, "_ENGINES", {})
    core, settings = load_core("mesh"), ForwardSettings(device="cpu")

    def engine(f):
        return kind.get_engine(core, [f], ["stack.h"], settings)

    a, b, c = engine(100.0), engine(200.0), engine(300.0)
    assert engine(100.0) is a  # used again: now the most recent
    engine(400.0)  # a fourth: b, the least recently used, goes
    assert engine(100.0) is a and engine(300.0) is c
    assert engine(200.0) is not b and len(kind._ENGINES) == 3


def test_engine_cache_builds_one_engine_per_key_across_threads(monkeypatch):
    """Threads asking get_engine for the same engines at once (Dask thread workers) get
    one engine per key, each built once, and the cache never exceeds ENGINES_KEPT; the
    engine's construction is slowed so that unguarded threads would each build one."""
    import threading
    import time
    from concurrent.futures import ThreadPoolExecutor

    from tawarp.measure import kind

    built, real = [], kind.Engine

    def slow_engine(*a, **k):
        time.sleep(0.05)
        built.append(a[1])
        return real(*a, **k)

    monkeypatch.setattr(kind, "Engine", slow_engine)
    monkeypatch.setattr(kind, "ENGINES_KEPT", 4)
    monkeypatch.setattr(kind, "_ENGINES", {})
    core, settings = load_core("mesh"), ForwardSettings(device="cpu")
    start = threading.Barrier(8)

    def ask(i):
        start.wait()
        return [kind.get_engine(core, [100.0 * (1 + (i + r) % 4)], ["stack.h"], settings) for r in range(6)]

    with ThreadPoolExecutor(8) as pool:
        got = [e for es in pool.map(ask, range(8)) for e in es]
    assert len(built) == 4 and len(kind._ENGINES) == 4
    assert len({id(e) for e in got}) == 4
