"""Outputs: a full disk or a lost permission is an ``error:`` line with the older output
intact; a file beside an output that tawarp did not write is never replaced; an
interrupted run's temporaries are removed by the next run that writes the same output."""

import subprocess
import sys
from collections import namedtuple

from tawarp.cli import main

SWEEP = ["sweep", "rvc_foam", "--var", "Q=1:18:3", "--device", "cpu", "--quiet"]
DESIGN = [
    "design",
    "rvc_foam",
    "--var",
    "Q=1:18",
    "--var",
    "stack.length=0.01:0.1",
    "--trials",
    "16",
    "--batch",
    "8",
    "--device",
    "cpu",
    "--quiet",
    "--no-plots",
]

# the HDF5 writes of a sweep fail as on a full disk
_FULL_DISK = """
import errno, sys
import h5py
def full(self, *a, **k):
    raise OSError(errno.ENOSPC, "No space left on device")
h5py.Dataset.__setitem__ = full
from tawarp.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _debris(folder):
    return sorted(p.name for p in folder.rglob(".*") if p.name.endswith((".tmp", ".old")))


def test_a_full_disk_during_a_sweep_is_an_error_line_and_the_older_file_stays(tmp_path):
    """It printed an h5py traceback and ended with SIGSEGV (HDF5's exit handler flushed the
    failed file again). In a child process: a crash is an exit code there."""
    (tmp_path / "res.nc").write_text("older")
    run = subprocess.run(
        [sys.executable, "-c", _FULL_DISK, *SWEEP, "-o", "res.nc"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 2, run.stderr
    assert run.stderr.strip().splitlines()[-1] == (
        "tawarp sweep: error: res.nc: could not be written (No space left on device); the older file is kept"
    )
    assert (tmp_path / "res.nc").read_text() == "older"
    assert not (tmp_path / "res.json").exists() and _debris(tmp_path) == []


def _little_space(monkeypatch, free):
    import shutil

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(free, 0, free))


def test_too_little_space_is_refused_before_writing(tmp_path, monkeypatch, capsys):
    """HDF5 cannot give up a file whose writing failed, so the space is checked first."""
    _little_space(monkeypatch, 1000)
    (tmp_path / "res.nc").write_text("older")
    assert main([*SWEEP, "-o", str(tmp_path / "res.nc")]) == 2
    err = capsys.readouterr().err
    assert "tawarp sweep: error: " in err and "res.nc: the disk has 0.001 MB free" in err
    assert "nothing was written" in err
    assert (tmp_path / "res.nc").read_text() == "older" and _debris(tmp_path) == []
    assert main([*DESIGN, "-o", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert "tawarp design: error: " in err and ".h5: the disk has 0.001 MB free" in err
    assert _debris(tmp_path) == []


def test_a_permission_error_is_an_error_line(tmp_path, monkeypatch, capsys):
    """The rename into place refused (a folder made read-only meanwhile)."""
    import errno
    import os

    def refused(src, dst):
        raise PermissionError(errno.EACCES, "Permission denied")

    (tmp_path / "res.nc").write_text("older")
    monkeypatch.setattr(os, "replace", refused)
    assert main([*SWEEP, "-o", str(tmp_path / "res.nc")]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"tawarp sweep: error: {tmp_path / 'res.nc'}: could not be written (Permission denied); the older file is kept"
    )
    assert (tmp_path / "res.nc").read_text() == "older" and _debris(tmp_path) == []


# -- files beside an output ----------------------------------------------------------------
def test_a_users_file_beside_the_sweep_is_refused_before_anything_is_written(tmp_path, capsys):
    """``echo '{"fit":1}' > res.json; tawarp sweep ... -o res.nc`` replaced res.json."""
    (tmp_path / "res.json").write_text('{"fit": 1}\n')
    assert main([*SWEEP, "-o", str(tmp_path / "res.nc")]) == 2
    err = capsys.readouterr().err
    assert f"tawarp sweep: error: {tmp_path / 'res.json'}: exists and tawarp did not write it" in err
    assert (tmp_path / "res.json").read_text() == '{"fit": 1}\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res.json"]
    # its own summary is replaced by the next run
    (tmp_path / "res.json").unlink()
    assert main([*SWEEP, "-o", str(tmp_path / "res.nc")]) == 0
    assert main([*SWEEP, "-o", str(tmp_path / "res.nc")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res.json", "res.nc"]


def test_a_users_figure_beside_the_ranking_is_refused(tmp_path, capsys):
    """``tawarp rank -o plot.json`` replaced a user's plot.png."""
    from PIL import Image

    Image.new("RGB", (4, 4)).save(tmp_path / "plot.png")
    before = (tmp_path / "plot.png").read_bytes()
    assert (
        main(
            [
                "rank",
                "--materials",
                "ceramic,mesh",
                "--Q",
                "5",
                "--samples",
                "16",
                "--device",
                "cpu",
                "--quiet",
                "-o",
                str(tmp_path / "plot.json"),
            ]
        )
        == 2
    )
    assert "plot.png: exists and tawarp did not write it" in capsys.readouterr().err
    assert (tmp_path / "plot.png").read_bytes() == before and not (tmp_path / "plot.json").exists()
    (tmp_path / "plot.png").unlink()
    for _ in range(2):  # tawarp's own figure is recognised and replaced
        assert (
            main(
                [
                    "rank",
                    "--materials",
                    "ceramic,mesh",
                    "--Q",
                    "5",
                    "--samples",
                    "16",
                    "--device",
                    "cpu",
                    "--quiet",
                    "-o",
                    str(tmp_path / "plot.json"),
                ]
            )
            == 0
        )


