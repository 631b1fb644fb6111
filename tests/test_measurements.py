"""Measurement loaders and writers (tawarp.measurements): formats, errors, conversions."""

import math

import numpy as np
import pytest

from shared_data import measured_folder
from tawarp.measure import files as m
from tawarp.model.gas import GASES

HEADER = "Q_W,freq_Hz,Tpp_re,Tpp_im,Tpu_re,Tpu_im,Tup_re,Tup_im,Tuu_re,Tuu_im"
ROW = "0,50,0.9121,-0.0177,-5.02e4,2.07e5,1e-6,2e-7,0.95,0.01"


def write(tmp_path, text, name="data.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def random_data(rng, n_q=3, n_f=4, sigma=True):
    Q = np.repeat(np.array([0.0, 20.0, 40.5])[:n_q], n_f)
    f = np.tile(np.linspace(30.0, 500.0, n_f), n_q) * (1 + 1e-3 * rng.random(n_q * n_f))
    scale = np.array([[1.0, 1e5], [1e-6, 1.0]])
    T = (rng.normal(size=(n_q * n_f, 2, 2)) + 1j * rng.normal(size=(n_q * n_f, 2, 2))) * scale
    s = rng.random((n_q * n_f, 2, 2, 2)) * scale[..., None] + 1e-12 if sigma else None
    return m.TMatrixData(Q, f, T, s, {"rig": "bench 2", "operator": "A. B."}, "<test>")


# -- T-matrix CSV ------------------------------------------------------------------------
@pytest.mark.parametrize("sigma", [True, False])
def test_tmatrix_round_trip_is_exact(tmp_path, sigma):
    data = random_data(np.random.default_rng(1), sigma=sigma)
    path = tmp_path / "T.csv"
    m.write_tmatrix_csv(path, data, metadata={"note": "round trip"})
    back = m.read_tmatrix_csv(path)
    assert np.array_equal(back.heat_input, data.heat_input)
    assert np.array_equal(back.freq, data.freq)
    assert np.array_equal(back.T, data.T)
    if sigma:
        assert np.array_equal(back.sigma, data.sigma)
    else:
        assert back.sigma is None
    assert back.metadata == {"convention": "exp(-iwt)", "rig": "bench 2", "operator": "A. B.", "note": "round trip"}
    assert path.read_text().startswith("# convention = exp(-iwt)\n")
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left


def test_tmatrix_helpers():
    data = random_data(np.random.default_rng(2), sigma=False)
    assert data.heat_inputs.tolist() == [0.0, 20.0, 40.5]
    sub = data.select(heat_input=20)
    assert len(sub) == 4 and np.all(sub.heat_input == 20.0)
    assert np.array_equal(sub.T, data.T[4:8])
    assert data.frequencies.size == 12 and np.all(np.diff(data.frequencies) > 0)
    with pytest.raises(KeyError, match="have"):
        data.select(heat_input=10)


def test_columns_any_order_and_single_sigma(tmp_path):
    cols = HEADER.split(",")
    vals = ROW.split(",")
    order = [9, 0, 3, 1, 2, 8, 4, 7, 5, 6]
    sig = ["sigma_Tpp", "sigma_Tpu_re", "sigma_Tpu_im", "sigma_Tup", "sigma_Tuu"]
    text = (
        ",".join([cols[i] for i in order] + sig)
        + "\n"
        + ",".join([vals[i] for i in order] + ["0.01", "10", "20", "1e-9", "0.02"])
        + "\n"
    )
    d = m.read_tmatrix_csv(write(tmp_path, text))
    assert d.T[0, 0, 1] == complex(-5.02e4, 2.07e5) and d.T[0, 1, 1] == complex(0.95, 0.01)
    assert d.sigma.shape == (1, 2, 2, 2)
    assert d.sigma[0, 0, 0].tolist() == [0.01, 0.01]
    assert d.sigma[0, 0, 1].tolist() == [10.0, 20.0]


#: ROW as exp(+iwt) data: its imaginary parts negated
ROW_PLUS = "0,50,0.9121,0.0177,-5.02e4,-2.07e5,1e-6,-2e-7,0.95,-0.01"


def test_plus_convention_is_conjugated(tmp_path):
    minus = m.read_tmatrix_csv(write(tmp_path, f"# convention = exp(-iwt)\n{HEADER}\n{ROW}\n", "a.csv"))
    plus = m.read_tmatrix_csv(
        write(
            tmp_path,
            f"# convention = exp(+iwt)\n{HEADER},sigma_Tpp,sigma_Tpu,sigma_Tup,sigma_Tuu\n{ROW_PLUS},1,2,3,4\n",
            "b.csv",
        )
    )
    assert np.array_equal(plus.T, minus.T)
    assert plus.sigma[0, :, :, 0].tolist() == [[1, 2], [3, 4]]  # sigma unchanged
    assert plus.metadata["convention"] == "exp(-iwt)"
    assert plus.metadata["original_convention"] == "exp(+iwt)"


BAD = {
    # name: (file text, line number expected in the message, words expected)
    "empty": ("", 1, "empty"),
    "only_metadata": ("# a = b\n", 1, "header"),
    "no_header": (f"{ROW}\n", 1, "missing header"),
    "missing_column": (HEADER.replace(",Tuu_im", "") + "\n" + ROW.rsplit(",", 1)[0] + "\n", 1, "Tuu_im"),
    "unknown_column": (f"{HEADER},temperature\n{ROW},3\n", 1, "temperature"),
    "bad_sigma_name": (f"{HEADER},sigma_Txx\n{ROW},3\n", 1, "sigma_Txx"),
    "non_numeric": (f"# x = 1\n{HEADER}\n{ROW.replace('0.9121', 'abc')}\n", 3, "abc"),
    "empty_cell": (f"{HEADER}\n{ROW.replace('0.9121', '')}\n", 2, "expected a number"),
    "nan": (f"{HEADER}\n{ROW}\n{ROW.replace('50,', '60,').replace('0.95', 'nan')}\n", 3, "finite"),
    "inf": (f"{HEADER}\n{ROW.replace('2.07e5', 'inf')}\n", 2, "finite"),
    "negative_Q": (f"{HEADER}\n{ROW.replace('0,50', '-1,50')}\n", 2, "heat input"),
    "zero_freq": (f"{HEADER}\n{ROW.replace('0,50', '0,0')}\n", 2, "freq_Hz"),
    "too_few_fields": (f"{HEADER}\n{ROW.rsplit(',', 1)[0]}\n", 2, "9 fields; expected 10"),
    "too_many_fields": (f"{HEADER}\n{ROW},1\n", 2, "11 fields; expected 10"),
    "duplicate": (f"{HEADER}\n{ROW}\n\n{ROW}\n", 4, "duplicate"),
    "zero_sigma": (f"{HEADER},sigma_Tpp,sigma_Tpu,sigma_Tup,sigma_Tuu\n{ROW},1,0,1,1\n", 2, "sigma_Tpu"),
    "negative_sigma": (f"{HEADER},sigma_Tpp,sigma_Tpu,sigma_Tup,sigma_Tuu\n{ROW},1,1,1,-2\n", 2, "sigma_Tuu"),
    "partial_sigma": (f"{HEADER},sigma_Tpp\n{ROW},1\n", 1, "sigma"),
    "sigma_re_only": (f"{HEADER},sigma_Tpp_re,sigma_Tpu,sigma_Tup,sigma_Tuu\n{ROW},1,1,1,1\n", 1, "sigma_Tpp_im"),
    "bad_convention": (f"# convention = exp(iwt)x\n{HEADER}\n{ROW}\n", 1, "convention"),
    "header_only": (f"{HEADER}\n", 1, "no data rows"),
    "metadata_after_header": (f"{HEADER}\n# a = 1\n{ROW}\n", 2, "before"),
    "duplicate_key": (f"# a = 1\n# a = 2\n{HEADER}\n{ROW}\n", 2, "twice"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_tmatrix_input_names_file_and_line(tmp_path, case):
    text, line, words = BAD[case]
    path = write(tmp_path, text, f"bad_{case}.csv")
    with pytest.raises(m.MeasurementError) as err:
        m.read_tmatrix_csv(path)
    msg = str(err.value)
    assert f"bad_{case}.csv" in msg and f"line {line}:" in msg and words in msg, msg


def test_failed_write_leaves_target_untouched(tmp_path, monkeypatch):
    path = tmp_path / "T.csv"
    path.write_text("old content\n")
    data = random_data(np.random.default_rng(3))
    data.T[2, 1, 0] = np.nan
    with pytest.raises(m.MeasurementError, match="row 2"):
        m.write_tmatrix_csv(path, data)
    data.T[2, 1, 0] = 1.0
    data.sigma[5, 0, 0, 1] = 0.0
    with pytest.raises(m.MeasurementError, match="sigma"):
        m.write_tmatrix_csv(path, data)
    data.sigma[5, 0, 0, 1] = 1.0
    with pytest.raises(m.MeasurementError, match="metadata"):
        m.write_tmatrix_csv(path, data, metadata={"bad=key": 1})

    def broken_replace(src, dst):  # a failure after the temporary file is written
        raise OSError("disk full")

    monkeypatch.setattr(m.os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        m.write_tmatrix_csv(path, data)
    assert path.read_text() == "old content\n"
    assert list(tmp_path.iterdir()) == [path]


def test_duplicate_rows_rejected_before_writing(tmp_path):
    data = random_data(np.random.default_rng(4), sigma=False)
    data.freq[1] = data.freq[0]
    with pytest.raises(m.MeasurementError, match="duplicate of row 0"):
        m.write_tmatrix_csv(tmp_path / "T.csv", data)
    assert not any(tmp_path.iterdir())


# -- surface impedance -----------------------------------------------------------------
def test_impedance_csv(tmp_path):
    text = (
        "# thickness = 0.0499\n# convention = exp(+iwt)\n# T_ambient = 294.65\n"
        "freq_Hz,Zs_re,Zs_im\n200,0.75,-4.5\n220,0.714,-4.16\n"
    )
    d = m.read_impedance_csv(write(tmp_path, text))
    assert d.thickness == 0.0499 and d.T_ambient == 294.65 and d.p_ambient is None
    assert d.freq.tolist() == [200, 220]
    assert d.Zs.tolist() == [0.75 + 4.5j, 0.714 + 4.16j]


@pytest.mark.parametrize(
    "text, where",
    [
        ("freq_Hz,Zs_re,Zs_im\n200,1,1\n", "'thickness'"),
        ("# thickness = -1\nfreq_Hz,Zs_re,Zs_im\n200,1,1\n", "line 1:"),
        ("# thickness = 0.05\n# p_ambient = abc\nfreq_Hz,Zs_re,Zs_im\n200,1,1\n", "line 2:"),
        ("# thickness = 0.05\nfreq_Hz,Zs_re,Zs_im\n200,1,1\n200,1,2\n", "line 4:"),
    ],
)
def test_bad_impedance_input(tmp_path, text, where):
    with pytest.raises(m.MeasurementError) as err:
        m.read_impedance_csv(write(tmp_path, text, "imp.csv"))
    assert "imp.csv" in str(err.value) and where in str(err.value), str(err.value)


def test_atalla_panneton_table():
    s = m.atalla_panneton_samples()
    assert sorted(s) == ["fibrous1", "fibrous2", "foam1", "foam2"]
    f1 = s["foam1"]
    assert f1["thickness_thin"] == 0.04992 and f1["thickness_thick"] == 0.0987
    assert (f1["sigma"], f1["phi"], f1["alpha_inf"]) == (4971, 0.97, 1.31)
    assert f1["Lambda"] == pytest.approx(123.19e-6) and f1["Lambda_prime"] == pytest.approx(289.54e-6)
    assert f1["T"] == pytest.approx(294.65) and f1["P0"] == 99200.0 and f1["frame"] == "rigid"
    assert s["foam2"]["thickness_thick"] == 0.06877 and s["fibrous1"]["thickness_thin"] == 0.02337
    assert s["fibrous2"]["thickness_thick"] is None and s["fibrous2"]["frame"] == "limp"
    assert s["fibrous2"]["P0"] == 97700.0 and s["fibrous1"]["sigma"] == 21235
    s["foam1"]["phi"] = 0.0  # a fresh copy each call
    assert m.atalla_panneton_samples()["foam1"]["phi"] == 0.97


@pytest.mark.parametrize("name", ["foam1", "foam2", "fibrous1", "fibrous2"])
def test_atalla_panneton_files_load(name):
    folder = measured_folder("atalla_panneton_2005")
    table = m.atalla_panneton_samples()[name]
    thin, thick = m.load_atalla_panneton(name, folder)
    for d, thickness in ((thin, table["thickness_thin"]), (thick, table["thickness_thick"])):
        assert len(d) == 71
        assert d.freq[0] == 200 and d.freq[-1] == 1600 and np.allclose(np.diff(d.freq), 20)
        assert d.thickness == thickness
        assert d.T_ambient == table["T"] and d.p_ambient == table["P0"]
        assert np.all(np.isfinite(d.Zs)) and d.metadata["convention"] == "exp(-iwt)"
    # thin rigid-backed layer is stiffness-like: Im Zs < 0 in exp(+jwt), > 0 in exp(-iwt)
    assert np.all(thin.Zs.imag[thin.freq <= 1000] > 0)


def test_atalla_panneton_bundled_and_missing_folder(tmp_path):
    """The default folder is the bundled copy (the same data as an explicit folder); a
    folder that does not exist is named in the error."""
    bundled = m.load_atalla_panneton("foam1")
    given = m.load_atalla_panneton("foam1", measured_folder("atalla_panneton_2005"))
    assert [d.Zs.tolist() for d in bundled] == [d.Zs.tolist() for d in given]
    with pytest.raises(FileNotFoundError, match="nowhere"):
        m.load_atalla_panneton("foam1", folder=tmp_path / "nowhere")
    with pytest.raises(KeyError, match="foam1"):
        m.load_atalla_panneton("foam3")


def test_read_atalla_panneton_ignores_leftover_columns(tmp_path):
    p = write(tmp_path, "f,Re,Im,,,\n200,0.75,-4.5,-0.036,0.34,-4.16\n220,0.714,-4.16,,,\n", "foam.csv")
    d = m.read_atalla_panneton(p, 0.05, 293.0, 1e5)
    assert d.Zs.tolist() == [0.75 + 4.5j, 0.714 + 4.16j] and d.thickness == 0.05


# -- scattering matrices ---------------------------------------------------------------
def duct_T(k, Zc, L):
    c, s = np.cos(k * L), np.sin(k * L)
    return m._matrix(c, 1j * Zc * s, 1j * s / Zc, c)


def test_scattering_transfer_are_inverses():
    rng = np.random.default_rng(5)
    n = 50
    S = rng.normal(size=(n, 2, 2)) + 1j * rng.normal(size=(n, 2, 2))
    k = rng.uniform(0.5, 10, n) + 1j * rng.uniform(0, 0.1, n)  # lossy k too
    Zc, d1, d2 = 1.5e6, 0.07, 0.11
    T = m.scattering_to_transfer(S, k, Zc, d1, d2)
    assert np.max(np.abs(m.transfer_to_scattering(T, k, Zc, d1, d2) - S)) < 1e-12
    # a general (non-reciprocal, lossy) T of O(1) dimensionless coefficients
    Y = np.eye(2) + 0.3 * (rng.normal(size=(n, 2, 2)) + 1j * rng.normal(size=(n, 2, 2)))
    T2 = Y * np.array([[1, Zc], [1 / Zc, 1]])
    back = m.scattering_to_transfer(m.transfer_to_scattering(T2, k, Zc, d1, d2), k, Zc, d1, d2)
    assert np.max(np.abs(back / np.array([[1, Zc], [1 / Zc, 1]]) - Y)) < 1e-12


def test_uniform_duct_scattering():
    k, Zc, L = np.linspace(0.1, 20, 40), 1.43e6, 0.25
    S = m.transfer_to_scattering(duct_T(k, Zc, L), k, Zc, 0.0, 0.0)
    assert np.max(np.abs(S[:, 0, 0])) < 1e-12 and np.max(np.abs(S[:, 1, 1])) < 1e-12
    assert np.allclose(np.abs(S[:, 1, 0]), 1, atol=1e-12)
    assert np.allclose(S[:, 1, 0], np.exp(1j * k * L), atol=1e-12)  # A travels +x: phase e^{ikL}
    assert np.allclose(S[:, 0, 1], S[:, 1, 0], atol=1e-12)  # reciprocal
    # reference planes d1, d2 outside the faces add their propagation phase
    S = m.transfer_to_scattering(duct_T(k, Zc, L), k, Zc, 0.05, 0.1)
    assert np.allclose(S[:, 1, 0], np.exp(1j * k * (L + 0.15)), atol=1e-12)
    assert np.max(np.abs(S[:, 0, 0])) < 1e-12


def scattering_text(S, freq, convention="exp(-iwt)", extra=""):
    lines = [
        "# tube_radius = 0.0167",
        "# T_ambient = 293.15",
        "# p_ambient = 101325",
        "# ref_upstream = 0.05",
        "# ref_downstream = 0.08",
        f"# convention = {convention}",
        *extra.splitlines(),
        ",".join(m.SCATTERING_COLUMNS),
    ]
    for f, s in zip(freq, S):
        lines.append(",".join(repr(float(v)) for v in [f] + [p for z in s.reshape(-1) for p in (z.real, z.imag)]))
    return "\n".join(lines) + "\n"


def test_read_scattering_csv(tmp_path):
    g = GASES["air"]
    c0 = math.sqrt(g.gamma * g.R_gas * 293.15)
    Zc = 101325 / (g.R_gas * 293.15) * c0 / (math.pi * 0.0167**2)
    freq = np.array([50.0, 120.0, 400.0])
    k = 2 * np.pi * freq / c0
    T_true = duct_T(k, Zc, 0.2)
    S = m.transfer_to_scattering(T_true, k, Zc, 0.05, 0.08)
    d = m.read_scattering_csv(write(tmp_path, scattering_text(S, freq, extra="# Q_W = 12.5"), "s.csv"))
    assert isinstance(d, m.TMatrixData) and d.heat_input.tolist() == [12.5] * 3
    assert np.allclose(d.T, T_true, rtol=1e-12, atol=0)
    plus = m.read_scattering_csv(write(tmp_path, scattering_text(S.conj(), freq, "exp(+iwt)"), "p.csv"))
    assert np.allclose(plus.T, T_true, rtol=1e-12, atol=0) and np.all(plus.heat_input == 0)
    no_radius = scattering_text(S, freq).replace("# tube_radius = 0.0167\n", "")
    with pytest.raises(m.MeasurementError, match=r"s2\.csv.*'tube_radius'"):
        m.read_scattering_csv(write(tmp_path, no_radius, "s2.csv"))
    with pytest.raises(m.MeasurementError, match=r"s3\.csv, line 7: gas = 'radon'"):
        m.read_scattering_csv(write(tmp_path, scattering_text(S, freq, extra="# gas = radon"), "s3.csv"))
