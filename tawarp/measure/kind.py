"""What a measurement kind is, the registry of kinds, and the one cache of forward engines.

A *measurement kind* (:class:`MeasurementKind`) holds measured complex observables ``y``
(rows,) with weights ``w`` (rows, 2) for (re, im) and row labels (``freq`` [Hz], ``group``
= heat input [W] or layer thickness [m], ``coef`` = index into ``coef_names``), and
predicts the same observables for a batch of parameter sets (:meth:`MeasurementKind.predict`).
The estimator (:mod:`tawarp.fit`) and the loop (:mod:`tawarp.loop`) need nothing else.

Adding a kind: subclass :class:`MeasurementKind` (set ``name``, ``group_name``,
``coef_names``, the row arrays, and :meth:`predict`; the loop's choices for the kind are its
hooks: :meth:`~MeasurementKind.base_names`, :meth:`~MeasurementKind.effect_library`,
:meth:`~MeasurementKind.first_step_rows`, :meth:`~MeasurementKind.heat_groups`,
:meth:`~MeasurementKind.extra_groups`, :meth:`~MeasurementKind.at_rows`,
``groups_are_heat_inputs``), and register it with
:func:`register_kind` (``detect`` tells its CSV header, ``load`` builds it from a file), so
that :func:`load_measurement`, ``tawarp fit`` and ``tawarp loop`` take its files.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np
import warp as wp

from ..kernels import lm as klm
from ..kernels import misfit as kmisfit
from ..model.coefficients import rms_error
from ..model.core import Core
from ..model.forward import Engine, ForwardSettings, resolve_device
from ..model.validity import ModelValidityError
from .files import MeasurementError
from .table import text_lines


@dataclass
class DeviceValues:
    """Model values (n, rows) of ``n`` parameter sets left on the device where a launch
    made them, as the table of :mod:`tawarp.kernels.misfit` reads them: ``values``
    (columns, 2 entries) float64, ``columns`` (sets, row groups) int32 (-1: not computed),
    ``gain`` (sets, 2) the sets' complex factor (empty: 1), and per row ``row_q``, ``row_e``,
    ``scale``; the sets ``start : start + n`` of the launch's (a slice of them is the same
    arrays at an offset, as :func:`tawarp.fit.problems.run_sets` and the fits slice a
    launch's model values)."""

    values: wp.array
    columns: wp.array
    gain: wp.array
    row_q: wp.array
    row_e: wp.array
    scale: wp.array
    start: int
    n: int

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n, self.row_q.shape[0])

    def __getitem__(self, sets: slice) -> "DeviceValues":
        a, b, stride = sets.indices(self.n)
        if stride != 1:
            raise IndexError("DeviceValues: a slice of sets is one run")
        # built directly: a fit's batch slices a launch's values once per fit and evaluation
        # (dataclasses.replace, which inspects the fields, cost several times more)
        return DeviceValues(
            self.values, self.columns, self.gain, self.row_q, self.row_e, self.scale, self.start + a, max(b - a, 0)
        )

    def table(self) -> kmisfit.ModelTable:
        """The launch's values as :mod:`tawarp.kernels.misfit` reads them."""
        t = kmisfit.ModelTable()
        t.values, t.columns, t.gain = self.values, self.columns, self.gain
        t.row_q, t.row_e, t.scale = self.row_q, self.row_e, self.scale
        return t

    @classmethod
    def of_host(cls, Y: np.ndarray, device) -> "DeviceValues":
        """The model values ``Y`` (n, rows) complex formed on the host, on ``device``."""
        n, size = Y.shape
        return cls(
            wp.array(np.ascontiguousarray(Y).view(np.float64), device=device),
            wp.array(np.arange(n, dtype=np.int32).reshape(n, 1), device=device),
            wp.zeros((0, 2), dtype=wp.float64, device=device),
            wp.array(np.zeros(size, dtype=np.int32), device=device),
            wp.array(np.arange(size, dtype=np.int32), device=device),
            wp.array(np.ones(size), device=device),
            0,
            n,
        )


