"""The measurement description: one TOML file that says what a lab measured and how
(docs/formats.md, "Measurement description").

It names the tube (shape and size), the gas (air at a temperature, pressure and relative
humidity, or a tawarp gas), the microphones (position and channel of each, in one or more
position sets with their frequency bands), the reference channel, the specimen, the
method and the signal files of each of its configurations, the calibration files and the
Welch options. :func:`load_setup` checks everything before any signal is read; every
error names the file and the key.

Positions are signed, in metres along the tube from the specimen's upstream face,
positive downstream (towards the termination): a microphone upstream of the specimen has
a negative position; one downstream of a specimen of thickness ``d`` has a position
``> d``.
"""

from __future__ import annotations

import math
import tomllib
from importlib import resources
from dataclasses import dataclass, field
from pathlib import Path

from ..measure.table import MeasurementError
from ..model.gas import GASES
from . import spectra
from .acoustics import HUMID_AIR, Gas, Tube, sound_speed

SHAPES = ("circular", "rectangular")
#: method -> (microphones per position set, configurations (files) it needs, what they are)
METHODS = {
    "two_load": (4, 2, "the specimen under two different terminations"),
    "one_load": (4, 1, "a symmetric specimen under one termination"),
    "two_source": (4, 2, "the source upstream, then the source downstream"),
    "iso10534": (2, 1, "the rigid-backed layer"),
    "terminations": (2, None, "one per [[termination]] table"),
}
#: ASTM E2611 / ISO 10534-2 limits of a position set's band: the lowest frequency has a
#: microphone spacing of LOW_SPACING wavelengths; the highest is UPPER_SPACING of the
#: spacing's half-wavelength limit or, below that, the first cross mode (CUT_ON times
#: c over the largest side, or the diameter).
LOW_SPACING = 0.05
UPPER_SPACING = 0.8
CUT_ON = {"rectangular": 0.5, "circular": 0.586}


@dataclass(frozen=True)
class PositionSet:
    """Microphones used together: ``channels`` (recorder channel of each, upstream to
    downstream), ``positions`` [m] (signed, from the specimen's upstream face), ``band``
    (lo, hi) [Hz] where the set is used."""

    name: str
    channels: tuple[int, ...]
    positions: tuple[float, ...]
    band: tuple[float, float]


@dataclass(frozen=True)
class Calibration:
    """Switched-microphone calibration: ``direct`` (the empty tube, every microphone in
    its place) and ``switched`` {channel: file with that channel's microphone switched
    with the reference's}; ``self_calibration``: fit spacings, sound speed and wall loss
    to the direct file."""

    direct: Path | None = None
    switched: dict[int, Path] = field(default_factory=dict)
    self_calibration: bool = True


@dataclass(frozen=True)
class Termination:
    """A known termination of a core's downstream face (the multi-termination method):
    the signal ``file``, the ``heat_input`` [W] of the core, and either a rigidly closed
    tube of the description's section ``closed_tube`` [m] long, or an ``impedance`` table
    (k, 3): freq_Hz, Z_re, Z_im, ``p / U`` [Pa s/m^3] in exp(-iwt) (the engine TOML's
    impedance CSV)."""

    file: Path
    heat_input: float
    closed_tube: float | None = None
    impedance: object = None


@dataclass(frozen=True)
class Setup:
    """A checked measurement description (module doc); paths are absolute."""

    source: str
    tube: Tube
    gas: Gas
    reference: int
    method: str
    files: tuple[Path, ...]
    thickness: float
    sets: tuple[PositionSet, ...]
    welch: dict
    calibration: Calibration
    heat_input: float = 0.0
    sample_rate: float | None = None  # for CSV time series without their own
    terminations: tuple[Termination, ...] = ()
    sensor_scale: float = 1.0  # Pa per unit of a pressure channel over m^3/s per unit of the reference

    def error(self, key: str, what: str) -> MeasurementError:
        return MeasurementError(f"{self.source}: {key}: {what}")


def _fail(src, key, what) -> MeasurementError:
    return MeasurementError(f"{src}: {key}: {what}")


