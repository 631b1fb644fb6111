"""Failures that must end in a clear message or go on: a design worker whose sampler
degenerated, bad files and arguments (one line naming the file and what to do)."""

from __future__ import annotations

import numpy as np
import pytest

from tawarp.design import search as search_module
from tawarp.design.samplers import make_sampler
from tawarp.design.search import search
from tawarp.design.space import DesignSpace
from tawarp.design.storage import trials_table
from tawarp.model.core import load_core


def _space():
    return DesignSpace(load_core("rvc_foam"), ["heat_input=1:18", "stack.length=0.01:0.1"])


class _DegeneratedSampler:
    """CMA-ES as it failed before its restarts: generation 2 asked as NaN points (stored
    by the search), then ``cmaes``' tell refusing them."""

    def __init__(self, *args):
        self.inner = make_sampler(*args)

    @property
    def generation(self):
        return self.inner.generation

    def ask(self, n):
        X = self.inner.ask(n)
        return np.full_like(X, np.nan) if self.inner.generation == 2 else X

    def tell(self, X, F, violation):
        if not np.all(np.isfinite(X)):
            raise AssertionError("Abs of all param values must be less than 1e+32 to avoid overflow errors")
        self.inner.tell(X, F, violation)


def test_a_worker_whose_sampler_degenerated_resumes(tmp_path, monkeypatch):
    """A lineage whose sampler degenerated (it asked NaN points: the evaluation refuses them
    before any launch, or they were stored and the sampler then failed) resumes with the
    seed and batch it was started with, to the trials asked; no point stored after it is NaN."""
    from tawarp.model.validity import ModelValidityError

    journal = str(tmp_path / "s.journal")
    with monkeypatch.context() as m:
        m.setattr(search_module, "make_sampler", lambda *a: _DegeneratedSampler(*a))
        with pytest.raises((AssertionError, ModelValidityError), match="1e\\+32|nan"):
            search(_space(), n_trials=64, batch=8, storage=journal, seed=3)
    ds = trials_table(search(_space(), n_trials=64, batch=8, storage=journal, seed=3).study)
    assert sorted(ds.generation.values.tolist()) == [g for g in range(8) for _ in range(8)]
    nan = np.isnan(ds["heat_input"].values) | np.isnan(ds["stack.length"].values)
    assert set(ds.generation.values[nan].tolist()) <= {2}


# -- files that are not what they should be -----------------------------------------------------
BUNDLED = "ceramic_hidden_effect.csv"  # T-matrices of the model, exp(-iwt), heat inputs from 0 W


def _bundled_path():
    from importlib import resources

    return resources.files("tawarp") / "data" / "measured" / BUNDLED


def _bundled_text() -> str:
    return _bundled_path().read_text()


def _header_index(lines) -> int:
    return next(i for i, line in enumerate(lines) if line.startswith("Q_W"))


def test_a_huge_field_is_named_with_its_line(tmp_path):
    """A field over the csv module's limit (128 kB) gave the csv module's traceback."""
    from tawarp.measure import MeasurementError, read_tmatrix_csv

    lines = _bundled_text().splitlines()
    h = _header_index(lines)
    lines[h + 1] += ',"' + "x" * (10 << 20) + '"'
    path = tmp_path / "big.csv"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(MeasurementError, match=rf"big\.csv, line {h + 2}: not a CSV line of numbers"):
        read_tmatrix_csv(path)