def test_forward_and_design_keep_a_users_files(tmp_path, capsys):
    (tmp_path / "T_temperature.png").write_bytes(b"mine")
    assert (
        main(["forward", "ceramic", "--freqs", "100", "-o", str(tmp_path / "T.csv"), "--device", "cpu", "--quiet"]) == 2
    )
    assert "T_temperature.png: exists and tawarp did not write it" in capsys.readouterr().err
    assert not (tmp_path / "T.csv").exists() and (tmp_path / "T_temperature.png").read_bytes() == b"mine"
    assert (
        main(
            [
                "forward",
                "ceramic",
                "--freqs",
                "100",
                "-o",
                str(tmp_path / "T.csv"),
                "--device",
                "cpu",
                "--quiet",
                "--no-plots",
            ]
        )
        == 0
    )  # no figure asked for: nothing beside it is touched
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "design.json").write_text("[]")
    assert main([*DESIGN, "-o", str(tmp_path / "d")]) == 2
    assert "design.json: exists and tawarp did not write it" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "d").iterdir()) == ["design.json"]


def test_what_tawarp_writes_is_recognised_as_its_own(tmp_path):
    from tawarp.io import write_json, written_by_tawarp
    from tawarp.plots import plt, save

    fig, _ = plt.subplots()
    assert written_by_tawarp(save(fig, tmp_path / "f.png"))
    assert written_by_tawarp(write_json(tmp_path / "a.json", {"generator": "tawarp sweep"}))
    assert not written_by_tawarp(write_json(tmp_path / "b.json", {"fit": 1}))
    assert not written_by_tawarp(write_json(tmp_path / "c.json", [1]))
    (tmp_path / "d.png").write_bytes(b"\x89PNG not really")
    assert not written_by_tawarp(tmp_path / "d.png") and not written_by_tawarp(tmp_path / "missing.json")