def _number(src, table, key, where, *, default=None, positive=True, minimum=None):
    if key not in table:
        if default is None:
            raise _fail(src, f"{where}.{key}", "missing; add it (see docs/formats.md, measurement description)")
        return default
    v = table[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _fail(src, f"{where}.{key}", f"expected a finite number, got {v!r}")
    if positive and v <= 0:
        raise _fail(src, f"{where}.{key}", f"expected a number > 0, got {v!r}")
    if minimum is not None and v < minimum:
        raise _fail(src, f"{where}.{key}", f"expected a number >= {minimum}, got {v!r}")
    return float(v)


def _table(src, data, key, required=True) -> dict:
    if key not in data:
        if required:
            raise _fail(src, f"[{key}]", "table missing")
        return {}
    if not isinstance(data[key], dict):
        raise _fail(src, key, f"expected a table [{key}], got {data[key]!r}")
    return data[key]


def _unknown(src, table, known, where) -> None:
    extra = sorted(set(table) - set(known))
    if extra:
        raise _fail(src, f"{where}.{extra[0]}", f"unknown key; expected one of {sorted(known)}")


class _Folder:
    """Where a description's file names point: relative to the description's folder, or, with
    a data folder given, the file of that name in it (the description's folders dropped)."""

    def __init__(self, folder: Path, by_name: bool):
        self.folder, self.by_name = folder, by_name

    def __truediv__(self, value: str) -> Path:
        return self.folder / (Path(value).name if self.by_name else value)


def _file(src, base: _Folder, value, key) -> Path:
    if not isinstance(value, str) or not value:
        raise _fail(src, key, f"expected a file name, got {value!r}")
    path = (base / value).resolve()
    if not path.is_file():
        raise _fail(
            src,
            key,
            f"file {value!r} not found (looked for {path}); paths are relative to the description; --data DIR reads them by name from DIR",
        )
    return path


def _channel(src, v, key) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise _fail(src, key, f"expected a channel number >= 0, got {v!r}")
    return v


def _tube(src, t) -> Tube:
    _unknown(src, t, ("shape", "diameter", "width", "height"), "tube")
    shape = t.get("shape")
    if shape not in SHAPES:
        raise _fail(src, "tube.shape", f"expected one of {list(SHAPES)}, got {shape!r}")
    if shape == "circular":
        if "width" in t or "height" in t:
            raise _fail(src, "tube.width", "a circular tube takes diameter only")
        d = _number(src, t, "diameter", "tube")
        return Tube(shape, d, d)
    if "diameter" in t:
        raise _fail(src, "tube.diameter", "a rectangular tube takes width and height")
    return Tube(shape, _number(src, t, "width", "tube"), _number(src, t, "height", "tube"))


def _gas(src, g) -> Gas:
    _unknown(src, g, ("name", "temperature", "pressure", "humidity"), "gas")
    name = g.get("name", HUMID_AIR)
    if name not in GASES:
        raise _fail(src, "gas.name", f"expected one of {sorted(GASES)}, got {name!r}")
    if "humidity" in g and name != HUMID_AIR:
        raise _fail(src, "gas.humidity", f"humidity applies to air only (gas.name = {name!r})")
    humidity = _number(src, g, "humidity", "gas", default=0.0, positive=False, minimum=0.0)
    if humidity > 100.0:
        raise _fail(src, "gas.humidity", f"expected a relative humidity in [0, 100] %, got {humidity!r}")
    return Gas(name, _number(src, g, "temperature", "gas"), _number(src, g, "pressure", "gas"), humidity)


def default_band(positions, tube: Tube, sound_speed: float) -> tuple[float, float]:
    """ASTM E2611 (sec. 6) band [Hz] of microphones at ``positions`` [m] in pairs
    (upstream pair, downstream pair; two microphones: one pair): from ``LOW_SPACING c /
    s_min`` to the lower of ``UPPER_SPACING c / (2 s_max)`` and the first cross mode."""
    x = list(positions)
    spacings = [x[1] - x[0]] if len(x) == 2 else [x[1] - x[0], x[3] - x[2]]
    lo = LOW_SPACING * sound_speed / min(spacings)
    hi = min(UPPER_SPACING * sound_speed / (2 * max(spacings)), CUT_ON[tube.shape] * sound_speed / tube.largest)
    return lo, hi


def _band(src, b, key) -> tuple[float, float]:
    """A frequency band ``[lo, hi]`` [Hz], 0 < lo < hi."""
    if not (isinstance(b, list) and len(b) == 2 and all(isinstance(v, (int, float)) for v in b)):
        raise _fail(src, key, f"expected [lo, hi] in Hz, got {b!r}")
    if not 0 < b[0] < b[1]:
        raise _fail(src, key, f"expected 0 < lo < hi, got {b!r}")
    return float(b[0]), float(b[1])


def _position_sets(src, raw, method, thickness, tube, gas) -> tuple[PositionSet, ...]:
    mics, _, _ = METHODS[method]
    if not isinstance(raw, list) or not raw or not all(isinstance(s, dict) for s in raw):
        raise _fail(src, "[[microphones]]", "expected one or more [[microphones]] tables")
    sets = []
    for n, s in enumerate(raw):
        where = f"microphones[{n}]"
        _unknown(src, s, ("name", "channels", "positions", "band"), where)
        name = s.get("name", f"set{n}")
        ch, x = s.get("channels"), s.get("positions")
        if not isinstance(ch, list) or len(ch) != mics:
            raise _fail(src, f"{where}.channels", f"method {method!r} needs {mics} microphone channels, got {ch!r}")
        channels = tuple(_channel(src, c, f"{where}.channels") for c in ch)
        if len(set(channels)) != mics:
            raise _fail(src, f"{where}.channels", f"a channel is listed twice: {list(channels)}")
        if not isinstance(x, list) or len(x) != mics:
            raise _fail(src, f"{where}.positions", f"expected {mics} positions [m], got {x!r}")
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in x):
            raise _fail(src, f"{where}.positions", f"expected finite numbers [m], got {x!r}")
        pos = tuple(float(v) for v in x)
        if any(b <= a for a, b in zip(pos, pos[1:])):
            raise _fail(src, f"{where}.positions", f"positions must increase downstream, got {list(pos)}")
        if mics == 4 and not (pos[1] < 0 and pos[2] > thickness):
            raise _fail(
                src,
                f"{where}.positions",
                f"two microphones upstream of the specimen (position < 0) and two downstream "
                f"(position > thickness = {thickness}), got {list(pos)}",
            )
        if mics == 2 and not pos[1] < 0:
            raise _fail(src, f"{where}.positions", f"both microphones upstream of the layer (< 0), got {list(pos)}")
        if "band" in s:
            band = _band(src, s["band"], f"{where}.band")
        else:
            band = default_band(pos, tube, sound_speed(gas))
        sets.append(PositionSet(str(name), channels, pos, band))
    return tuple(sets)


