"""Sensor calibration: offsets and correction matrices for gyro, accelerometer, compass.

A cheap MEMS board (the GY-86's MPU6050 and HMC5883L) reads with zero-g offsets of tens
of mg, percent-level scale and cross-axis errors, and a magnetometer distorted by the
board's own iron. Uncorrected, these tilt and turn the estimated attitude by degrees.
A :class:`SensorCalibration` removes them with, per sensor,

    corrected = M @ (measured - offset)

applied to the SI vectors ingest produces — body FRD, after the board profile's scaling
and the mounting rotation — so one calibration file serves every IMU message type.
The default is the identity (zero offsets, unit matrices).

Files are small TOML documents (see :meth:`SensorCalibration.to_toml`); anything wrong
in them is a ValueError naming the key and the problem.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: Largest plausible offset per axis, per sensor (in the file's units). An offset is a
#: sensor's zero error; one far beyond any datasheet's means a wrong unit (deg/s, g,
#: microtesla) or a wrong file, and would make the estimate silently wrong:
#: MPU6050 gyro zero-rate offset ±20 °/s plus its drift over temperature stays below
#: 50 °/s; its zero-g offset (±80 mg plus drift) below 3 m/s^2 (0.3 g); a hard iron
#: beyond 8 gauss (the HMC5883L's widest range, 12 Earth fields) would saturate the sensor.
MAX_GYRO_OFFSET = math.radians(50.0)  # rad/s
MAX_ACCEL_OFFSET = 3.0  # m/s^2
MAX_MAG_OFFSET = 8.0  # gauss
#: Plausible overall scale |det M|^(1/3) of the gyro and accelerometer matrices. These
#: correct scale-factor errors: the MPU6050's are ±3 % at 25 °C (datasheet "sensitivity
#: scale factor tolerance") plus a few percent over temperature and cross-axis terms, so
#: a real correction stays within some 10 %; 0.8..1.25 (symmetric in log, 1/1.25 = 0.8)
#: leaves ample room for a worse chip. Beyond it the matrix is a unit or file mistake
#: (100·I made every accelerometer sample implausible and froze the eskf without a word).
IMU_SCALE_RANGE = (0.8, 1.25)
#: The magnetometer matrix's scale is free (only the field's direction is used, and a fit
#: or a hand-made file may change the unit: gauss to microtesla is 100), so it is bounded
#: only against absurd values: at 1e-6 the Earth's field (0.25..0.65 gauss) is still 1e5
#: times the estimators' zero-norm threshold (1e-12), at 1e6 a saturated 8 gauss reading
#: squared (6.4e13) is far from overflow.
MAG_SCALE_RANGE = (1e-6, 1e6)
#: (TOML table, offset key, matrix key, dataclass offset field, dataclass matrix field,
#: (largest offset, its unit, the same in words), plausible matrix scale range)
_SECTIONS = (
    ("gyro", "offset", "matrix", "gyro_offset", "gyro_matrix",
     (MAX_GYRO_OFFSET, "rad/s", f"{math.degrees(MAX_GYRO_OFFSET):g} deg/s"), IMU_SCALE_RANGE),
    ("accel", "offset", "matrix", "accel_offset", "accel_matrix",
     (MAX_ACCEL_OFFSET, "m/s^2", f"{MAX_ACCEL_OFFSET / 9.80665:.2g} g"), IMU_SCALE_RANGE),
    ("mag", "offset", "matrix", "mag_offset", "mag_matrix", (MAX_MAG_OFFSET, "gauss", ""),
     MAG_SCALE_RANGE),
)
#: Smallest allowed |det| relative to the product of row norms: below it the matrix
#: squashes a direction to (almost) nothing, which no real correction does.
MIN_RELATIVE_DET = 1e-6
#: A correction matrix further than this from a multiple of the identity (per entry,
#: relative to its scale) is rejected: real sensor errors are a few percent, so a
#: larger one means a wrong fit or a wrong file, and it would rotate the attitude.
MAX_RELATIVE_DISTORTION = 0.5


def _zeros() -> np.ndarray:
    return np.zeros(3)


def _eye() -> np.ndarray:
    return np.eye(3)


def _has_bool(value: object) -> bool:
    """Whether a (nested) value holds a boolean: Python's bool is an int, so numpy
    would silently read a TOML ``true`` as 1.0."""
    if isinstance(value, bool | np.bool_):
        return True
    if isinstance(value, np.ndarray):
        return value.dtype == bool or (value.dtype == object
                                       and any(_has_bool(v) for v in value.flat))
    if isinstance(value, list | tuple):
        return any(_has_bool(v) for v in value)
    return False


def _refuse_bools(value: object, name: str) -> None:
    if _has_bool(value):
        raise ValueError(f"{name} must be numbers, not true/false, got {value!r}")


def _has_non_number(value: object) -> bool:
    """Whether a (nested) value holds anything but a real number: numpy would silently
    read a TOML string ``"0.5"`` as 0.5 (a quoted value is a mistake to report, not to
    guess at)."""
    if isinstance(value, np.ndarray):
        if value.dtype.kind in "iuf":
            return False
        return value.dtype != object or any(_has_non_number(v) for v in value.flat)
    if isinstance(value, list | tuple):
        return any(_has_non_number(v) for v in value)
    return not isinstance(value, int | float | np.integer | np.floating)


def _vector(value: object, name: str, limit: tuple[float, str, str]) -> np.ndarray:
    """3 finite numbers, none beyond ``limit`` (largest offset, unit, in words)."""
    _refuse_bools(value, name)
    if _has_non_number(value):
        raise ValueError(f"{name} must be 3 numbers, got {value!r}")
    try:
        v = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be 3 numbers, got {value!r}") from None
    if v.shape != (3,):
        raise ValueError(f"{name} must be 3 numbers, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be finite, got {v.tolist()}")
    bound, unit, words = limit
    if np.max(np.abs(v)) > bound:
        said = f"{bound:.3g} {unit}" + (f" = {words}" if words else "")
        raise ValueError(f"{name} is not a plausible offset (at most {said} per axis; "
                         f"a wrong unit or file?): {v.tolist()}")
    return v


def _matrix(value: object, name: str, scale_range: tuple[float, float]) -> np.ndarray:
    """A 3x3 correction matrix: finite, not singular, no axis flip, its scale
    |det|^(1/3) within ``scale_range`` and within MAX_RELATIVE_DISTORTION of that
    multiple of the identity.

    Everything is computed from the rows normalised to unit length (their norms kept in
    logs), so entries near the float limits (1e308, 1e-300) neither overflow nor
    underflow: such a matrix is refused as not a plausible correction, not as singular,
    and without a numpy warning.
    """
    _refuse_bools(value, name)
    if _has_non_number(value):
        raise ValueError(f"{name} must be a 3x3 array of numbers, got {value!r}")
    try:
        m = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a 3x3 array of numbers, got {value!r}") from None
    if m.shape != (3, 3):
        raise ValueError(f"{name} must be 3x3 (three rows of three numbers), got shape "
                         f"{m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{name} must be finite, got {m.tolist()}")
    peaks = np.max(np.abs(m), axis=1)
    if np.any(peaks == 0.0):
        raise ValueError(f"{name} is singular (it would flatten the measured vector): "
                         f"{m.tolist()}")
    # Each row divided by its largest entry (all in [-1, 1], one of them ±1), then by
    # its norm (between 1 and sqrt(3)): |det| of the result is |det m| relative to the
    # product of row norms, in [0, 1] (Hadamard), and the log scale needs no product.
    with np.errstate(under="ignore"):  # a 1e-300 beside a 1 becomes 0: harmless here
        unit = m / peaks[:, None]
        norms = np.linalg.norm(unit, axis=1)
        unit /= norms[:, None]
    relative_det = float(np.linalg.det(unit))
    if abs(relative_det) < MIN_RELATIVE_DET:
        raise ValueError(f"{name} is singular (it would flatten the measured vector): "
                         f"{m.tolist()}")
    # In logs: |det|^(1/3) of 1.7e308 entries is beyond the largest float.
    log10_scale = float(np.sum(np.log10(peaks) + np.log10(norms))
                        + math.log10(abs(relative_det))) / 3.0
    low, high = scale_range
    if not math.log10(low) <= log10_scale <= math.log10(high):
        shown = f"{10.0 ** log10_scale:.3g}" if abs(log10_scale) < 300 else f"1e{log10_scale:+.0f}"
        raise ValueError(f"{name} is not a plausible correction (scale |det|^(1/3) = "
                         f"{shown}, not in {low:g}..{high:g}; a wrong unit or file?): "
                         f"{m.tolist()}")
    scale = 10.0 ** log10_scale
    with np.errstate(over="ignore", invalid="ignore"):  # a 1e308 entry: inf, refused below
        distortion = np.max(np.abs(m / scale - np.eye(3) * np.sign(relative_det)))
    if relative_det < 0.0 or not distortion <= MAX_RELATIVE_DISTORTION:
        raise ValueError(f"{name} is not a plausible correction (a few percent from a "
                         f"multiple of the identity, no axis flip): {m.tolist()}")
    return m


@dataclass(frozen=True, eq=False)  # eq on arrays is ambiguous; compare fields explicitly
class SensorCalibration:
    """Offsets and correction matrices, applied as ``M @ (raw - offset)`` (body FRD, SI).

    ``gyro_offset`` [rad/s] and ``gyro_matrix`` (scale and cross-axis; identity in files
    written before it existed); ``accel_offset`` [m/s^2] and ``accel_matrix``;
    ``mag_offset`` (hard iron, in the unit of the magnetometer vectors: gauss for every
    built-in board profile) and ``mag_matrix`` (soft iron). Only the magnetometer's
    direction matters to the estimators, so its matrix's overall scale is free.
    """

    gyro_offset: np.ndarray = field(default_factory=_zeros)
    gyro_matrix: np.ndarray = field(default_factory=_eye)
    accel_offset: np.ndarray = field(default_factory=_zeros)
    accel_matrix: np.ndarray = field(default_factory=_eye)
    mag_offset: np.ndarray = field(default_factory=_zeros)
    mag_matrix: np.ndarray = field(default_factory=_eye)

    def __post_init__(self) -> None:
        for _, _, _, off, mat, limit, scales in _SECTIONS:
            object.__setattr__(self, off, _vector(getattr(self, off), off, limit))
            if mat is not None:
                object.__setattr__(self, mat, _matrix(getattr(self, mat), mat, scales))
        for name in ("gyro_offset", "gyro_matrix", "accel_offset", "accel_matrix",
                     "mag_offset", "mag_matrix"):
            getattr(self, name).setflags(write=False)

    @property
    def is_identity(self) -> bool:
        return (not self.gyro_offset.any() and not self.accel_offset.any()
                and not self.mag_offset.any() and np.array_equal(self.gyro_matrix, np.eye(3))
                and np.array_equal(self.accel_matrix, np.eye(3))
                and np.array_equal(self.mag_matrix, np.eye(3)))

    # --- applying ------------------------------------------------------------------
    def gyro(self, v: np.ndarray) -> np.ndarray:
        """Corrected rates for (..., 3) vectors."""
        return (np.asarray(v, dtype=float) - self.gyro_offset) @ self.gyro_matrix.T

    def accel(self, v: np.ndarray) -> np.ndarray:
        return (np.asarray(v, dtype=float) - self.accel_offset) @ self.accel_matrix.T

    def mag(self, v: np.ndarray) -> np.ndarray:
        return (np.asarray(v, dtype=float) - self.mag_offset) @ self.mag_matrix.T

    def affine(self, sensor: str) -> tuple[np.ndarray, np.ndarray]:
        """(M, c) with ``corrected = M @ raw + c`` — for folding into other matrices."""
        if sensor == "gyro":
            return self.gyro_matrix, -self.gyro_matrix @ self.gyro_offset
        if sensor == "accel":
            return self.accel_matrix, -self.accel_matrix @ self.accel_offset
        if sensor == "mag":
            return self.mag_matrix, -self.mag_matrix @ self.mag_offset
        raise ValueError(f"unknown sensor {sensor!r}; valid: gyro, accel, mag")

    # --- files ---------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: dict) -> SensorCalibration:
        """From the TOML tables ``[gyro]``, ``[accel]``, ``[mag]`` (each optional)."""
        known = {s[0] for s in _SECTIONS} | {"meta"}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown calibration table(s) {unknown}; valid: "
                             f"{sorted(known)}")
        values: dict[str, np.ndarray] = {}
        for table, off_key, mat_key, off, mat, limit, scales in _SECTIONS:
            section = data.get(table, {})
            if not isinstance(section, dict):
                raise ValueError(f"[{table}] must be a table")
            allowed = {off_key} | ({mat_key} if mat_key else set())
            if table in data and not section:
                # (a file cut after its header: the sensor would go uncorrected unsaid)
                raise ValueError(f"[{table}] is empty; give {' and/or '.join(sorted(allowed))}"
                                 f", or leave the table out")
            extra = sorted(set(section) - allowed)
            if extra:
                raise ValueError(f"unknown key(s) {extra} in [{table}]; valid: "
                                 f"{sorted(allowed)}")
            if off_key in section:
                values[off] = _vector(section[off_key], f"{table}.{off_key}", limit)
            if mat_key and mat_key in section:
                values[mat] = _matrix(section[mat_key], f"{table}.{mat_key}", scales)
        return cls(**values)

    @classmethod
    def load(cls, path: str | Path) -> SensorCalibration:
        """Read a calibration TOML file; ValueError (with the file name) if it is bad."""
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")  # TOML is UTF-8, whatever the locale
        except OSError as exc:
            raise ValueError(f"cannot read calibration file {p}: {exc}") from exc
        except UnicodeDecodeError as exc:  # a ValueError that does not name the file
            raise ValueError(f"{p}: not valid TOML (not UTF-8 text: byte "
                             f"{exc.object[exc.start]:#04x} at offset {exc.start})") from exc
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{p}: not valid TOML ({exc})") from exc
        if not set(data) - {"meta"}:  # (an unknown table is said by from_dict)
            # An empty (or truncated, or wrong) file would apply nothing without a word.
            raise ValueError(f"{p}: no [gyro], [accel] or [mag] table")
        try:
            return cls.from_dict(data)
        except ValueError as exc:
            raise ValueError(f"{p}: {exc}") from exc

    def to_toml(self, comment: str = "") -> str:
        """The file text: ``[gyro]``, ``[accel]``, ``[mag]``, each ``offset`` and ``matrix``."""

        def num(x: float) -> str:
            return repr(float(x)) if math.isfinite(x) else "nan"

        def vec(v: np.ndarray) -> str:
            return "[" + ", ".join(num(x) for x in v) + "]"

        lines = [f"# {line}" for line in comment.splitlines()]
        lines.append("# attitude-bridge sensor calibration: corrected = matrix @ (raw - offset),")
        lines.append("# body FRD, SI (rad/s, m/s^2; magnetometer in gauss), after board scaling "
                     "and rotation.")
        for table, off_key, mat_key, off, mat, _, _ in _SECTIONS:
            lines += ["", f"[{table}]", f"{off_key} = {vec(getattr(self, off))}"]
            if mat_key:
                rows = ",\n    ".join(vec(r) for r in getattr(self, mat))
                lines.append(f"{mat_key} = [\n    {rows},\n]")
        return "\n".join(lines) + "\n"

    def save(self, path: str | Path, comment: str = "") -> None:
        Path(path).write_text(self.to_toml(comment))
