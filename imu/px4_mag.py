"""PX4's magnetometer without PX4's own bias estimate in it: the one policy the bridge and
the replay both follow.

PX4 fills HIGHRES_IMU's field with its calibrated magnetometer (``vehicle_magnetometer``)
*minus the magnetometer bias its EKF2 estimates* (``estimator_sensor_bias``; PX4's
``HIGHRES_IMU`` stream). That bias is a state of PX4's filter, not of the sensor: it moves
when EKF2 re-aligns its field after the first climb and settles differently from run to
run, so another estimator reading HIGHRES_IMU sees a body-frame offset that comes and
goes (in PX4 SIH flights the field's azimuth moved by 3° for 8 s after take-off while
the sensor's own did not). SCALED_IMU carries ``sensor_mag`` as the sensor gave it:
without that estimate, but also without PX4's calibration.

So the raw reading is used only where it *is* the calibrated one. PX4 says so in its
parameters: the first magnetometer's calibration offsets (``CALIBRATION_PARAMS``) are
exactly 0 only where it was never calibrated (a simulator: PX4 refuses to arm a real
vehicle with an uncalibrated compass), since a calibration always finds some. The data
must agree as well: while the vehicle streams both, their mean fields over ``WINDOW_S``
are compared. A calibration the raw reading lacks (the parameters of another sensor than
SCALED_IMU's, a calibration made since) is a constant offset in the body frame: it is in
every window. EKF2's estimate is not: it jumps when EKF2 re-aligns its field, for a
window or two, by as much as a sixth of the field's strength, and comes back while the
raw field holds still (docs/accuracy.md, "Live flights"). So the offsets of the
last ``MEMORY_WINDOWS`` windows are averaged, as vectors, and a mean further than
``AGREE`` of the field's strength from zero keeps HIGHRES_IMU's for good, and says so:
a missing calibration shows in the first window already, EKF2's excursions are diluted.
``AGREE`` is hand-set: 3x what EKF2's estimate moved the mean field of a window in the
PX4 SIH flights recorded here (up to 4.8 % of its strength; 0.5-1.5 % at rest, the
comparison's own noise), below what an uncalibrated magnetometer on a real board is off
by (its hard-iron offset alone is usually larger).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

#: HIGHRES_IMU's and SCALED_IMU's mean fields are compared over windows this long [s].
WINDOW_S = 5.0
#: Readings of each a window needs before it is judged (PX4 updates HIGHRES_IMU's field
#: at 10-50 Hz, SCALED_IMU's at the 50 Hz asked).
MIN_READINGS = 20
#: Mean fields further apart than this fraction of the field's strength: the raw reading
#: is not the calibrated one (see the module docstring).
AGREE = 0.15
#: The offsets of this many windows (a minute) are averaged for that judgement: long
#: enough to dilute one window of EKF2 re-aligning, short enough that an offset that
#: stays (a calibration made while the bridge runs) is seen within a minute (one of
#: 40 % of the field within half a minute).
MEMORY_WINDOWS = 12
#: A raw reading older than this (by arrival) is not used: SCALED_IMU has stopped [s].
STALE_S = 0.5

#: PX4's calibration offsets of its first magnetometer (SCALED_IMU's), gauss.
CALIBRATION_PARAMS = ("CAL_MAG0_XOFF", "CAL_MAG0_YOFF", "CAL_MAG0_ZOFF")

WAITING, RAW, CALIBRATED = "waiting", "raw", "calibrated"


def calibration_free(params: dict[str, float]) -> bool | None:
    """Whether PX4 applies no calibration to its first magnetometer, from its
    parameters (None: they are not all known)."""
    if not all(name in params for name in CALIBRATION_PARAMS):
        return None
    return all(params[name] == 0.0 for name in CALIBRATION_PARAMS)


@dataclass
class _Window:
    start: float | None = None
    highres: np.ndarray = field(default_factory=lambda: np.zeros(3))
    highres_norm: float = 0.0
    n_highres: int = 0
    raw: np.ndarray = field(default_factory=lambda: np.zeros(3))
    n_raw: int = 0


@dataclass
class RawMagnetometer:
    """Chooses, reading by reading, between HIGHRES_IMU's field and SCALED_IMU's raw one
    (both in gauss, body FRD, after the same mounting rotation)."""

    state: str = WAITING
    #: PX4's parameters say it applies no calibration (None: not known yet)
    uncalibrated: bool | None = None
    #: largest |mean over the remembered windows of (HIGHRES - raw)| / mean |HIGHRES|
    difference: float | None = None
    #: largest |HIGHRES - raw| / |HIGHRES| of a single window (shown, not judged)
    largest_window: float | None = None
    windows: int = 0
    used: int = 0  # HIGHRES_IMU readings replaced by the raw one
    offered: int = 0  # raw readings received
    _latest: np.ndarray | None = None
    _latest_at: float = -math.inf
    _window: _Window = field(default_factory=_Window)
    #: (HIGHRES - raw, mean |HIGHRES|) of the last MEMORY_WINDOWS windows judged
    _offsets: deque = field(default_factory=lambda: deque(maxlen=MEMORY_WINDOWS))

    def reset(self) -> None:
        """Start over (the vehicle rebooted: its calibration may have changed)."""
        self.state, self.difference, self.windows = WAITING, None, 0
        self.largest_window = None
        self.uncalibrated = None
        self._latest, self._latest_at, self._window = None, -math.inf, _Window()
        self._offsets.clear()

    def set_parameters(self, params: dict[str, float]) -> None:
        """The vehicle's parameters (those of ``CALIBRATION_PARAMS`` it has sent)."""
        self.uncalibrated = calibration_free(params)
        if self.uncalibrated is False:
            self.state = CALIBRATED

    def offer_raw(self, mag: np.ndarray, arrival: float) -> None:
        """A SCALED_IMU reading [gauss, FRD] that arrived at ``arrival`` [s]."""
        if not np.all(np.isfinite(mag)) or not mag.any():
            return
        self.offered += 1
        self._latest, self._latest_at = mag, arrival
        if self.state == CALIBRATED or not self.uncalibrated:
            return  # compared only while the raw field may be taken (as in choose)
        w = self._window
        w.raw = w.raw + mag
        w.n_raw += 1

    def choose(self, highres: np.ndarray | None, arrival: float) -> np.ndarray | None:
        """The field to use for a HIGHRES_IMU reading ``highres`` that arrived at
        ``arrival``: the latest raw one where that is the calibrated field and fresh,
        else ``highres``. None stays None (no field, or one judged disturbed). The
        reading also goes into the comparison (only while the raw field may be taken:
        the parameters say "uncalibrated"; every IMU sample comes through here)."""
        if self.state == CALIBRATED or highres is None or not self.uncalibrated:
            return highres
        self._compare(highres, arrival)
        if self.state != RAW or arrival - self._latest_at > STALE_S:
            return highres
        self.used += 1
        return self._latest

    def _compare(self, highres: np.ndarray, arrival: float) -> None:
        w = self._window
        if w.start is None:
            w.start = arrival
        w.highres = w.highres + highres
        w.highres_norm += math.sqrt(float(highres @ highres))
        w.n_highres += 1
        if arrival - w.start < WINDOW_S:
            return
        if w.n_highres >= MIN_READINGS and w.n_raw >= MIN_READINGS and w.highres_norm > 0:
            gap = w.highres / w.n_highres - w.raw / w.n_raw
            strength = w.highres_norm / w.n_highres
            self.largest_window = max(float(np.linalg.norm(gap)) / strength,
                                      self.largest_window or 0.0)
            self._offsets.append((gap, strength))
            mean_gap = sum(g for g, _ in self._offsets) / len(self._offsets)
            mean_strength = sum(n for _, n in self._offsets) / len(self._offsets)
            difference = float(np.linalg.norm(mean_gap)) / mean_strength
            self.difference = max(difference, self.difference or 0.0)
            self.windows += 1
            self.state = CALIBRATED if difference > AGREE else RAW
        self._window = _Window()

    def status(self) -> dict[str, object]:
        """For the status file: which field is used and how the two compared."""
        return {"source": "SCALED_IMU" if self.state == RAW else "HIGHRES_IMU",
                "state": self.state, "windows": self.windows, "raw_readings": self.offered,
                "replaced": self.used,
                "difference_pct": (None if self.difference is None
                                   else round(100 * self.difference, 2)),
                "largest_window_pct": (None if self.largest_window is None
                                       else round(100 * self.largest_window, 2))}

    def describe(self) -> str:
        """One line for a log or a replay note."""
        pct = 100 * (self.difference or 0.0)
        if self.state == RAW:
            return (f"magnetometer: SCALED_IMU's raw field, which is PX4's calibrated one "
                    f"(within {pct:.1f} % over {self.windows} windows of {WINDOW_S:g} s); "
                    f"HIGHRES_IMU's has PX4's own bias estimate taken out")
        if self.state == CALIBRATED and self.uncalibrated is False:
            return ("magnetometer: HIGHRES_IMU's (PX4 calibrates this sensor: "
                    f"{', '.join(CALIBRATION_PARAMS)} are not 0)")
        if self.state == CALIBRATED:
            return (f"magnetometer: HIGHRES_IMU's (the raw SCALED_IMU field is {pct:.1f} % "
                    f"away from it)")
        if self.uncalibrated is None:
            return ("magnetometer: HIGHRES_IMU's (PX4's calibration parameters "
                    f"{', '.join(CALIBRATION_PARAMS)} not known)")
        return "magnetometer: HIGHRES_IMU's (no raw SCALED_IMU field to compare with yet)"
