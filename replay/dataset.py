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


class ReplayInputError(ValueError):
    """A file that cannot be replayed: missing, unknown format, no IMU, no overlap..."""


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

    def __post_init__(self) -> None:
        if self.north not in NORTH_KINDS:
            raise ValueError(f"reference north must be one of {NORTH_KINDS}, got {self.north!r}")
        if self.kind not in REFERENCE_KINDS:
            raise ValueError(f"reference kind must be one of {REFERENCE_KINDS}, got {self.kind!r}")
        if self.q.shape != (self.t.shape[0], 4):
            raise ValueError(f"reference q must be ({self.t.shape[0]}, 4), got {self.q.shape}")


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
        return float(1e3 * np.std(self._steps)) if self._steps.size else 0.0

    @cached_property
    def dt(self) -> np.ndarray:
        """Per-sample step for the estimators: the first sample gets the mean step.

        Cached: computed once per recording, reused by every tune grid point.
        """
        d = np.diff(self.t, prepend=np.nan)
        d[0] = 1.0 / self.rate_hz
        return d