def test_a_binary_file_is_named(tmp_path):
    """A PNG given as data gave a bare utf-8 codec error, without the file's name."""
    from tawarp.measure import MeasurementError, load_measurement

    path = tmp_path / "figure.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    with pytest.raises(MeasurementError, match=r"figure\.png: not a text file \(byte 0x89 on line 1"):
        load_measurement(path)


@pytest.mark.parametrize("where", [0, 1])
def test_a_byte_order_mark_before_a_metadata_line_is_accepted(tmp_path, where):
    """A byte-order mark at the start of the file or of a later metadata line (files
    joined by hand) was taken for the header; the data read are those without it."""
    from tawarp.measure import load_measurement, read_tmatrix_csv

    text = _bundled_text()
    lines = text.splitlines()
    lines[where] = "\ufeff" + lines[where]
    path = tmp_path / "bom.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    plain = tmp_path / "plain.csv"
    plain.write_text(text)
    assert load_measurement(path, "ceramic").name == "tmatrix"
    np.testing.assert_array_equal(read_tmatrix_csv(path).T, read_tmatrix_csv(plain).T)


def _conjugated_text(text: str, convention: str | None) -> str:
    """The file's data conjugated (its imaginary parts negated; sigma columns kept), with
    the convention line replaced by ``convention`` (None: no such line)."""
    lines = [line for line in text.splitlines() if not line.startswith("# convention")]
    h = _header_index(lines)
    names = lines[h].split(",")
    flip = [j for j, name in enumerate(names) if name.endswith("_im") and not name.startswith("sigma_")]
    rows = []
    for line in lines[h + 1 :]:
        f = line.split(",")
        for j in flip:
            f[j] = repr(-float(f[j]))
        rows.append(",".join(f))
    head = ([f"# convention = {convention}"] if convention else []) + lines[: h + 1]
    return "\n".join(head + rows) + "\n"


def test_tmatrix_data_of_the_other_convention_are_named(tmp_path):
    """exp(+iwt) T-matrices read as exp(-iwt) gave an error blaming the core's pore radius.
    Below its first resonance a passive core has Im Tpu > 0 and Im Tup > 0 in exp(-iwt)
    (a duct: Tpu = i Zc sin kL, Tup = i sin(kL)/Zc): the conjugated file is refused,
    undeclared or declared exp(-iwt), naming the line to write; declared exp(+iwt) it
    reads back as the original."""
    from tawarp.measure import MeasurementError, read_tmatrix_csv

    text = _bundled_text()
    original = tmp_path / "minus.csv"
    original.write_text(text)
    for name, convention in (("undeclared.csv", None), ("declared.csv", "exp(-iwt)")):
        path = tmp_path / name
        path.write_text(_conjugated_text(text, convention))
        with pytest.raises(
            MeasurementError,
            match=r"looks like exp\(\+iwt\) data \(Im Tpu < 0 and Im Tup < 0 at "
            r"50 Hz.*'# convention = exp\(\+iwt\)'",
        ):
            read_tmatrix_csv(path)
    path = tmp_path / "plus.csv"
    path.write_text(_conjugated_text(text, "exp(+iwt)"))
    np.testing.assert_array_equal(read_tmatrix_csv(path).T, read_tmatrix_csv(original).T)


def _layer_impedance(f, d=0.05):
    """Zs / (rho0 c0) of a rigid-backed lossy layer of thickness d [m] in exp(-iwt):
    i Zc cot(k d) (pressure p = A cos k(x - d) against the wall at x = d), with a complex
    k and Zc of a foam (speed 250 m/s, 5 % loss; Zc 1.3 (1 + 0.3 i))."""
    k = 2 * np.pi * f / 250.0 * (1 + 0.05j)
    return 1j * 1.3 * (1 + 0.3j) / np.tan(k * d)


def _impedance_file(path, f, Zs, convention=None) -> None:
    head = f"# convention = {convention}\n" if convention else ""
    rows = "".join(f"{a!r},{float(z.real)!r},{float(z.imag)!r}\n" for a, z in zip(f.tolist(), Zs))
    path.write_text(head + "# thickness = 0.05\nfreq_Hz,Zs_re,Zs_im\n" + rows)


def test_impedance_data_of_the_other_convention_are_named(tmp_path):
    """A rigid-backed layer is a compliance at low frequency: Im Zs > 0, falling with
    frequency, in exp(-iwt). Its conjugate without a convention line is refused; with
    '# convention = exp(+iwt)' it reads as the layer."""
    from tawarp.measure import MeasurementError, read_impedance_csv

    f = np.linspace(200.0, 1600.0, 71)
    Zs = _layer_impedance(f)
    _impedance_file(tmp_path / "minus.csv", f, Zs)
    np.testing.assert_allclose(read_impedance_csv(tmp_path / "minus.csv").Zs, Zs, rtol=1e-15)
    _impedance_file(tmp_path / "plus.csv", f, Zs.conj())
    with pytest.raises(
        MeasurementError,
        match=r"plus\.csv: this file looks like exp\(\+iwt\) data \(Im Zs < 0 at "
        r"200 Hz.*add a line '# convention = exp\(\+iwt\)'",
    ):
        read_impedance_csv(tmp_path / "plus.csv")
    _impedance_file(tmp_path / "declared.csv", f, Zs.conj(), "exp(+iwt)")
    np.testing.assert_allclose(read_impedance_csv(tmp_path / "declared.csv").Zs, Zs, rtol=1e-15)


def test_measured_impedances_pass_the_convention_check():
    """The measured Atalla & Panneton layers (conjugated from the paper's exp(+jwt) on
    load) show the signs of exp(-iwt) data; their conjugates those of exp(+iwt)."""
    from shared_data import measured_folder

    from tawarp.measure import atalla_panneton_samples, load_atalla_panneton
    from tawarp.measure.files import impedance_convention_evidence

    folder = measured_folder("atalla_panneton_2005")
    for name, sample in atalla_panneton_samples().items():
        for d in load_atalla_panneton(name, folder):
            assert impedance_convention_evidence(d.freq, d.Zs) is None, (name, d.source)
            if d.thickness == sample["thickness_thin"]:
                assert impedance_convention_evidence(d.freq, d.Zs.conj()) is not None, (name, d.source)


def test_zero_impedance_is_named(tmp_path):
    """Zs = 0 (no layer can have it) gave "SVD did not converge" from the fit: the file is
    refused naming the line, data made in code naming the kind."""
    from tawarp.measure import (
        ImpedanceData,
        ImpedanceKind,
        MeasurementError,
        read_impedance_csv,
    )

    f = np.linspace(200.0, 1600.0, 8)
    _impedance_file(tmp_path / "zero.csv", f, np.zeros(8))
    with pytest.raises(MeasurementError, match=r"zero\.csv, line 3: Zs = 0"):
        read_impedance_csv(tmp_path / "zero.csv")
    with pytest.raises(MeasurementError, match="impedance data: every value is 0"):
        ImpedanceKind(ImpedanceData(f, np.zeros(8), thickness=0.05))


def test_transfer_matrices_of_no_core_is_a_type_error():
    """transfer_matrices(None, ...) raised AttributeError from deep inside."""
    from tawarp.model.forward import transfer_matrices

    with pytest.raises(TypeError, match="core must be a Core, e.g. load_core"):
        transfer_matrices(None, [100.0])


def test_a_database_in_a_missing_folder_is_named(tmp_path, capsys):
    """--storage sqlite:///missing/dir/x.db gave sqlalchemy's traceback."""
    from tawarp.cli import main
    from tawarp.design.storage import make_storage

    url = f"sqlite:///{tmp_path / 'missing' / 'dir' / 'x.db'}"
    with pytest.raises(ValueError, match=r"the folder '.*missing/dir' of the database does not exist; create it"):
        make_storage(url)
    assert (
        main(
            [
                "design",
                "rvc_foam",
                "--var",
                "Q=1:18",
                "--trials",
                "8",
                "--batch",
                "8",
                "--storage",
                url,
                "--device",
                "cpu",
                "--quiet",
                "-o",
                str(tmp_path / "out"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing/dir' of the database does not exist" in err
    assert not (tmp_path / "missing").exists()
    with pytest.raises(ValueError, match="not a database URL"):
        make_storage("sqlite://x:y:z//")


# -- command-line arguments ---------------------------------------------------------------------
def _refused(argv, capsys) -> str:
    """The error line of a command that must end with exit status 2 and one line on stderr."""
    from tawarp.cli import main

    assert main([*argv, "--device", "cpu", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize(
    "argv, say",
    [
        (["sweep", "rvc_foam", "--var", "stack.h=1:nan:8"], "upper bound of stack.h is nan"),
        (["design", "rvc_foam", "--var", "stack.length=0.01:nan"], "upper bound of stack.length is nan"),
        (["design", "rvc_foam", "--var", "Q=1:18", "--var", "stack.length=0.01:nan"], "stack.length is nan"),
    ],
)
def test_a_range_bound_that_is_not_finite_is_named(argv, say, tmp_path, capsys):
    out = tmp_path / ("s.nc" if argv[0] == "sweep" else "d")
    err = _refused([*argv, "-o", str(out)], capsys)
    assert err.startswith(f"tawarp {argv[0]}: error:") and say in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("materials, batch", [(None, "1"), ("ceramic,mesh,rvc_foam", "5")])
def test_a_population_too_small_for_cma_es_is_refused_before_any_output(materials, batch, tmp_path, capsys):
    # CMA-ES runs one instance per material, each needing a parent: 2 trials per material
    var = ["--var", f"material={materials}"] if materials else []
    argv = ["design", "rvc_foam", "--var", "Q=1:18", *var, "--batch", batch, "-o", str(tmp_path / "d")]
    err = _refused(argv, capsys)
    n = len(materials.split(",")) if materials else 1
    assert f"--batch {batch} too small: CMA-ES needs at least 2 trials per material ({n} materials)" in err
    assert list(tmp_path.iterdir()) == []
    from tawarp.design.search import search
    from tawarp.design.space import DesignSpace
    from tawarp.model.core import load_core

    space = DesignSpace(load_core("rvc_foam"), ["Q=1:18", *var[1:]])
    with pytest.raises(ValueError, match=f"batch {batch} too small"):
        search(space, batch=int(batch), storage=str(tmp_path / "s.journal"))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("column, value", [(1, "-50"), (0, "-5"), (10, "-0.01")])
def test_a_bad_value_of_a_file_is_shown_as_a_plain_number(column, value, tmp_path, capsys):
    lines = _bundled_text().splitlines()
    h = _header_index(lines)
    fields = lines[h + 1].split(",")
    fields[column] = value
    lines[h + 1] = ",".join(fields)
    (tmp_path / "bad.csv").write_text("\n".join(lines) + "\n")
    name = lines[h].split(",")[column]
    err = _refused(["fit", str(tmp_path / "bad.csv"), "-o", str(tmp_path / "f.json")], capsys)
    assert f"bad.csv, line {h + 2}: {name} = {float(value)!r}: expected" in err and "np." not in err


def test_a_repeated_heat_input_of_synth_is_shown_as_a_plain_number(tmp_path, capsys):
    err = _refused(["synth", "ceramic", "--Q", "10,10", "-o", str(tmp_path / "s.csv")], capsys)
    assert "(Q = 10.0 W, freq = 50.0 Hz): duplicate of row 0" in err and "np." not in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "argv, say",
    [
        (["standing_wave", "--mode", "0"], "--mode 0: expected a mode number >= 1"),
        (["traveling_wave", "--mode", "-2"], "--mode -2: expected a mode number >= 1"),
        (["traveling_wave", "--T-ratio-max", "0.5"], "--T-ratio-max 0.5: expected a ratio T_hot/T_cold > 1"),
        (["traveling_wave", "--amplitude", "-5"], "--amplitude -5: expected |p| > 0 Pa"),
        (["standing_wave", "--bracket", "1"], "--bracket 1: expected at least 2 points"),
    ],
)
def test_onset_names_an_impossible_option(argv, say, tmp_path, capsys):
    err = _refused(["onset", *argv, "-o", str(tmp_path / "o")], capsys)
    assert err.startswith(f"tawarp onset: error: {say}")
    assert list(tmp_path.iterdir()) == []


def test_onset_functions_refuse_impossible_arguments():
    from tawarp.model import network_reference as nr
    from tawarp.model.network import load_network
    from tawarp.model.onset import onset
    from tawarp.model.resonator import load_engine

    with pytest.raises(ValueError, match="mode must be >= 1, got 0"):
        onset(load_engine("standing_wave"), Q_max=10.0, mode=0)
    net = load_network("traveling_wave")
    with pytest.raises(ValueError, match=r"T_max \[K\] must be finite and above T_min"):
        nr.onset(net, 600.0 + 0j, T_max=0.5 * net.gas.T_cold)
    with pytest.raises(ValueError, match=r"amplitude \[Pa\] must be finite and > 0, got -5.0"):
        nr.profiles(net, 600.0 + 0j, amplitude=-5.0)


def test_a_negative_number_of_restarts_is_refused(tmp_path, capsys):
    from tawarp.fit.estimate import fit

    data = str(_bundled_path())
    err = _refused(["fit", data, "--restarts", "-3", "-o", str(tmp_path / "f.json")], capsys)
    assert err.startswith("tawarp fit: error: --restarts -3: expected a number of restarts >= 0")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="restarts must be >= 0, got -3"):
        fit(load_core("ceramic"), [100.0], np.eye(2).reshape(1, 4), ["stack.h"], restarts=-3)


DESIGN_Q = ["design", "rvc_foam", "--var", "Q=1:18"]
NETWORK = ["design", "traveling_wave", "--var", "regenerator.length=0.05:0.07"]
RANK = ["rank", "--materials", "ceramic,mesh", "--samples", "4"]
SWEEP = ["sweep", "rvc_foam", "--var", "stack.length=0.01:0.1:3"]
OUTPUT = {"design": "d", "rank": "r.json", "sweep": "s.nc"}


def _refused_before_writing(argv, say, tmp_path, capsys) -> str:
    err = _refused([*argv, "-o", str(tmp_path / OUTPUT[argv[0]])], capsys)
    assert err.startswith(f"tawarp {argv[0]}: error: {say}")
    assert list(tmp_path.iterdir()) == []
    return err


@pytest.mark.parametrize(
    "argv, say",
    [
        ([*DESIGN_Q, "--trials", "0"], "--trials 0: expected a number of trials >= 1"),
        ([*DESIGN_Q, "--batch", "-5"], "--batch -5: expected a population of at least 1 trial"),
        ([*DESIGN_Q, "--objectives", "gradient,foo"], "--objectives gradient,foo: unknown objective 'foo'; choose"),
        ([*DESIGN_Q, "--T-limit", "-5"], "--T-limit -5: expected a temperature limit > 0 K"),
        ([*DESIGN_Q, "--keep", "0"], "--keep 0: expected a number of best designs >= 1"),
        ([*DESIGN_Q, "--draws", "0"], "--draws 0: expected a number of parameter sets >= 1"),
        ([*DESIGN_Q, "--bracket", "1"], "--bracket 1: expected at least 2 points of the searched range"),
        ([*DESIGN_Q, "--Q-max", "-5"], "--Q-max -5: expected a heat input > 0 W"),
        ([*NETWORK, "--keep", "-1"], "--keep -1: expected a number of best designs >= 1"),
        ([*NETWORK, "--trials", "0"], "--trials 0: expected a number of trials >= 1"),
        ([*NETWORK, "--T-ratio-max", "0.5"], "--T-ratio-max 0.5: expected a ratio T_hot/T_cold > 1"),
    ],
)
def test_design_names_an_impossible_option_and_leaves_no_folder(argv, say, tmp_path, capsys):
    _refused_before_writing(argv, say, tmp_path, capsys)


def test_design_functions_refuse_impossible_arguments():
    from tawarp.design.network_design import search_network
    from tawarp.design.space import parse_variable
    from tawarp.model.network import load_network

    with pytest.raises(ValueError, match=r"T_limit \[K\] must be finite and > 0 \(None: no limit\), got -5"):
        search(_space(), n_trials=8, batch=8, T_limit=-5.0)
    net = load_network("traveling_wave")
    with pytest.raises(ValueError, match="batch and n_trials must be >= 1"):
        search_network(net, [parse_variable("regenerator.length=0.05:0.07")], n_trials=0)


@pytest.mark.parametrize(
    "argv, say",
    [
        ([*RANK, "--T-limit", "-5"], "--T-limit -5: expected a temperature limit > 0 K"),
        ([*RANK, "--segment", "nosuch"], "--segment nosuch: not a segment of "),
        ([*RANK, "--by", "onset", "--segment", "nosuch"], "--segment nosuch: not a segment of "),
        ([*RANK, "--samples", "0"], "--samples 0: expected at least 2 draws per material"),
        ([*RANK, "--by", "onset", "--Q-max", "-5"], "--Q-max -5: expected a heat input > 0 W"),
        ([*RANK, "--by", "onset", "--Q-max", "nan"], "--Q-max nan: expected a heat input > 0 W"),
        ([*RANK, "--by", "onset", "--bracket", "1"], "--bracket 1: expected at least 2 points of the searched range"),
    ],
)
def test_rank_names_an_impossible_option(argv, say, tmp_path, capsys):
    err = _refused_before_writing(argv, say, tmp_path, capsys)
    if "--segment" in argv:
        assert err.endswith("; one of duct_left, stack, hot_hx, tbt, duct_right\n")


def test_rank_materials_refuses_impossible_arguments():
    from tawarp.design.rank import rank_materials

    with pytest.raises(ValueError, match=r"T_limit \[K\] must be finite and > 0, got -5"):
        rank_materials(["ceramic"], n_samples=4, T_limit=-5.0)
    with pytest.raises(KeyError, match="no segment 'nosuch' for the materials; one of duct_left, stack"):
        rank_materials(["ceramic"], n_samples=4, segment="nosuch")


@pytest.mark.parametrize(
    "argv, say",
    [
        ([*SWEEP, "--objectives", "foo"], "--objectives foo: unknown objective 'foo'; choose from gradient"),
        ([*SWEEP, "--objectives", "gradient,foo", "--reduce", "best"], "--objectives gradient,foo: unknown objective"),
        ([*SWEEP[:3], "stack.length=0.01:0.1", "--samples", "0"], "--samples 0: expected a number of Sobol points"),
        ([*SWEEP, "--chunk", "0"], "--chunk 0: expected at least 1 point per launch"),
    ],
)
def test_sweep_names_an_impossible_option(argv, say, tmp_path, capsys):
    _refused_before_writing(argv, say, tmp_path, capsys)


def test_sweep_refuses_an_unknown_objective_without_reductions(tmp_path):
    from tawarp.design.sweep import sweep

    with pytest.raises(KeyError, match="unknown objective 'foo'"):
        sweep(DesignSpace(load_core("rvc_foam"), ["Q=1:18:3"]), tmp_path / "s.nc", objectives=["foo"])
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "argv",
    [
        ["synth", "ceramic", "-o", "s.csv"],
        ["synth", "ceramic", "--scattering=-0.05,0.04", "-o", "s.csv"],
        [*DESIGN_Q, "-o", "d"],
        [*RANK, "-o", "r.json"],
        [*SWEEP, "-o", "s.nc"],
    ],
)
def test_a_negative_seed_is_named(argv, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    err = _refused([*argv, "--seed", "-1"], capsys)
    assert err.startswith(f"tawarp {argv[0]}: error: --seed -1: expected an integer >= 0")
    assert list(tmp_path.iterdir()) == []


def _seeded_calls(tmp_path):
    """{name the error gives: a call of a public function with the seed given}: each checks
    its seed before any work (the arguments that the check precedes are placeholders)."""
    from tawarp.cli.demo import demo_fit
    from tawarp.design.catalogue import default_catalogue
    from tawarp.design.network_design import search_network
    from tawarp.design.objectives import OnsetSpec
    from tawarp.design.rank import draw_parameter_sets, rank_by_network_onset, rank_by_onset, rank_materials
    from tawarp.design.samplers import BatchCmaEs, BatchNsga2, sobol_directions, sobol_unit
    from tawarp.design.search import worker_seed
    from tawarp.design.space import parse_variable
    from tawarp.design.sweep import sweep
    from tawarp.distributed import ClusterEvaluator
    from tawarp.fit.characterize import characterize
    from tawarp.fit.estimate import fit, spread_starts
    from tawarp.measure.synthetic import make_paper_data, scattering_measurement, synthetic_tmatrix
    from tawarp.model.network import load_network
    from tawarp.tube.synthetic import sensor_measurement, sensor_signals, signals

    core = load_core("ceramic")
    net_var = [parse_variable("regenerator.length=0.05:0.07")]
    planes = dict(tube_radius=0.01, plane_upstream=-0.05, plane_downstream=0.05, length=0.1)
    return {
        "fit": lambda s: fit(core, [100.0], np.eye(2).reshape(1, 4), ["stack.h"], seed=s),
        "spread_starts": lambda s: spread_starts(core, ["stack.h"], 4, seed=s),
        "characterize": lambda s: characterize(None, core, seed=s),
        "search": lambda s: search(_space(), n_trials=8, batch=8, seed=s),
        "worker_seed": lambda s: worker_seed(s, "w0"),
        "search_network": lambda s: search_network(load_network("traveling_wave"), net_var, seed=s),
        "OnsetSpec": lambda s: OnsetSpec(seed=s),
        "draw_parameter_sets": lambda s: draw_parameter_sets([], 4, s),
        "rank_materials": lambda s: rank_materials(["ceramic"], n_samples=4, seed=s),
        "rank_by_onset": lambda s: rank_by_onset(["ceramic"], n_samples=4, seed=s),
        "rank_by_network_onset": lambda s: rank_by_network_onset(["ceramic"], n_samples=4, seed=s),
        "Material.sample: rng": lambda s: default_catalogue()["ceramic"].sample(4, s),
        "sobol_unit": lambda s: sobol_unit(4, 2, s),
        "sobol_directions": lambda s: sobol_directions(2, s),
        "BatchCmaEs": lambda s: BatchCmaEs(2, 0, 8, s, device="cpu"),
        "BatchNsga2": lambda s: BatchNsga2(2, 0, 8, s, device="cpu"),
        "sweep": lambda s: sweep(_space(), tmp_path / "s.nc", mode="sobol", n_samples=4, seed=s),
        "ClusterEvaluator.evaluate_sobol": lambda s: ClusterEvaluator.evaluate_sobol(None, 4, seed=s),
        "sensor_signals": lambda s: sensor_signals(None, None, 1024.0, 1024, (10.0, 100.0), 30.0, seed=s),
        "sensor_measurement": lambda s: sensor_measurement(None, [0.1], None, (10.0, 100.0), seed=s),
        "signals": lambda s: signals(None, 0.01, None, None, [0.1], 1024.0, 1024, (10.0, 100.0), 30.0, seed=s),
        "make_paper_data": lambda s: make_paper_data("ceramic", seed=s),
        "synthetic_tmatrix": lambda s: synthetic_tmatrix(core, seed=s),
        "scattering_measurement": lambda s: scattering_measurement(None, [100.0], seed=s, **planes),
        "demo_fit": lambda s: demo_fit(tmp_path / "demo", seed=s),
    }


@pytest.mark.parametrize("bad", [-1, 0.5])
def test_a_bad_seed_is_named_by_the_function_that_took_it(bad, tmp_path):
    """A negative or fractional seed given to a library function (the command line checks
    its own) is refused before any work by a ValueError naming the function and the
    argument, not NumPy's "expected non-negative integer"; nothing is written."""
    for name, call in _seeded_calls(tmp_path).items():
        where, _, argument = name.partition(": ")
        say = f"{where}: {argument or 'seed'} must be a non-negative integer, got {bad!r}"
        with pytest.raises(ValueError) as refused:
            call(bad)
        assert str(refused.value) == say, name
    assert list(tmp_path.iterdir()) == []


def test_a_valid_seed_gives_numpys_own_stream():
    """The shared check passes a valid seed through: its generator draws what
    ``np.random.default_rng`` draws, a Generator is used as it is, and None (fresh entropy)
    is allowed except where the seed must be an integer."""
    from tawarp.rng import checked_seed, generator

    for seed in (0, 7, np.int64(12345)):
        assert generator(seed, "f").random(5).tolist() == np.random.default_rng(seed).random(5).tolist()
    g = np.random.default_rng(3)
    assert generator(g, "f") is g
    assert checked_seed(None, "f") is None and checked_seed(np.uint32(4), "f", integer=True) == 4
    for bad in (None, g, True, "3"):
        with pytest.raises(ValueError, match="^f: seed must be a non-negative integer, got "):
            checked_seed(bad, "f", integer=True)


def test_a_relative_humidity_over_100_per_cent_is_named(tmp_path, capsys, monkeypatch):
    from importlib import resources

    text = (resources.files("tawarp") / "data" / "tube" / "e2611_two_load.toml").read_text()
    assert "\nhumidity = 0.0" in text
    (tmp_path / "wet.toml").write_text(text.replace("\nhumidity = 0.0", "\nhumidity = 140.0"))
    monkeypatch.chdir(tmp_path)
    err = _refused(["measure", "wet.toml", "-o", "w.csv"], capsys)
    assert (
        err == "tawarp measure: error: wet.toml: gas.humidity: expected a relative humidity in [0, 100] %, got 140.0\n"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["wet.toml"]
