"""Helpers shared by the subcommands: list options, the common options, printing."""

from __future__ import annotations

import argparse

import numpy as np

from ..measure import load_measurement


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
        raise argparse.ArgumentTypeError(f"{text!r}: expected a comma list (30,100,250) or start:stop:count (30:500:100)")


def _common(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    p.add_argument("--device", default=None, help="cpu, cuda or cuda:N (default: a GPU if Warp sees one, else cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bars, banners or chatter")
    return p


def add_measurement_options(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of a measurement file shared by ``tawarp fit`` and ``tawarp loop``."""
    p.add_argument("--empty-tube", default=None, metavar="EMPTY.csv",
                   help="empty-tube scattering CSV (same tube, reference planes and frequencies, no sample) that "
                        "calibrates scattering data: microphone gain/phase and the tube's own wavenumber "
                        "(docs/formats.md)")
    return p


def load_data(args, settings):
    """The measurement kind of ``args.data`` with ``args.core`` and, when given,
    ``args.empty_tube`` (refused by kinds that take none)."""
    return load_measurement(args.data, args.core, settings, empty_tube=getattr(args, "empty_tube", None))


def _say(args, *text):
    if not args.quiet:
        print(*text, flush=True)