class MeasurementKind:
    """Measured observables and their model (see the module doc).

    ``y`` (rows,) complex measured values; ``w`` (rows, 2) weights of (re, im) residuals:
    1/sigma with sigma columns (``has_sigma``), else 1/rms|y| (the docs/formats.md error
    measure); ``freq``, ``group``, ``coef`` (rows,) labels; ``core`` the model the
    parameter names refer to.
    """

    name = "kind"
    group_name = "group"
    coef_names: tuple[str, ...] = ()
    y: np.ndarray
    w: np.ndarray
    freq: np.ndarray
    group: np.ndarray
    coef: np.ndarray
    has_sigma: bool = False
    core: Core
    #: the groups are heat inputs [W]: the loop refits the h's per heat input (report.json's
    #: ``drift_before``/``drift_after``) and names a planned measurement's groups
    #: ``heat_inputs_W``; else ``group_name``
    groups_are_heat_inputs: bool = False
    #: a parameter set's forward-difference neighbours in host-side fields share its kernel
    #: columns within one :meth:`predict` call: the fits evaluate an LM trial and its
    #: neighbours in one call (:class:`tawarp.fit.problems.KindProblems`), not the trial first
    neighbours_share_columns: bool = False
    #: :meth:`predict` takes ``rows``, the rows of each set that are needed, and leaves out
    #: the work of the others (the fits on some rows alone pass them,
    #: :class:`tawarp.fit.problems.KindProblems`)
    predicts_rows: bool = False
    #: the forward model's settings (their ``device`` runs :meth:`predict`'s launches)
    settings: ForwardSettings | None = None
    #: on a GPU (:meth:`predicts_on_gpu`) the fits reduce the model values where
    #: :meth:`predict_on_device` leaves them (:class:`tawarp.fit.problems.KindProblems`);
    #: a kind whose values are formed on the host keeps the host's fits
    reduces_on_device: bool = False

    def predicts_on_gpu(self) -> bool:
        """Whether :meth:`predict` launches on a GPU (its settings' device)."""
        return self.settings is not None and wp.get_device(resolve_device(self.settings.device)).is_cuda

    def predict_on_device(self, values: dict, n: int, effect=None, rows: list | None = None) -> "DeviceValues":
        """:meth:`predict`'s model values left on the device of the kind's launches
        (:class:`DeviceValues`), for fits that reduce them there
        (:mod:`tawarp.kernels.misfit`); this default forms them on the host and copies them
        there."""
        Y = self.predict(values, n, effect) if rows is None else self.predict(values, n, effect, rows=rows)
        return DeviceValues.of_host(Y, resolve_device(self.settings.device if self.settings else "cpu"))

    def family(self) -> tuple | None:
        """A key shared by the kinds whose parameter sets one :meth:`predict` call of any of
        them computes, each at its own core's values passed per set (the same structure,
        rows and settings; :class:`tawarp.fit.problems.Families`); None: this kind predicts
        alone (the default)."""
        return None

    def for_family(self, members: list) -> "MeasurementKind":
        """The kind that predicts for every kind of ``members``, a family of this one
        (:meth:`family`): this kind itself, where the family's settings are its own."""
        return self

    def predict(self, values: dict, n: int, effect=None, rows: list | None = None) -> np.ndarray:
        """Model values (n, rows) complex for ``n`` parameter sets ``values`` {name: (n,)}
        (missing names take the core's values); ``effect`` an
        :class:`tawarp.model.effects.Effect` whose ``transform`` changes the structure.
        ``rows`` (kinds with :attr:`predicts_rows`): None, or per set the row indices whose
        values are needed (None: all); a set's other values may then be NaN."""
        raise NotImplementedError

    def default_names(self) -> list[str]:
        """Parameters fitted when none are named."""
        raise NotImplementedError

    def base_names(self) -> list[str]:
        """The loop's base fit (the paper's full method for this kind): by default
        :meth:`default_names`."""
        return self.default_names()

    def ties(self) -> dict[str, list[str]]:
        """{parameter: [model parameters]} that the loop's base fit sets to that parameter's
        value where it fits it alone (one material in two segments): none by default."""
        return {}

    def effect_library(self) -> list:
        """The loop's candidate effects (:class:`tawarp.model.effects.Effect`) for this
        kind's data on its core: none by default."""
        return []

    def first_step_rows(self) -> np.ndarray:
        """Rows of the paper's first step, fitted alone before everything together (a core's
        Q = 0 rows, where the h's do not act); none by default."""
        return np.zeros(0, dtype=int)

    def heat_groups(self) -> list[float]:
        """Groups that are heat inputs > 0, whose h's the loop refits apart to show their
        drift; none by default."""
        return []

    def extra_groups(self) -> list[float]:
        """Groups a further measurement could add (the loop's next-measurement plans): none
        by default."""
        return []

    def at_rows(self, groups, freqs) -> "MeasurementKind | None":
        """The same kind and model at every (group, frequency) of ``groups`` x ``freqs``
        (its measured values are placeholders): what a planned measurement would see. None
        where the kind cannot say."""
        return None

    def unit_weights(self) -> np.ndarray:
        """(rows, 2) weights 1/rms|y|: the cost is then the docs/formats.md error squared times rows."""
        rms = np.sqrt(np.mean(np.abs(self.y) ** 2))
        if not rms > 0:
            raise MeasurementError(f"{self.name} data: every value is 0, nothing to fit; check the data")
        return np.full((self.y.size, 2), 1.0 / rms)

    def error(self, Y: np.ndarray, rows=None) -> float:
        """The docs/formats.md error measure of model values ``Y`` (rows,) on ``rows``."""
        rows = slice(None) if rows is None else rows
        return float(rms_error(self.y[rows], np.asarray(Y)[..., rows]))

    def noise_floor(self, sigma: np.ndarray | None = None) -> float | None:
        """The docs/formats.md error of data that differ from the model by noise alone: of
        standard deviation ``sigma`` per real residual in weighted units (the fit's residual
        order: the rows' real parts, then their imaginary parts), or by default the data's
        own sigma columns (weights 1/sigma: 1 each; None without them)."""
        if sigma is None:
            if not self.has_sigma:
                return None
            sigma = np.ones(2 * self.y.size)
        w = np.concatenate([self.w[:, 0], self.w[:, 1]])
        return float(np.sqrt(np.sum((sigma / w) ** 2) / self.y.size / np.mean(np.abs(self.y) ** 2)))


