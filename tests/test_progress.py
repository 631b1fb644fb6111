"""Progress bars (tawarp.progress): tqdm on a terminal when asked for, else a silent bar that
is no tqdm at all."""

from __future__ import annotations

import subprocess
import sys
import textwrap

from tqdm.auto import tqdm

from tawarp.progress import SilentBar, progress_bar


def test_a_bar_shows_only_when_asked_for_on_a_terminal(monkeypatch):
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False)
    assert isinstance(progress_bar(3, "piped", True), SilentBar)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert isinstance(progress_bar(3, "quiet", False), SilentBar)
    bar = progress_bar(3, "shown", True)
    try:
        assert isinstance(bar, tqdm) and not bar.disable
    finally:
        bar.close()
    with progress_bar(3, "silent", False) as silent:  # every call the package makes on a bar
        silent.update(2)
        silent.set_postfix_str("stage")
        silent.update(-1)
    silent.close()


def test_a_silent_bar_makes_no_semaphore_in_a_spawned_process():
    # tqdm's first bar in a process, a disabled one too, makes tqdm's lock: a named
    # multiprocessing semaphore where the start method is spawn, as in a study's worker
    # processes, and a pool that terminates them (an interrupted study) left it to the
    # resource tracker's warning at exit. The start method alone is set here: the same lock.
    probe = textwrap.dedent(
        """
        import multiprocessing
        multiprocessing.set_start_method("spawn")
        from tqdm.auto import tqdm
        from tawarp.progress import progress_bar
        progress_bar(3, "fits", False).close()
        print(hasattr(tqdm, "_lock"))
        tqdm(total=3, disable=True).close()
        lock = tqdm.get_lock().locks[0]
        print(lock._semlock.name is not None)
        """
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "True"]  # no lock from the silent bar; tqdm's own makes a named one