# -- temporaries of killed runs ----------------------------------------------------------
def test_a_killed_runs_temporaries_are_removed_by_the_next_run(tmp_path):
    """After SIGKILL (or SIGTERM) of a sweep its ``.res.nc.*.tmp`` file stayed forever."""
    import os
    import signal
    import tempfile
    import time

    from tawarp.io import remove_stale_temporaries

    # the sweep's messages into an unnamed file: unread while it runs, a pipe could fill and
    # stall it, and a file in tmp_path would be one more entry there
    messages = tempfile.TemporaryFile("w+")
    child = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from tawarp.cli import main; sys.exit(main())",
            *SWEEP[:2],
            "--var",
            "Q=1:18:100",
            "--var",
            "stack.length=0.01:0.1:100",
            "--chunk",
            "16",
            "-o",
            "res.nc",
        ],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=messages,
    )
    try:
        deadline = time.monotonic() + 240
        while not list(tmp_path.glob(".res.nc.*.tmp")) and time.monotonic() < deadline and child.poll() is None:
            time.sleep(0.05)
        ended = child.poll()  # (the sweep ended before it was killed: its exit status and messages say why)
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait(timeout=60)
    messages.seek(0)
    err = messages.read()
    messages.close()
    left = list(tmp_path.glob(".res.nc.*.tmp"))
    assert len(left) == 1 and f".res.nc.{child.pid}@" in left[0].name, (ended, err[-2000:])
    # a temporary of a live writer (this process) is left alone
    live = tmp_path / f".res.nc.{os.getpid()}@{left[0].name.split('@')[1]}"
    live.write_text("")
    assert main([*SWEEP, "-o", str(tmp_path / "res.nc")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["res.nc", "res.json", live.name])
    assert remove_stale_temporaries(tmp_path / "res.nc") == []


# -- the fitted-temperature figure ---------------------------------------------------------
def test_the_fitted_temperature_figure_is_drawn_at_the_measured_heat_inputs(tmp_path, monkeypatch):
    """It was drawn at Q = 9 W whatever the data held (beyond the RVC foam's 5 and 7 W)."""
    import numpy as np

    from tawarp import plots
    from tawarp.fit.characterize import characterize, write_figures
    from tawarp.measure.synthetic import make_paper_data
    from tawarp.model.forward import ForwardSettings, steady_temperature

    settings = ForwardSettings(cells=8, device="cpu")
    data = make_paper_data("rvc_foam", n_freqs=12, cells=12, seed=0, heat_inputs=[0.0, 5.0, 7.0], device="cpu")
    ch = characterize(data, "rvc_foam", settings=settings, warn=False, restarts=0)
    drawn = {}
    monkeypatch.setattr(
        plots, "plot_temperature", lambda x, curves, path, **kw: drawn.update(x=x, curves=curves, **kw) or path
    )
    write_figures(ch, tmp_path / "fit")
    assert list(drawn["curves"]) == ["Q = 5 W", "Q = 7 W"] and "measured heat inputs" in drawn["title"]
    for T, Q, h in zip(drawn["curves"].values(), (5.0, 7.0), ch.step2.values):
        direct, _ = steady_temperature(ch.core, drawn["x"], Q, params=dict(zip(ch.heat_names, h)), settings=settings)
        np.testing.assert_array_equal(T, direct[0])


def test_a_users_figure_beside_the_fit_is_refused_before_fitting(tmp_path, capsys):
    from importlib import resources

    data = resources.files("tawarp") / "data" / "measured" / "ceramic_hidden_effect.csv"
    (tmp_path / "fit_h.png").write_bytes(b"mine")
    assert main(["fit", str(data), "--device", "cpu", "--quiet", "-o", str(tmp_path / "fit.json")]) == 2
    assert (
        "fit_h.png: exists and tawarp did not write it; it would be replaced by a figure of the fit"
        in capsys.readouterr().err
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit_h.png"]


def test_fit_json_carries_tawarps_mark_and_is_still_read(tmp_path):
    """``tawarp fit -o fit.json`` marks its JSON as tawarp's (``"generator": "tawarp fit"``),
    as the loop's report.json and the demo's fits carry theirs; the reader of a fit.json
    (a catalogue material) takes the marked file, its values the file's."""
    import json
    from importlib import resources

    import pytest

    from tawarp.design.catalogue import Material
    from tawarp.io import written_by_tawarp

    data = resources.files("tawarp") / "data" / "measured" / "ceramic_hidden_effect.csv"
    out = tmp_path / "fit.json"
    assert main(["fit", str(data), "--device", "cpu", "--quiet", "--no-plots", "-o", str(out)]) == 0
    obj = json.loads(out.read_text())
    assert obj.get("generator") == "tawarp fit", "fit.json carries no generator mark"
    assert written_by_tawarp(out)
    material = Material.from_fit_json(out)
    assert material.porosity == pytest.approx(obj["parameters"]["stack.porosity"]["value"], rel=1e-12)
    assert material.pore_radius == pytest.approx(obj["parameters"]["stack.pore_radius"]["value"], rel=1e-12)


def test_a_full_disk_leaves_no_half_line_in_the_study_journal(tmp_path, monkeypatch):
    """A journal append cut short by a full disk left a partial JSON line: every later
    reader of the study, and every worker resuming it, would stop on it."""
    import errno
    import os

    import pytest

    from tawarp.design.storage import JournalFile

    journal = JournalFile(str(tmp_path / "study.journal"))
    journal.append_logs([{"op_code": 0, "worker_id": "w", "study_name": "s", "directions": [1]}])
    before = (tmp_path / "study.journal").read_bytes()
    write = os.write

    def half_then_full(fd, data):  # the first write gets half through, the next finds the disk full
        if len(data) > 8:
            return write(fd, bytes(data[: len(data) // 2]))
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "write", half_then_full)
    with pytest.raises(
        OSError,
        match=r"study\.journal: could not be written \(No space left on device\); the "
        r"trials stored before are kept",
    ):
        journal.append_logs([{"op_code": 4, "worker_id": "w", "study_id": 0, "payload": "x" * 100}])
    monkeypatch.setattr(os, "write", write)
    assert (tmp_path / "study.journal").read_bytes() == before
    assert len(list(journal.read_logs(0))) == 1


def test_the_loop_keeps_a_users_files_and_replaces_its_own(tmp_path, capsys):
    """``tawarp loop -o OUT`` replaced a report.md of the user's in OUT."""
    from tawarp.io import written_by_tawarp

    loop = ["loop", "atalla:foam1", "--device", "cpu", "--quiet", "-o", str(tmp_path)]
    assert main(loop) == 0
    written = sorted(p.name for p in tmp_path.iterdir())
    assert {"report.json", "report.md", "residuals.png"} <= set(written)
    assert all(written_by_tawarp(tmp_path / name) for name in written)
    assert (tmp_path / "report.md").read_text().startswith("# tawarp loop report\n<!-- generator = tawarp loop -->\n")
    assert main(loop) == 0  # its own outputs are replaced
    (tmp_path / "report.md").write_text("mine\n")
    (tmp_path / "notes.md").write_text("# tawarp loop report\n")
    assert not written_by_tawarp(tmp_path / "notes.md")
    assert main(loop) == 2
    err = capsys.readouterr().err
    assert f"tawarp loop: error: {tmp_path / 'report.md'}: exists and tawarp did not write it" in err
    assert (tmp_path / "report.md").read_text() == "mine\n"


def test_the_demo_keeps_a_users_files_and_replaces_its_own(tmp_path, monkeypatch, capsys):
    """``tawarp demo -o OUT`` replaced a summary.json of the user's in OUT, and its own files
    carried no mark that a later demo could recognise."""
    from tawarp.cli import demo
    from tawarp.io import written_by_tawarp

    # the fits, the loop and the onset are slow: their files are checked on their own below
    for step in ("demo_fit", "demo_loop", "demo_onset"):
        monkeypatch.setattr(demo, step, lambda *a, **k: None)
    run = ["demo", "--device", "cpu", "--quiet", "-o", str(tmp_path)]
    assert main(run) == 0
    written = set(tmp_path.iterdir())
    assert tmp_path / "summary.json" in written and written <= set(demo.demo_outputs(tmp_path))
    assert all(written_by_tawarp(p) for p in written)
    assert main(run) == 0  # its own outputs are replaced
    (tmp_path / "loop").mkdir()
    (tmp_path / "loop" / "report.md").write_text("mine\n")

    def no_work(*a, **k):
        raise AssertionError("the demo started before it claimed its outputs")

    monkeypatch.setattr(demo, "transfer_matrices", no_work)
    assert main(run) == 2
    err = capsys.readouterr().err
    assert f"tawarp demo: error: {tmp_path / 'loop' / 'report.md'}: exists and tawarp did not write it" in err
    assert (tmp_path / "loop" / "report.md").read_text() == "mine\n"


def test_the_demos_fits_and_onset_are_its_own_outputs(tmp_path):
    from tawarp.cli.demo import demo_fit, demo_onset, demo_outputs
    from tawarp.io import written_by_tawarp

    demo_fit(tmp_path / "fit", device="cpu", quiet=True, n_freqs=8, cells=8)
    demo_onset(tmp_path / "onset.json", device="cpu", quiet=True)
    written = {*(tmp_path / "fit").iterdir(), tmp_path / "onset.json"}
    assert tmp_path / "fit" / "fit_summary.json" in written and written <= set(demo_outputs(tmp_path))
    assert [p.name for p in written if not written_by_tawarp(p)] == []
