"""Progress bars: shown on a terminal, off when output is piped or ``--quiet``."""

from __future__ import annotations

import sys

from tqdm.auto import tqdm


class SilentBar:
    """What a bar that shows nothing needs (the methods of tqdm's that the package calls):
    a silent bar is not a tqdm, whose first bar in a process makes tqdm's lock, a named
    semaphore of ``multiprocessing`` in a spawned process, which a pool's terminated
    worker (an interrupted study) leaves to the resource tracker's warning at exit."""

    def update(self, n: float = 1) -> None:
        pass

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> SilentBar:
        return self

    def __exit__(self, *exc) -> None:
        pass


def progress_bar(total: int, desc: str, enabled: bool = True, unit: str = "it"):
    """A tqdm bar where ``enabled`` and stderr is a terminal, else a :class:`SilentBar`."""
    if not (enabled and sys.stderr.isatty()):
        return SilentBar()
    return tqdm(total=total, desc=desc, unit=unit, dynamic_ncols=True, leave=False)
