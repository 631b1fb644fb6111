"""Atomic outputs: nothing half-written, no stray temporary files,
normal permissions."""

import json
import os
import stat

import numpy as np
import pytest

from tawarp.io import atomic_path, write_json, write_text


def test_write_json_is_complete_and_has_umask_permissions(tmp_path):
    old = os.umask(0o022)
    try:
        p = write_json(tmp_path / "a" / "out.json", {"x": np.arange(3), "y": np.float64(2.5), "ok": np.bool_(True)})
    finally:
        os.umask(old)
    assert json.loads(p.read_text()) == {"x": [0, 1, 2], "y": 2.5, "ok": True}
    assert stat.S_IMODE(p.stat().st_mode) == 0o644
    assert sorted(x.name for x in p.parent.iterdir()) == ["out.json"]


def test_failure_or_interrupt_leaves_the_old_file_and_no_debris(tmp_path):
    p = write_text(tmp_path / "r.md", "old\n")
    for exc in (ValueError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with atomic_path(p) as tmp:
                assert tmp.name.startswith(".r.md.") and tmp.suffix == ".tmp" and tmp.parent == p.parent
                tmp.write_text("half")
                raise exc
        assert p.read_text() == "old\n"
        assert sorted(x.name for x in tmp_path.iterdir()) == ["r.md"]


def test_a_directory_as_output_is_refused(tmp_path):
    with pytest.raises(IsADirectoryError, match="is a directory"):
        write_json(tmp_path, {})


def test_figures_are_written_atomically(tmp_path):
    from tawarp.plots import plot_temperature

    x = np.linspace(0, 1, 5)
    p = plot_temperature(x, {"a": 300 + x}, tmp_path / "t.png")
    assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["t.png"]


# the swallowed Ctrl-C is the case under test: Python reports it as "Exception ignored"
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_interrupt_guard_remembers_a_ctrl_c_that_a_callback_swallowed():
    """Python drops an exception raised inside a weakref callback ("Exception ignored in"):
    a Ctrl-C landing there was lost and a design search went on. The guard remembers it and
    raises it at the next safe point; Ctrl-C elsewhere still raises at once."""
    import gc
    import os
    import signal
    import weakref

    from tawarp.io import interrupt_guard

    class Thing:
        pass

    before = signal.getsignal(signal.SIGINT)
    with interrupt_guard() as interrupted:
        interrupted()  # nothing pressed: no-op
        t = Thing()
        weakref.finalize(t, lambda: os.kill(os.getpid(), signal.SIGINT))  # Ctrl-C inside a callback
        del t
        gc.collect()
        with pytest.raises(KeyboardInterrupt):
            interrupted()  # remembered
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)  # and raised at once as usual
            for _ in range(1000):
                pass
    assert signal.getsignal(signal.SIGINT) is before  # handler restored
