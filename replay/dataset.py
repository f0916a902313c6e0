"""What every reader produces: IMU samples and a reference attitude, each on its own clock.

Readers do the unit and frame work (board profiles, Gauss/µT, FRD); everything after
them (evaluation, plots, tuning) only sees a :class:`Recording`.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

REFERENCE_KINDS = ("truth", "autopilot")
NORTH_KINDS = ("true", "magnetic")
#: No IMU samples faster than this: the fastest MEMS gyros output 32 kHz (ICM-42688's
#: top ODR), a flight controller's FIFO at most 8 kHz. A higher mean rate means time
#: in the wrong unit (ms, µs or ns read as seconds) or a wrong ``rate``, and every dt
#: would be off by that factor: the file is refused instead of scored.
MAX_RATE_HZ = 100e3
#: A quaternion shorter than this is no attitude (an all-zero row: "no value")
MIN_QUATERNION_NORM = 1e-6


class ReplayInputError(ValueError):
    """A file that cannot be replayed: missing, unknown format, no IMU, no overlap..."""


def usable_quaternions(q: np.ndarray) -> np.ndarray:
    """(M,) True where a row is an attitude: finite, with a finite norm not about zero.

    A zero row is how several logs say "no value"; a row whose norm overflows cannot
    be normalised. Either, used as a reference, would score a made-up attitude.
    """
    q = np.asarray(q, dtype=float)
    finite = np.all(np.isfinite(q), axis=1)
    with np.errstate(over="ignore", invalid="ignore"):
        norm = np.linalg.norm(np.where(finite[:, None], q, 0.0), axis=1)
    return finite & np.isfinite(norm) & (norm > MIN_QUATERNION_NORM)


def usable_magnetometer(mag: np.ndarray) -> np.ndarray:
    """(N,) True where a magnetometer reading has a direction: finite and not all zero
    (an all-zero reading is an unset field; the estimators skip both kinds)."""
    return np.all(np.isfinite(mag), axis=1) & np.any(mag != 0.0, axis=1)


def damaged_magnetometer_rows(mag: np.ndarray) -> int:
    """Readings without a direction, leaving out the all-NaN rows before the first good
    one: those say "no reading yet" (a slower magnetometer held on the IMU clock)."""
    usable = usable_magnetometer(mag)
    not_yet = (np.arange(len(mag)) < int(np.argmax(usable))) & np.all(np.isnan(mag), axis=1)
    return int(np.count_nonzero(~usable & ~not_yet))


def scale_safe_std(x: np.ndarray) -> float:
    """Standard deviation that does not overflow for any finite ``x`` (squaring steps of
    1e300 s from a nonsense rate would, with a numpy warning)."""
    scale = float(np.max(np.abs(x))) if x.size else 0.0
    return scale * float(np.std(x / scale)) if scale > 0.0 else 0.0


@dataclass(frozen=True)
class TimeCleanup:
    """Samples dropped from one stream because their timestamp did not move forward."""

    kept: int = 0
    duplicates: int = 0  # same timestamp as the previous kept sample
    backwards: int = 0  # earlier than the previous kept sample
    non_finite: int = 0  # NaN/inf timestamp

    @property
    def dropped(self) -> int:
        return self.duplicates + self.backwards + self.non_finite

    def __str__(self) -> str:
        """"3 of 5000 (1 duplicate time, 2 going backwards)" for the replay summary."""
        parts = [f"{n} {what}" for n, what in ((self.duplicates, "duplicate time"),
                                                (self.backwards, "going backwards"),
                                                (self.non_finite, "time not a number"))
                 if n]
        return f"{self.dropped} of {self.kept + self.dropped} ({', '.join(parts)})"


@dataclass(frozen=True)
class Reference:
    """Attitude to score against, on its own time base.

    ``q`` rotates body vectors into the recording's world frame (same body axes as the
    IMU samples). ``kind`` is "truth" (simulator/optical ground truth) or "autopilot"
    (the vehicle's own estimate, e.g. PX4 vehicle_attitude). NaN rows mean "no reference".
    """

    t: np.ndarray  # (M,) seconds, strictly increasing
    q: np.ndarray  # (M, 4) [w, x, y, z]
    kind: str
    source: str  # where it came from, e.g. "vehicle_attitude_groundtruth"
    cleanup: TimeCleanup = field(default_factory=TimeCleanup)
    # "true": heading relative to true north (simulators, autopilots that apply the
    # declination); "magnetic": relative to the magnetic north the IMU sees (BROAD).
    north: str = "true"
    timing: str = ""  # how its time was obtained when not its own stamp (e.g. arrival)
    #: rows given with a zero or non-finite quaternion (damage; made NaN here). All-NaN
    #: rows are not counted: they are how a file says "no reference here".
    damaged: int = 0

    def __post_init__(self) -> None:
        if self.north not in NORTH_KINDS:
            raise ValueError(f"reference north must be one of {NORTH_KINDS}, got {self.north!r}")
        if self.kind not in REFERENCE_KINDS:
            raise ValueError(f"reference kind must be one of {REFERENCE_KINDS}, got {self.kind!r}")
        if self.q.shape != (self.t.shape[0], 4):
            raise ValueError(f"reference q must be ({self.t.shape[0]}, 4), got {self.q.shape}")
        self._blank_unusable_rows()

    def _blank_unusable_rows(self) -> None:
        """Zero and non-finite quaternions become NaN ("no reference"), counted in
        ``damaged``, however the Reference was made: none is ever scored against."""
        bad = ~usable_quaternions(self.q)
        if not bad.any():
            return
        q = np.array(self.q, dtype=float)
        damaged = bad & ~np.all(np.isnan(q), axis=1)
        q[bad] = np.nan
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "damaged", self.damaged + int(np.count_nonzero(damaged)))

    @property
    def valid(self) -> int:
        """Samples with an attitude."""
        return int(np.count_nonzero(np.all(np.isfinite(self.q), axis=1)))

    def damage_note(self, label: str) -> str:
        """"<label>: K of M quaternions unusable (...)", or "" when none was damaged."""
        if not self.damaged:
            return ""
        return (f"{label}: {self.damaged} of {self.t.shape[0]} quaternions unusable "
                f"(zero or not finite)")


@dataclass(frozen=True)
class Position:
    """Where the vehicle was (WGS-84), for the World Magnetic Model."""

    lat_deg: float
    lon_deg: float
    alt_m: float
    source: str  # message or topic it came from


@dataclass(frozen=True)
class Velocity:
    """World-frame (NED, true north) velocity aligned to the IMU samples.

    The estimators' aiding contract: ``vel`` is NaN except at the IMU sample where a
    measurement became available to the vehicle (a NaN component: that axis unknown,
    e.g. the vertical from a GPS course and speed); ``age`` is the IMU sample's time
    minus the instant the measurement was valid (>= 0, NaN where ``vel`` is NaN).
    """

    vel: np.ndarray  # (N, 3) m/s
    age: np.ndarray  # (N,) s
    source: str
    placement: str  # how a measurement was put on an IMU sample (arrival / own stamp)

    @property
    def count(self) -> int:
        return int(np.count_nonzero(np.any(np.isfinite(self.vel), axis=1)))


@dataclass(frozen=True)
class StateEvent:
    """One report of the vehicle's flight state on the IMU clock (see ``imu.flight_state``).

    ``kind``: ``heartbeat`` (value = base_mode, ``autopilot`` = MAV_AUTOPILOT),
    ``landed_state`` (EXTENDED_SYS_STATE, value = MAV_LANDED_STATE), ``land_detector``
    (value 1 landed, 0 not), ``armed`` (value 1 armed, 0 disarmed).
    """

    t: float
    kind: str
    value: int
    autopilot: int = 0


@dataclass(frozen=True)
class Recording:
    """IMU samples (SI units, body axes of the reference) and an optional reference.

    ``mag`` is None for a 6D recording; its unit is irrelevant (only direction is used).
    ``score_mask`` (N,) selects the IMU samples that count for the RMSE (BROAD's
    ``movement``); None means all samples with a reference.
    """

    path: Path
    format: str  # "ulog" | "tlog" | "npz" | "csv"
    t: np.ndarray  # (N,) seconds, strictly increasing
    gyr: np.ndarray  # (N, 3) rad/s
    acc: np.ndarray  # (N, 3) m/s^2, specific force
    mag: np.ndarray | None  # (N, 3) any unit, NaN where no sample yet
    world: str  # "NED" | "ENU": the frame of reference.q and of the estimates
    body: str  # description of the body axes, e.g. "FRD" or "sensor"
    source: str  # which stream the IMU came from, e.g. "sensor_combined", "RAW_IMU"
    reference: Reference | None = None
    score_mask: np.ndarray | None = None
    cleanup: TimeCleanup = field(default_factory=TimeCleanup)
    notes: tuple[str, ...] = ()  # human-readable remarks from the reader (dropped, trimmed)
    #: those of the notes that say what the log lost (samples dropped, a cut or damaged
    #: file): a score on it is not one on a whole log. Given here, a note is added to
    #: ``notes`` too if the reader left it out.
    damage: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()  # things that make numbers doubtful (wrong board?)
    board: str | None = None  # RAW_IMU board profile used, None when not applicable
    params: Mapping[str, float] = field(default_factory=dict)  # the vehicle's parameters
    position: Position | None = None
    when: _dt.datetime | None = None  # when it was recorded (UTC), for the WMM
    when_source: str = ""
    velocity: Velocity | None = None
    mav_type: int | None = None  # MAVLink MAV_TYPE of the vehicle, None when unknown
    mav_type_source: str = ""  # where it came from (HEARTBEAT, parameter MAV_TYPE)
    mav_autopilot: int | None = None  # MAVLink MAV_AUTOPILOT of the IMU's sender (HEARTBEAT)
    #: the vehicle's own reports of its flight state, in time order (replay.flight)
    state_events: tuple[StateEvent, ...] = ()
    state_events_source: str = ""  # the messages / topics they came from
    #: every kind of reference the file has (REFERENCE_KINDS), whichever was loaded
    references: tuple[str, ...] = ()
    #: the autopilot's own attitude when ``reference`` is another kind (the truth), to
    #: score it beside the estimators; None otherwise
    autopilot: Reference | None = None
    #: readings of a magnetometer the file had without a single usable one: it is left
    #: out (``mag`` None, heading not observable) and this says why
    mag_dropped: int = 0

    def __post_init__(self) -> None:
        if self.reference is not None and self.reference.kind not in self.references:
            object.__setattr__(self, "references", (*self.references, self.reference.kind))
        n = self.t.shape[0]
        for name in ("gyr", "acc", "mag"):
            arr = getattr(self, name)
            if arr is not None and arr.shape != (n, 3):
                raise ValueError(f"{name} must be ({n}, 3), got {arr.shape}")
        if self.score_mask is not None and self.score_mask.shape != (n,):
            raise ValueError(f"score_mask must be ({n},), got {self.score_mask.shape}")
        if self.velocity is not None and (self.velocity.vel.shape != (n, 3)
                                          or self.velocity.age.shape != (n,)):
            raise ValueError(f"velocity must be ({n}, 3) with age ({n},)")
        self._check_rate()
        self._drop_useless_magnetometer()
        lost = tuple(n for n in self._damage_notes() if n not in self.damage)
        if lost:
            object.__setattr__(self, "damage", (*self.damage, *lost))
        self._add_notes(list(self.damage))

    def _check_rate(self) -> None:
        """Refuse a rate no IMU has (:data:`MAX_RATE_HZ`): every dt would be wrong."""
        if self.n > 1 and self.rate_hz > MAX_RATE_HZ:
            raise ReplayInputError(f"{self.path}: IMU rate {self.rate_hz:.4g} Hz implausible: "
                                   f"time not in seconds? (no IMU samples faster than "
                                   f"{MAX_RATE_HZ:g} Hz)")

    def _drop_useless_magnetometer(self) -> None:
        """A magnetometer without one usable reading is no magnetometer: estimators fed
        it would report a heading they never observed."""
        if self.mag is None or usable_magnetometer(self.mag).any():
            return
        object.__setattr__(self, "mag_dropped", self.n)
        object.__setattr__(self, "mag", None)

    def _damage_notes(self) -> list[str]:
        """One counted note per damaged stream (the gyro's are the estimators' skipped
        samples, said under the scores)."""
        notes = []
        if self.mag_dropped:
            notes.append(f"magnetometer: none of {self.mag_dropped} readings usable (NaN, "
                         f"infinite or zero): replayed without it, heading not observable")
        elif self.mag is not None and (bad := damaged_magnetometer_rows(self.mag)):
            notes.append(f"magnetometer: {bad} of {self.n} readings unusable (NaN, infinite "
                         f"or zero)")
        bad_acc = int(np.count_nonzero(~np.all(np.isfinite(self.acc), axis=1)))
        if bad_acc:
            notes.append(f"accelerometer: {bad_acc} of {self.n} readings not finite (the "
                         f"estimators use the gyro alone there)")
        for ref, label in ((self.reference, "reference"),
                           (self.autopilot, "the autopilot's attitude")):
            if ref is not None and (note := ref.damage_note(label)):
                notes.append(note)
        return notes

    def _add_notes(self, notes: list[str]) -> None:
        """Append the notes not there yet (a Recording copied with dataclasses.replace
        runs this again)."""
        new = tuple(n for n in notes if n not in self.notes)
        if new:
            object.__setattr__(self, "notes", (*self.notes, *new))

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0]) if self.n > 1 else 0.0

    @cached_property
    def _steps(self) -> np.ndarray:
        """The IMU's time steps, without the outages (steps over 5x the median)."""
        d = np.diff(self.t)
        if d.size == 0:
            return d
        return d[(d > 0.0) & (d <= 5.0 * np.median(d))]

    @cached_property
    def rate_hz(self) -> float:
        """Mean IMU rate over the steps between outages, used as the estimators' nominal
        rate (dt comes from ``t``). The mean, not the median step: ArduPilot's 333 Hz
        RAW_IMU comes in uneven 2.5 ms / 5 ms steps."""
        if self._steps.size == 0:
            return 1.0
        return float(1.0 / np.mean(self._steps))

    @cached_property
    def jitter_ms(self) -> float:
        """Standard deviation of the IMU's time steps (outages left out) [ms]."""
        return 1e3 * scale_safe_std(self._steps)

    @cached_property
    def dt(self) -> np.ndarray:
        """Per-sample step for the estimators: the first sample gets the mean step.

        Cached: computed once per recording, reused by every tune grid point.
        """
        d = np.diff(self.t, prepend=np.nan)
        d[0] = 1.0 / self.rate_hz
        return d