def _sensor(src, data, base, tube, gas) -> tuple:
    """The impedance sensor and the terminations of the multi-termination method."""
    sensor = _table(src, data, "sensor")
    _unknown(src, sensor, ("channels", "scale", "band"), "sensor")
    ch = sensor.get("channels")
    if not isinstance(ch, list) or len(ch) != 2:
        raise _fail(src, "sensor.channels", f"expected the channels of [p(x1), p(x6)], got {ch!r}")
    channels = tuple(_channel(src, c, "sensor.channels") for c in ch)
    scale = _number(src, sensor, "scale", "sensor", default=1.0)
    band = _band(src, sensor.get("band"), "sensor.band")
    raw = data.get("termination")
    if not isinstance(raw, list) or not all(isinstance(t, dict) for t in raw):
        raise _fail(src, "[[termination]]", "expected one [[termination]] table per file")
    terms = []
    for n, t in enumerate(raw):
        where = f"termination[{n}]"
        _unknown(src, t, ("file", "heat_input", "closed_tube", "impedance_csv"), where)
        if ("closed_tube" in t) == ("impedance_csv" in t):
            raise _fail(src, where, "give closed_tube = LENGTH [m] or impedance_csv = FILE (one of them)")
        file = _file(src, base, t.get("file"), f"{where}.file")
        heat = _number(src, t, "heat_input", where, default=0.0, positive=False, minimum=0.0)
        if "closed_tube" in t:
            terms.append(Termination(file, heat, closed_tube=_number(src, t, "closed_tube", where)))
        else:
            from ..model.resonator import read_impedance_csv

            table = read_impedance_csv(_file(src, base, t["impedance_csv"], f"{where}.impedance_csv"))
            if not (table[0, 0] <= band[0] and table[-1, 0] >= band[1]):
                raise _fail(
                    src,
                    f"{where}.impedance_csv",
                    f"covers {table[0, 0]:g}-{table[-1, 0]:g} Hz, not sensor.band {list(band)}",
                )
            terms.append(Termination(file, heat, impedance=table))
    per_q = {}
    for t in terms:
        per_q[t.heat_input] = per_q.get(t.heat_input, 0) + 1
    few = sorted(q for q, count in per_q.items() if count < 2)
    if few:
        raise _fail(src, "[[termination]]", f"heat input(s) {few} W have one termination; the method needs two or more")
    return tuple(terms), PositionSet("sensor", channels, (0.0, 0.0), band), scale


