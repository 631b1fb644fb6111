"""Figures: T-matrix coefficients against frequency, temperature profiles.

Every function takes an output path, draws with the non-interactive Agg backend and
writes atomically (a temporary file renamed into place).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .io import GENERATOR, atomic_path  # noqa: E402
from .model.coefficients import COEFFICIENTS  # noqa: E402


#: Matplotlib's metadata key for the writing software, per format: tawarp's mark
#: (:func:`tawarp.io.written_by_tawarp` reads it back from a PNG).
SOFTWARE_KEY = {"png": "Software", "pdf": "Creator", "svg": "Creator"}


def save(fig, path: str | Path) -> Path:
    """Write ``fig`` to ``path`` atomically (:func:`tawarp.io.atomic_path`), marked as
    tawarp's (:data:`SOFTWARE_KEY`), and close it."""
    fmt = Path(path).suffix.lstrip(".").lower() or "png"
    metadata = {SOFTWARE_KEY[fmt]: GENERATOR} if fmt in SOFTWARE_KEY else None
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=120, bbox_inches="tight", format=fmt, metadata=metadata)
    finally:
        plt.close(fig)
    return Path(path)


def plot_coefficients(
    freqs, curves: dict[str, np.ndarray], path, *, markers: dict[str, np.ndarray] | None = None, title: str = ""
):
    """|Y| and arg Y of the four dimensionless coefficients against frequency.

    ``curves``: label -> (m, 4) complex, drawn as lines; ``markers``: label -> (m, 4)
    complex drawn as points (measured data).
    """
    fig, axes = plt.subplots(2, 4, figsize=(14, 5.5), sharex=True)
    for label, Y in (markers or {}).items():
        for c in range(4):
            axes[0, c].plot(freqs, np.abs(Y[:, c]), "o", ms=3, mfc="none", label=label)
            axes[1, c].plot(freqs, np.unwrap(np.angle(Y[:, c])), "o", ms=3, mfc="none")
    for label, Y in curves.items():
        for c in range(4):
            axes[0, c].plot(freqs, np.abs(Y[:, c]), "-", lw=1.2, label=label)
            axes[1, c].plot(freqs, np.unwrap(np.angle(Y[:, c])), "-", lw=1.2)
    for c, name in enumerate(COEFFICIENTS):
        axes[0, c].set_title(name)
        axes[1, c].set_xlabel("frequency [Hz]")
    axes[0, 0].set_ylabel("modulus")
    axes[1, 0].set_ylabel("phase [rad, unwrapped]")
    axes[0, 0].legend(fontsize=7)
    if title:
        fig.suptitle(title)
    return save(fig, path)


def plot_temperature(x, profiles: dict[str, np.ndarray], path, *, planes=None, title: str = ""):
    """Temperature profiles T(x) [K] (label -> (len(x),)) with the segment planes."""
    fig, ax = plt.subplots(figsize=(7, 4))
    for label, T in profiles.items():
        ax.plot(np.asarray(x) * 100, T, label=label)
    for xp in planes or []:
        ax.axvline(xp * 100, color="0.8", lw=0.8, zorder=0)
    ax.set_xlabel("x [cm]")
    ax.set_ylabel("T [K]")
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    return save(fig, path)
