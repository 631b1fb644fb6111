"""The command line: outputs readable per docs/formats.md, bad input named, exit codes."""

import numpy as np
import pytest

from tawarp.cli import main
from tawarp.cli.common import parse_list
from tawarp.model.core import load_core
from tawarp.model.forward import transfer_matrices
from tawarp.measure.files import read_tmatrix_csv


def test_list_options():
    np.testing.assert_allclose(parse_list("30:500:100"), np.linspace(30, 500, 100))
    np.testing.assert_allclose(parse_list("30,100,250"), [30, 100, 250])
    with pytest.raises(Exception, match="start:stop:count"):
        parse_list("30:500")


def test_forward_writes_measurement_csv(tmp_path):
    out = tmp_path / "T.csv"
    assert (
        main(["forward", "mesh", "--freqs", "40,200", "--Q", "0,20", "-o", str(out), "--device", "cpu", "--quiet"]) == 0
    )
    data = read_tmatrix_csv(out)
    expected = transfer_matrices(load_core("mesh"), [40.0, 200.0], [0.0, 20.0], device="cpu").T
    # rows are (Q, freq) in Q-major order; repr() round trip is exact
    np.testing.assert_array_equal(data.T, expected.reshape(-1, 2, 2))
    np.testing.assert_array_equal(data.heat_input, [0, 0, 20, 20])
    # the core as named (a bundled name, not this installation's path: the file stays
    # readable without --core where tawarp is installed elsewhere)
    assert data.metadata["core"] == "mesh" and data.metadata["cells"] == "adaptive"
    assert (tmp_path / "T_coefficients.png").stat().st_size > 0
    assert (tmp_path / "T_temperature.png").stat().st_size > 0