# -- forward engines for fits -------------------------------------------------------------
def smooth_settings(
    core: Core,
    freqs,
    settings: ForwardSettings | None,
    values: dict | None = None,
    heat_input=0.0,
    k_factor: float = 2.0,
) -> ForwardSettings:
    """Forward settings whose model is smooth in the parameters, as finite-difference
    Jacobians need.

    The adaptive cell count (``cells = None``) changes with h and the conductivities
    (``ceil(cell_density (1 + k L + w L / c))``, k = sqrt(2 h / (R lam))): a step across an
    integer boundary makes the model jump by its discretisation error (~1e-6), which a
    difference quotient with step 1e-6 turns into an O(1) Jacobian error. So a fit fixes
    one count per thermal segment for the whole batch: the adaptive rule at the highest
    frequency with ``2 k L`` (``k_factor`` = 2: room for the fit to move h up to 4x), evaluated by the
    kernels' own functions (:func:`fit_cells`, with the cell density the error estimate of
    ``settings.tolerance`` asks for over ``freqs``); ``values`` {name: scalar or array} are the
    parameter values to size for (their maxima; the core's values for the rest), at the
    largest of ``heat_input`` [W] (scalar or array). Settings
    with fixed ``cells`` are returned unchanged.
    """
    settings = settings or ForwardSettings()
    if settings.cells is not None:
        return settings
    values = {k: float(np.max(v)) for k, v in (values or {}).items()}
    # one parameter set: sized on the CPU, where its few cascades take microseconds (on a
    # GPU each estimate round costs a whole thread's latency and a synchronization); the
    # count does not depend on the device
    counts = fit_cells(
        core,
        float(np.max(freqs)),
        values,
        dataclasses.replace(settings, device="cpu"),
        k_factor=k_factor,
        freqs=freqs,
        heat_input=float(np.max(heat_input, initial=0.0)),
    )
    return dataclasses.replace(settings, cells={s.name: int(n) for s, n in zip(core.segments, counts) if s.thermal})


def fit_cells(
    core: Core,
    freq: float,
    values: dict | None = None,
    settings: ForwardSettings | None = None,
    k_factor: float = 1.0,
    freqs=None,
    heat_input: float = 0.0,
) -> np.ndarray:
    """Magnus cells (n_segments,) the cascade kernel's adaptive rule gives each thermal
    segment at frequency ``freq`` [Hz] with parameter ``values`` {name: scalar} (0 for
    non-thermal segments) on the uniform grid of fixed cells, at the cell density the error
    estimate of ``settings.tolerance`` asks for over the frequencies ``freqs`` (default
    ``[freq]``: then the density is the cascade's own at ``freq`` and ``heat_input`` [W],
    which only the estimate sees; the cascade's own grid is graded, fewer cells for the same
    error);
    ``k_factor`` > 1 sizes for a heat decay rate k that many times larger
    (:mod:`tawarp.kernels.lm`'s ``magnus_cells``). With (n,) arrays among the values:
    (n, n_segments), one row per parameter set (each at its own estimated density), from
    one launch."""
    settings = settings or ForwardSettings()
    names = list(values or {})
    cols = [np.asarray(values[k], dtype=float) for k in names]
    n = max([c.size for c in cols if c.ndim], default=1)
    eng = get_engine(core, [freq] if freqs is None else freqs, names, dataclasses.replace(settings, cells=None))
    params, theta = eng.heat(np.stack([np.full(n, float(heat_input))] + [np.broadcast_to(c, (n,)) for c in cols]))
    cells = wp.empty((n, len(core.segments)), dtype=wp.int32, device=eng.device)
    wp.launch(
        klm.magnus_cells,
        dim=(n, len(core.segments)),
        device=eng.device,
        inputs=[
            eng._sets(params),
            2 * math.pi * float(freq),
            eng.cell_densities(params, theta),
            float(k_factor),
            cells,
        ],
    )
    return cells.numpy() if any(c.ndim for c in cols) else cells.numpy()[0]