def load_setup(path: str | Path, data_dir: str | Path | None = None) -> Setup:
    """Read and check the measurement description TOML ``path`` (module doc; a bundled
    description by name, e.g. ``e2611_two_load``). Its file names are relative to the
    description's folder; with ``data_dir`` each is the file of that name in ``data_dir``."""
    from ..model.core import bundled

    path = Path(path)
    if not path.exists() and str(path) in bundled("tube"):
        path = Path(str(resources.files("tawarp") / "data" / "tube" / f"{path}.toml"))
    src = str(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise MeasurementError(f"{src}: cannot read ({e.strerror})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise MeasurementError(f"{src}: not valid TOML ({e})") from None
    _unknown(
        src,
        data,
        ("tube", "gas", "specimen", "microphones", "measurement", "calibration", "spectra", "sensor", "termination"),
        "description",
    )
    if data_dir is not None and not Path(data_dir).is_dir():
        raise MeasurementError(f"{data_dir}: data folder does not exist")
    base = _Folder(Path(data_dir).resolve(), True) if data_dir is not None else _Folder(path.resolve().parent, False)
    tube = _tube(src, _table(src, data, "tube"))
    gas = _gas(src, _table(src, data, "gas"))
    m = _table(src, data, "measurement")
    _unknown(src, m, ("method", "files", "reference", "sample_rate"), "measurement")
    method = m.get("method")
    if method not in METHODS:
        raise _fail(src, "measurement.method", f"expected one of {sorted(METHODS)}, got {method!r}")
    core = method == "terminations"
    spec = _table(src, data, "specimen", required=not core)
    _unknown(src, spec, ("thickness", "heat_input"), "specimen")
    thickness = _number(src, spec, "thickness", "specimen", positive=False, minimum=0.0, default=0.0 if core else None)
    heat = _number(src, spec, "heat_input", "specimen", default=0.0, positive=False, minimum=0.0)
    if "reference" not in m:
        raise _fail(src, "measurement.reference", "missing: the channel every transfer function is taken from")
    reference = _channel(src, m["reference"], "measurement.reference")
    rate = _number(src, m, "sample_rate", "measurement") if "sample_rate" in m else None
    terminations, scale = (), 1.0
    if core:
        for key in ("files", "microphones", "calibration"):
            if key in m or key in data:
                raise _fail(src, key, "the terminations method takes [sensor] and [[termination]] tables instead")
        terminations, sensor, scale = _sensor(src, data, base, tube, gas)
        files, sets = tuple(t.file for t in terminations), (sensor,)
    else:
        for key in ("sensor", "termination"):
            if key in data:
                raise _fail(src, key, f"applies to method 'terminations' only (measurement.method = {method!r})")
        _, nfiles, what = METHODS[method]
        files = m.get("files")
        if not isinstance(files, list) or len(files) != nfiles:
            raise _fail(src, "measurement.files", f"method {method!r} needs {nfiles} file(s), {what}; got {files!r}")
        files = tuple(_file(src, base, f, "measurement.files") for f in files)
        sets = _position_sets(src, data.get("microphones"), method, thickness, tube, gas)

    w = _table(src, data, "spectra", required=False)
    _unknown(src, w, ("block", "window", "overlap"), "spectra")
    block = w.get("block", spectra.BLOCK)
    if isinstance(block, bool) or not isinstance(block, int) or block < 16:
        raise _fail(src, "spectra.block", f"expected a whole number of samples >= 16, got {block!r}")
    window = w.get("window", spectra.WINDOW)
    if not isinstance(window, str):
        raise _fail(src, "spectra.window", f"expected a window name (scipy.signal.get_window), got {window!r}")
    overlap = _number(src, w, "overlap", "spectra", default=spectra.OVERLAP, positive=False, minimum=0.0)
    if overlap >= 1:
        raise _fail(src, "spectra.overlap", f"expected a fraction in [0, 1), got {overlap!r}")

    c = _table(src, data, "calibration", required=False)
    _unknown(src, c, ("direct", "switched", "self_calibration"), "calibration")
    direct = _file(src, base, c["direct"], "calibration.direct") if "direct" in c else None
    sw = c.get("switched", {})
    if not isinstance(sw, dict):
        raise _fail(src, "calibration.switched", f"expected a table {{channel = file}}, got {sw!r}")
    switched = {}
    for k, v in sw.items():
        if not k.isdigit():
            raise _fail(src, f"calibration.switched.{k}", 'keys are channel numbers, e.g. 1 = "empty_01.h5"')
        switched[int(k)] = _file(src, base, v, f"calibration.switched.{k}")
    if switched and direct is None:
        raise _fail(src, "calibration.direct", "switched files need the direct (unswitched) empty-tube file")
    if reference in switched:
        raise _fail(src, f"calibration.switched.{reference}", "the reference channel is not switched with itself")
    self_cal = c.get("self_calibration", direct is not None)
    if not isinstance(self_cal, bool):
        raise _fail(src, "calibration.self_calibration", f"expected true or false, got {self_cal!r}")
    if self_cal and direct is None:
        raise _fail(src, "calibration.self_calibration", "needs the empty-tube file calibration.direct")
    if self_cal and METHODS[method][0] < 3:
        raise _fail(src, "calibration.self_calibration", "needs at least three microphones; set it to false")
    if switched:
        used = sorted({ch for s in sets for ch in s.channels} - {reference} - set(switched))
        if used:
            raise _fail(src, "calibration.switched", f"channel(s) {used} are used but have no switched file")
    return Setup(
        src,
        tube,
        gas,
        reference,
        method,
        files,
        thickness,
        sets,
        {"block": block, "window": window, "overlap": overlap},
        Calibration(direct, switched, self_cal),
        heat,
        rate,
        terminations,
        scale,
    )
