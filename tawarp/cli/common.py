"""Helpers shared by the subcommands: list options, the common options, printing."""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import tempfile

import numpy as np

from ..measure import ImpedanceKind, load_measurement
from ..model.core import CoreError, load_core


def parse_list(text: str) -> np.ndarray:
    """A list option: ``30,100,250`` or ``start:stop:count`` (inclusive, linear); at least
    one value, all finite."""
    values = _parse_list(text)
    if values.size == 0 or not np.all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"{text!r}: expected at least one finite value, e.g. 30,100,250 or 30:500:100")
    return values


def _parse_list(text: str) -> np.ndarray:
    try:
        if ":" in text:
            parts = text.split(":")
            if len(parts) != 3:
                raise ValueError
            start, stop, count = float(parts[0]), float(parts[1]), int(parts[2])
            if count < 1:
                raise ValueError
            return np.linspace(start, stop, count)
        return np.array([float(v) for v in text.split(",") if v.strip()])
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected a comma list (30,100,250) or start:stop:count (30:500:100)"
        ) from None


def _common(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    p.add_argument("--device", default=None, help="cpu, cuda or cuda:N (default: a GPU if Warp sees one, else cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bars, banners or chatter")
    p.add_argument(
        "--verbose",
        action="store_true",
        help="let Warp print its banner, driver warnings and a line per kernel module loaded",
    )
    return p


def init_warp(verbose: bool = False, quiet: bool = False) -> None:
    """Initialize Warp for a command. Unless ``verbose``, what Warp prints on its own
    (its banner and a line per module load, at log level INFO, and the native library's
    "Warp CUDA warning: ..." on a machine without a CUDA driver, written straight to file
    descriptor 2) is kept off the terminal, where it breaks the progress bars: the log
    level becomes WARNING (ERROR with ``quiet``) and ``wp.init`` runs with descriptor 2
    captured, its text shown only if the initialization fails."""
    import warp as wp

    if verbose:
        return
    wp.config.log_level = wp.LOG_ERROR if quiet else wp.LOG_WARNING
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 2)
        try:
            wp.init()
        except BaseException:
            os.dup2(saved, 2)
            captured.seek(0)
            sys.stderr.write(captured.read().decode(errors="replace"))
            raise
        finally:
            os.dup2(saved, 2)
            os.close(saved)


@contextlib.contextmanager
def interrupts_honoured():
    """Within the block, a Ctrl-C that Python drops is raised again. Python swallows an
    exception raised in a weakref callback or ``__del__`` (it prints "Exception ignored
    in ..." through ``sys.unraisablehook``), and Warp frees its arrays in such callbacks: a
    Ctrl-C landing there was lost and the command ran on. The hook hands such a
    KeyboardInterrupt back to the main thread (``_thread.interrupt_main``) 20 ms later,
    from a timer thread: signalled at once, the main thread would raise it inside the
    hook itself, where it is dropped again; once the hook has returned it raises it at its
    next bytecode (inside another callback: dropped and handed back once more). Any
    other unraisable exception goes to the hook before."""
    import _thread
    import threading

    previous = sys.unraisablehook

    def hook(unraisable):
        if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
            again = threading.Timer(0.02, _thread.interrupt_main)
            again.daemon = True
            again.start()
        else:
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous


def add_measurement_options(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of a measurement file shared by ``tawarp fit`` and ``tawarp loop``."""
    p.add_argument(
        "--empty-tube",
        default=None,
        metavar="EMPTY.csv",
        help="empty-tube scattering CSV (same tube, reference planes and frequencies, no sample) that "
        "calibrates scattering data: microphone gain/phase, the tube's sound speed and wall losses "
        "(docs/formats.md)",
    )
    return p


def load_data(args, settings):
    """The measurement kind of ``args.data`` with ``args.core`` (:func:`impedance_on_core`
    for surface impedance) and, when given, ``args.empty_tube`` (refused by kinds that
    take none)."""
    kind = load_measurement(args.data, args.core, settings, empty_tube=getattr(args, "empty_tube", None))
    if isinstance(kind, ImpedanceKind) and args.core is not None:
        kind = impedance_on_core(kind, args.core, settings)
    return kind


def impedance_on_core(kind: ImpedanceKind, core_arg, settings) -> ImpedanceKind:
    """Surface-impedance data with ``--core``: a passive core of one porous segment gives
    the layer's start values (porosity, pore radius, tortuosity) and gas; the thickness
    stays the file's and the parameters are named ``layer.*``. A core with thermal
    segments, or not exactly one porous segment, is refused naming ``--core``."""
    core = load_core(core_arg)
    thermal = [core.segments[i].name for i in core.thermal_indices]
    if thermal:
        raise CoreError(
            f"--core {core_arg}: a thermoacoustic core (thermal segments {', '.join(thermal)}) cannot "
            "model surface-impedance data of a rigid-backed layer; give a passive core of one porous "
            "segment, or no --core"
        )
    porous = [s for s in core.segments if s.is_porous]
    if len(porous) != 1:
        raise CoreError(
            f"--core {core_arg}: surface-impedance data need a core of one porous segment (the layer); "
            f"it has {len(porous)}"
        )
    start = {f"layer.{f}": getattr(porous[0], f) for f in ("porosity", "pore_radius", "tortuosity")}
    return ImpedanceKind(kind.data, settings, start=start, gas=core.gas.name)


def check_option(ok: bool, option: str, value, need: str) -> None:
    """Refuse ``option``'s ``value`` unless ``ok``, naming the option as it was typed: the
    library's own check names its parameter (``n_samples``), which the command line
    user never saw."""
    if not ok:
        raise ValueError(f"{option} {f'{value:g}' if isinstance(value, float) else value}: {need}")


def check_onset_search(args) -> None:
    """``--Q-max`` and ``--bracket`` of an onset search (onset, design, rank)."""
    check_option(math.isfinite(args.Q_max) and args.Q_max > 0, "--Q-max", args.Q_max, "expected a heat input > 0 W")
    check_option(args.bracket >= 2, "--bracket", args.bracket, "expected at least 2 points of the searched range")


def check_network_options(args) -> None:
    """``--T-ratio-max`` and ``--amplitude`` of a network engine (onset, design)."""
    check_option(
        math.isfinite(args.T_ratio_max) and args.T_ratio_max > 1,
        "--T-ratio-max",
        args.T_ratio_max,
        "expected a ratio T_hot/T_cold > 1",
    )
    check_option(
        math.isfinite(args.amplitude) and args.amplitude > 0, "--amplitude", args.amplitude, "expected |p| > 0 Pa"
    )


def check_seed(args) -> None:
    """``--seed``: NumPy's own refusal of a negative seed names no option."""
    check_option(args.seed >= 0, "--seed", args.seed, "expected an integer >= 0")


def _say(args, *text):
    if not args.quiet:
        print(*text, flush=True)


def parse_vars(texts: list[str]) -> dict[str, np.ndarray]:
    """``--var NAME=LIST`` options as {name: values} (:func:`parse_list` for each LIST)."""
    out = {}
    for t in texts:
        name, sep, values = t.partition("=")
        if not sep or not name.strip():
            raise ValueError(f"--var {t!r}: expected NAME=LIST, e.g. engine.left_duct=0.5:0.9:5")
        out[name.strip()] = parse_list(values)
    return out