#: Engines :func:`get_engine` keeps, the least recently used let go first. A loop's fits
#: cycle through a few dozen cores, names and settings; loops run together
#: (:func:`tawarp.loop.run_loops`) through more, as each launch's names are the union of its
#: fits': 16 loops of the validation study's T-matrix cases used 117, and with 32 kept
#: rebuilt engines and lost their warm starts (:class:`tawarp.model.warm_starts.WarmStarts`) all
#: along. An engine holds its kernels' small arrays and at most
#: :data:`tawarp.model.warm_starts.WARM_SETS` kept heat solutions (about 1 MB).
ENGINES_KEPT = 512
_ENGINES: dict = {}  # in the order of their last use
_ENGINES_LOCK = threading.RLock()


def get_engine(core: Core, freqs, names, settings: ForwardSettings) -> Engine:
    """A cached :class:`Engine` per (core, frequencies, varying names, settings): the
    package's one cache (estimator, kinds, loop). Safe to call from several threads (Dask
    thread workers): one engine per key, built once."""
    key = (core, tuple(np.asarray(freqs, dtype=float).tolist()), tuple(names), repr(settings))
    with _ENGINES_LOCK:
        eng = _ENGINES.pop(key, None)
        if eng is None:
            while len(_ENGINES) >= ENGINES_KEPT:
                _ENGINES.pop(next(iter(_ENGINES)))
            eng = Engine(core, freqs, names, settings)
        _ENGINES[key] = eng
    return eng


# -- registry ---------------------------------------------------------------------------
@dataclass(frozen=True)
class KindEntry:
    """A registered kind: ``detect(columns)`` is True for its CSV header's column names;
    ``load(path, core, settings)`` builds the kind from a file."""

    name: str
    cls: type
    detect: Callable[[list[str]], bool]
    load: Callable


KINDS: dict[str, KindEntry] = {}


def register_kind(name: str, cls: type, detect: Callable[[list[str]], bool], load: Callable | None = None) -> None:
    """Register a measurement kind: ``cls`` a :class:`MeasurementKind` subclass, ``detect``
    a test on the CSV header's column names, ``load(path, core, settings)`` (default
    ``cls.from_file``). A later registration of the same name replaces the earlier one."""
    KINDS[name] = KindEntry(name, cls, detect, load or cls.from_file)


def header_columns(path) -> list[str]:
    """Column names of a CSV measurement file (its first line that is not a comment)."""
    for _, line in text_lines(path):
        if not line.startswith("#"):
            return [c.strip() for c in line.split(",")]
    raise MeasurementError(f"{path}: no header line")


def kind_of(path) -> KindEntry:
    """The registered kind whose ``detect`` takes the file's header (latest registration first)."""
    cols = header_columns(path)
    for entry in reversed(list(KINDS.values())):
        if entry.detect(cols):
            return entry
    raise MeasurementError(f"{path}: header {','.join(cols)} matches no measurement kind ({sorted(KINDS)})")


def load_measurement(
    path, core: Core | None = None, settings: ForwardSettings | None = None, **options
) -> MeasurementKind:
    """A measurement kind built from the CSV file ``path``, the kind picked by its header.
    ``options`` {name: value} (e.g. ``empty_tube`` for scattering data; None values are
    dropped) go to the kind's loader; a kind whose loader does not take one is refused,
    naming the option."""
    entry = kind_of(path)
    options = {k: v for k, v in options.items() if v is not None}
    for key in options:
        if key not in inspect.signature(entry.load).parameters:
            takers = [n for n, e in KINDS.items() if key in inspect.signature(e.load).parameters]
            raise MeasurementError(
                f"{path}: {entry.name} data take no {key} option (it applies to "
                f"{', '.join(takers) or 'no kind of'} data)"
            )
    try:
        kind = entry.load(path, core, settings, **options)
    except ModelValidityError as e:  # the file's frequencies or heat inputs are outside the model: name it
        raise MeasurementError(f"{path}: {e}") from None
    for what, a in (("values", kind.y), ("weights (1/sigma)", kind.w)):
        bad = np.flatnonzero(~np.isfinite(a).reshape(len(kind.y), -1).all(axis=1))
        if bad.size:  # finite in the file, out of the float64 range once scaled
            raise MeasurementError(
                f"{path}: {bad.size} {what} overflow the float64 range once made dimensionless "
                f"(the first of the {kind.name} rows: {int(bad[0])}); the file holds values out "
                f"of scale"
            )
    return kind
