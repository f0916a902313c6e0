"""Velocity aiding: the vehicle's own velocity, handed to the estimators with its age.

A velocity tells an estimator how the vehicle accelerates, so that the accelerometer's
specific force can be split into gravity and motion (``vel=``/``vel_age=`` of
``Estimator.update``). It must be honest about time: a GPS velocity reaches the
autopilot ~0.1 s after the instant it is valid for, and the link adds more; used as
if it were current, it would tell the filter the wrong acceleration in every turn.

Per vehicle, from its autopilot component, in order of preference (the best one heard
in the last ``SOURCE_ALIVE_S`` is used, the others are ignored and counted):

1. LOCAL_POSITION_NED ``vx, vy, vz`` [m/s] (the autopilot's navigation solution);
2. GLOBAL_POSITION_INT ``vx, vy, vz`` [cm/s];
3. GPS_RAW_INT ``vel`` [cm/s] along ``cog`` [cdeg]: horizontal only (vertical NaN).

Each fix is stamped with its message's own time (``time_boot_ms`` / ``time_usec``, the
vehicle's boot clock, the clock of the IMU stamps too). At the next IMU sample it goes
to every estimator with ``vel_age`` = that sample's time − the fix's time, after
unwrapping a 32-bit microsecond IMU clock. A stamp of 0 (PX4 SIH's GPS_RAW_INT) or one
that is UNIX time rather than time since boot (ArduPilot's GPS_RAW_INT) says nothing
about the boot clock: the fix is then placed by its arrival against the IMU stream's
arrival, which knows only the link's delay, not the receiver's (``stamp: arrival`` in
the status says so).

Dropped and counted: no 3D fix or unknown speed (``no_fix``), non-finite or faster than
``MAX_SPEED_M_S`` (``implausible``), a stamp not newer than the last one of its source
(``old``: a repeat or reordered datagram), older than ``max_age_s`` when its IMU sample
comes (``stale``), further in the future than ``MAX_FUTURE_S`` (``future``), or replaced
by a newer fix before any IMU sample took it (``superseded``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..wire.mav import MAVLinkMessage, mavlink

ID_LOCAL_POSITION_NED = mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED
ID_GLOBAL_POSITION_INT = mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT
ID_GPS_RAW_INT = mavlink.MAVLINK_MSG_ID_GPS_RAW_INT
#: Velocity messages, best first.
PREFERENCE = (ID_LOCAL_POSITION_NED, ID_GLOBAL_POSITION_INT, ID_GPS_RAW_INT)
VELOCITY_MESSAGE_IDS = frozenset(PREFERENCE)
NAMES = {ID_LOCAL_POSITION_NED: "LOCAL_POSITION_NED",
         ID_GLOBAL_POSITION_INT: "GLOBAL_POSITION_INT", ID_GPS_RAW_INT: "GPS_RAW_INT"}

#: A better source heard within this long [s] (local time) keeps the worse ones unused.
SOURCE_ALIVE_S = 3.0
#: Faster than this [m/s] is no vehicle the bridge serves: a corrupted or forged value.
MAX_SPEED_M_S = 150.0
#: A fix stamped up to this far after its IMU sample is taken as current (millisecond
#: stamps, and two messages stamped at slightly different points of one cycle).
FUTURE_TOLERANCE_S = 0.05
#: A fix further ahead of the IMU samples than this is not on their clock.
MAX_FUTURE_S = 1.0
#: No vehicle has been up for this long [s] (3 years): a larger stamp is UNIX time.
MAX_UPTIME_S = 1e8
#: A 32-bit microsecond IMU clock wraps after this long [s].
WRAP_US_S = 2.0**32 * 1e-6
DROP_CAUSES = ("no_fix", "implausible", "old", "stale", "future", "superseded")
#: Used fixes remembered for the rate and age statistics.
_RECENT = 256
_RATE_WINDOW_S = 5.0


@dataclass(slots=True)
class VelocityFix:
    """One velocity measurement as it came off the link."""

    source: int  # message id
    stamp_s: float | None  # vehicle boot clock [s]; None: place it by its arrival
    vel: np.ndarray  # (3,) NED, true north [m/s]; NaN components unknown
    arrival: float  # time.perf_counter() when read


def parse_velocity(msg: MAVLinkMessage, msg_id: int) -> tuple[VelocityFix | None, str]:
    """(fix, "") or (None, drop cause) for a velocity message; ``arrival`` left 0."""
    if msg_id == ID_LOCAL_POSITION_NED:
        vel = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        stamp = msg.time_boot_ms * 1e-3
    elif msg_id == ID_GLOBAL_POSITION_INT:
        vel = np.array([msg.vx, msg.vy, msg.vz], dtype=float) * 0.01
        stamp = msg.time_boot_ms * 1e-3
    else:
        if msg.fix_type < mavlink.GPS_FIX_TYPE_3D_FIX or msg.vel == 65535 or \
                msg.cog == 65535:
            return None, "no_fix"
        speed, course = msg.vel * 0.01, math.radians(msg.cog * 0.01)
        vel = np.array([speed * math.cos(course), speed * math.sin(course), math.nan])
        stamp = msg.time_usec * 1e-6
    known = vel[np.isfinite(vel)]
    if not np.all(np.isfinite(vel[:2])) or float(np.sqrt(np.sum(known * known))) > \
            MAX_SPEED_M_S or (msg_id != ID_GPS_RAW_INT and not math.isfinite(vel[2])):
        return None, "implausible"
    if stamp <= 0.0 or stamp >= MAX_UPTIME_S:
        return VelocityFix(msg_id, None, vel, 0.0), ""
    return VelocityFix(msg_id, stamp, vel, 0.0), ""


@dataclass
class VelocityAiding:
    """The velocity input of one vehicle (see module docstring)."""

    max_age_s: float = 0.5
    pending: VelocityFix | None = None
    used: int = 0
    ignored: int = 0  # fixes of a worse source while a better one is heard
    dropped: dict[str, int] = field(default_factory=lambda: dict.fromkeys(DROP_CAUSES, 0))
    last_heard: dict[int, float] = field(default_factory=dict)  # source -> arrival
    last_stamp: dict[int, float] = field(default_factory=dict)  # source -> newest stamp
    source: int | None = None  # the source in use
    by_arrival: bool = False  # its stamps say nothing: placed by arrival
    recent: deque = field(default_factory=lambda: deque(maxlen=_RECENT))  # (board t, age)

    def offer(self, msg: MAVLinkMessage, msg_id: int, arrival: float) -> None:
        """A velocity message from the vehicle's autopilot."""
        better = [s for s in PREFERENCE[:PREFERENCE.index(msg_id)]
                  if arrival - self.last_heard.get(s, -math.inf) <= SOURCE_ALIVE_S]
        fix, cause = parse_velocity(msg, msg_id)
        if better:
            self.ignored += 1
            return
        if fix is None:
            self.dropped[cause] += 1
            return
        self.last_heard[msg_id] = arrival
        fix.arrival = arrival
        if fix.stamp_s is not None:
            if fix.stamp_s <= self.last_stamp.get(msg_id, -math.inf):
                self.dropped["old"] += 1
                return
            self.last_stamp[msg_id] = fix.stamp_s
        if self.pending is not None and self.pending.source == msg_id:
            self.dropped["superseded"] += 1  # (a worse source's fix just gives way)
        self.pending = fix
        if self.source != msg_id:
            self.source = msg_id
            self.recent.clear()
        self.by_arrival = fix.stamp_s is None

    def take(self, t: float, arrival: float) -> tuple[np.ndarray | None, float]:
        """(vel, vel_age) for the IMU sample at board time ``t`` read at ``arrival``:
        the pending fix if there is one that this sample may carry, else (None, 0)."""
        fix = self.pending
        if fix is None:
            return None, 0.0
        if fix.stamp_s is None:
            valid = t - max(0.0, arrival - fix.arrival)
        else:
            valid = fix.stamp_s + round((t - fix.stamp_s) / WRAP_US_S) * WRAP_US_S
        age = t - valid
        if age < -FUTURE_TOLERANCE_S:
            if age < -MAX_FUTURE_S:
                self.pending = None
                self.dropped["future"] += 1
            return None, 0.0  # (an older, held-back IMU sample: a later one takes it)
        self.pending = None
        age = max(age, 0.0)
        if age > self.max_age_s:
            self.dropped["stale"] += 1
            return None, 0.0
        self.used += 1
        self.recent.append((t, age))
        return fix.vel, age

    def forget_pending(self) -> None:
        """The IMU timeline restarted: a fix placed on the old one is of no use."""
        self.pending = None

    def status(self) -> dict[str, Any]:
        """Source, rate over the last few seconds of board time, median age, counts."""
        rate = age_ms = None
        if self.recent:
            t_last = self.recent[-1][0]
            window = [a for t, a in self.recent if t >= t_last - _RATE_WINDOW_S]
            span = t_last - min(t for t, _ in self.recent if t >= t_last - _RATE_WINDOW_S)
            rate = round((len(window) - 1) / span, 2) if span > 0 else None
            age_ms = round(float(np.median(window)) * 1e3, 1)
        return {"source": NAMES.get(self.source) if self.source is not None else None,
                "stamp": None if self.source is None else
                ("arrival" if self.by_arrival else "message"),
                "rate_hz": rate, "median_age_ms": age_ms, "used": self.used,
                "ignored": self.ignored, "dropped": dict(self.dropped)}