def test_bad_core_exit_code_names_key(tmp_path, capsys):
    core = tmp_path / "bad.toml"
    text = (load_core("ceramic").source and open(load_core("ceramic").source).read()).replace(
        "porosity = 0.9\n", "porosity = 1.3\n", 1
    )
    core.write_text(text)
    assert main(["forward", str(core), "--freqs", "50", "-o", str(tmp_path / "T.csv"), "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert "bad.toml" in err and "porosity" in err
    assert not (tmp_path / "T.csv").exists()  # nothing half-written


def test_demo_loop_finds_the_bundled_hidden_effect(tmp_path):
    # The bundled measurement hides natural convection in the buffer tube, tbt.h_convection = 3
    # (studies/make_demo_data.py): the loop must choose it, reach the noise floor (<= 1.5 x),
    # and bring h_s back to the true 150 W/(m^2 K) within 2 std, with less drift of h_s over Q.
    from tawarp.cli.demo import demo_loop

    rep = demo_loop(tmp_path / "loop", device="cpu", quiet=True)
    assert rep["chosen_effect"] == "convection"
    c = rep["parameters_after"]["tbt.h_convection"]
    assert abs(c["value"] - 3.0) < 2 * c["std"]
    assert rep["error_after"] <= 1.5 * rep["noise_floor"] < rep["error_before"] * 1.5
    h = rep["parameters_after"]["stack.h"]
    assert abs(h["value"] - 150.0) < 2 * h["std"]
    assert rep["drift_after"]["relative_spread"]["stack.h"] < rep["drift_before"]["relative_spread"]["stack.h"]
    # unmodelled, the convection makes the buffer tube's h change with the heat input beyond
    # its uncertainty; modelled, every h is one value at both heat inputs within it
    assert rep["drift_before"]["consistency_p"]["tbt.h"] < 0.05
    assert min(rep["drift_after"]["consistency_p"].values()) > 0.05
    # report.md names an h of the final model that drifts: none here, tbt.h had the base won
    from tawarp.loop.report import report_markdown

    assert "changing with the heat input" not in report_markdown(rep)
    line = next(x for x in report_markdown(dict(rep, drift_after=rep["drift_before"])).splitlines() if "changing" in x)
    assert "tbt.h (p = " in line
    assert (tmp_path / "loop" / "report.json").exists() and (tmp_path / "loop" / "report.md").exists()


@pytest.mark.parametrize("bad", ["", ",", "30:nan:3", "inf"])
def test_empty_or_non_finite_lists_are_refused(bad):
    with pytest.raises(Exception, match="at least one finite value"):
        parse_list(bad)


def test_forward_help_shows_defaults(capsys):
    with pytest.raises(SystemExit):
        main(["forward", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "(default: 30:500:100)" in out and "(default: 0)" in out


@pytest.mark.parametrize(
    "args, say",
    [
        (["forward", "mesh", "--device", "cuda:7"], "cuda:7"),  # no GPU here, or no 8th GPU
        (["forward", "{tmp}", "--freqs", "50"], "{tmp}"),  # a directory as the core
        (["forward", "mesh", "--freqs", "50", "-o", "{tmp}/afile/T.csv"], "afile"),  # output parent is a file
    ],
)
def test_bad_paths_and_devices_give_a_message_not_a_traceback(args, say, tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    assert main(args + ["--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tawarp forward: error:") and say.replace("{tmp}", str(tmp_path)) in err
    assert "Traceback" not in err


def test_interrupt_exits_130_with_a_message(monkeypatch, capsys):
    import tawarp.cli.app as cli

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "cmd_forward", interrupted)
    assert cli.main(["forward", "mesh", "--quiet"]) == 130
    assert "interrupted" in capsys.readouterr().err


def test_quiet_prints_nothing_on_stdout(tmp_path):
    """--quiet silences Warp's banner and module-load lines too (a fresh process: Warp
    prints them at its first initialisation)."""
    import subprocess
    import sys

    code = (
        f"from tawarp.cli import main; raise SystemExit(main(['forward', 'mesh', '--freqs', '50', '--no-plots', "
        f"'-o', {str(tmp_path / 'T.csv')!r}, '--device', 'cpu', '--quiet']))"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout == ""
    assert "initialized" not in run.stderr


def test_warp_prints_its_own_lines_only_with_verbose(tmp_path):
    """Warp's banner, its module-load lines and its native "Warp CUDA warning" (a machine
    without a CUDA driver) broke the progress bars: without --verbose none is printed, on
    either stream; with it Warp's banner is there (fresh processes: Warp prints at its
    first initialisation)."""
    import subprocess
    import sys

    def run(*extra):
        code = (
            f"from tawarp.cli import main; raise SystemExit(main(['forward', 'mesh', '--freqs', '50', "
            f"'--no-plots', '-o', {str(tmp_path / 'T.csv')!r}, '--device', 'cpu', {', '.join(map(repr, extra))}]))"
        )
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False)
        assert done.returncode == 0, done.stderr
        return done.stdout + done.stderr

    plain = run()
    assert "wrote" in plain
    for line in ("Warp", "Module ", "initialized"):
        assert line not in plain, plain
    verbose = run("--verbose")
    assert "Warp" in verbose and "initialized" in verbose


def test_a_ctrl_c_that_python_drops_is_raised_again():
    """Python drops an exception raised in a weakref callback ("Exception ignored in"), and
    Warp frees its arrays in such callbacks: a Ctrl-C landing there was lost and the
    command ran on (one in three during tawarp demo). Every command runs inside
    interrupts_honoured, which raises it again in the main thread; the loop after it
    (bounded, so that a regression fails instead of hanging) never ends."""
    import gc
    import os
    import signal
    import weakref

    from tawarp.cli.common import interrupts_honoured

    class Thing:
        pass

    def work():
        t = Thing()
        weakref.finalize(t, lambda: os.kill(os.getpid(), signal.SIGINT))  # Ctrl-C inside a callback
        del t
        gc.collect()
        for _ in range(10**8):
            pass
        return "ran on"

    with pytest.raises(KeyboardInterrupt), interrupts_honoured():
        work()


def test_fit_with_an_undetermined_std_prints_it(tmp_path, capsys):
    """`tawarp fit DATA --fit stack.h` on data that do not determine h: fit.json is written
    and the summary says 'undetermined' (it ended in a traceback when the covariance was singular)."""
    from importlib import resources

    data = resources.files("tawarp") / "data" / "measured" / "ceramic_hidden_effect.csv"
    out = tmp_path / "f.json"
    assert (
        main(
            ["fit", str(data), "--core", "ceramic", "--fit", "stack.h", "--device", "cpu", "--no-plots", "-o", str(out)]
        )
        == 0
    )
    assert "undetermined" in capsys.readouterr().out and out.exists()


def test_fit_of_a_passive_core_recovers_the_layer(tmp_path, capsys):
    """A passive core (no heater) takes the kind fit of every porous segment's geometry
    (it ended in a StopIteration traceback, finding no heater). Data from the independent
    reference; the core file starts 15 % off on every parameter."""
    from tawarp import reference
    from tawarp.measure.files import TMatrixData, write_tmatrix_csv
    from tawarp.model.core import Core, Segment, dump_core

    truth = {"layer.porosity": 0.95, "layer.pore_radius": 2e-4, "layer.tortuosity": 1.1}
    segs = (
        Segment("duct_left", "duct", 0.05),
        Segment("layer", "porous", 0.03, porosity=0.95, pore_radius=2e-4, tortuosity=1.1),
        Segment("duct_right", "duct", 0.05),
    )
    core = Core(segs, radius=0.05, source="passive")
    freqs = np.linspace(100.0, 1000.0, 12)
    T = reference.transfer_matrix(core, freqs)
    write_tmatrix_csv(tmp_path / "p.csv", TMatrixData(np.zeros(12), freqs, T, source="p.csv"))
    start = core.replace(
        **{"layer.porosity": 0.95 * 0.85, "layer.pore_radius": 2e-4 * 1.15, "layer.tortuosity": 1.1 * 1.15}
    )
    (tmp_path / "start.toml").write_text(dump_core(start))
    out = tmp_path / "f.json"
    assert (
        main(
            [
                "fit",
                str(tmp_path / "p.csv"),
                "--core",
                str(tmp_path / "start.toml"),
                "--device",
                "cpu",
                "--no-plots",
                "--quiet",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    import json

    got = json.loads(out.read_text())["fits"][0]["parameters"]
    for name, v in truth.items():
        assert got[name]["value"] == pytest.approx(v, rel=1e-4), name


def test_an_inadequate_fit_says_so(tmp_path, capsys):
    """`tawarp synth mesh; tawarp fit --core ceramic` reported 'ok' on every line at a
    reduced chi^2 of ~2000; the summary must flag it."""
    csv = tmp_path / "m.csv"
    assert (
        main(
            [
                "synth",
                "mesh",
                "-o",
                str(csv),
                "--freqs",
                "30:500:12",
                "--Q",
                "0,40",
                "--cells",
                "8",
                "--device",
                "cpu",
                "--quiet",
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "fit",
                str(csv),
                "--core",
                "ceramic",
                "--cells",
                "8",
                "--device",
                "cpu",
                "--no-plots",
                "-o",
                str(tmp_path / "f.json"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "INADEQUATE FIT: reduced chi^2 = " in out


def _help(command, capsys) -> str:
    with pytest.raises(SystemExit):
        main([command, "--help"])
    return " ".join(capsys.readouterr().out.split())


def test_help_names_the_bundled_data_each_command_takes(tmp_path, capsys):
    from tawarp.measure import atalla_panneton_samples
    from tawarp.model.core import bundled, bundled_cores

    assert f"a bundled core: {', '.join(bundled_cores())}" in _help("forward", capsys)
    assert "foam_sample" in bundled_cores()
    assert f"atalla:NAME ({', '.join(sorted(atalla_panneton_samples()))})" in _help("loop", capsys)
    assert "fibrous2" in atalla_panneton_samples()
    assert f"a bundled engine: {', '.join(bundled('engines'))}" in _help("onset", capsys)
    # design takes a network engine file, sweep does not (it refuses traveling_wave)
    assert "network engine file (traveling_wave)" in _help("design", capsys)
    assert "network" not in _help("sweep", capsys).split("options:")[0]
    assert main(["sweep", "traveling_wave", "--var", "stack.length=0.01:0.1:3", "-o", str(tmp_path / "s.nc")]) == 2


def test_every_option_has_help():
    import argparse

    from tawarp.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    silent = [f"{name} {a.option_strings}" for name, p in sub.choices.items() for a in p._actions if not a.help]
    assert silent == []
