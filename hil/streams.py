"""Message streams and their rates, as MAV_CMD_SET_MESSAGE_INTERVAL changes them.

Each stream is NATURAL (every sample, reading or fix the board has), off, or sent at an
interval: a candidate at time t goes out when t reaches the stream's next due time,
which then advances by the interval (so the average rate is the one asked, up to what
the sensor produces: at most one message per sample). This is how an autopilot's
stream scheduler behaves: it sends the newest data when the interval has elapsed.

The link's receiver (event loop) changes intervals while the firmware (a worker
thread) builds the next chunk; a lock keeps the two apart. A change applies from the
next chunk on (at most ~0.1 s later), like a real autopilot's next stream cycle.

``ON_REQUEST_STREAMS`` (EXTENDED_SYS_STATE) start off and get their own default
interval when asked for the default rate; a board without a flight state has none.
``request_once`` (MAV_CMD_REQUEST_MESSAGE) makes a stream send its next candidate
whatever its interval, once.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterable

from .personality import NATURAL, ON_REQUEST_STREAMS, Personality

OFF = 0.0


class StreamTable:
    def __init__(self, personality: Personality, imu_message: str, sample_period_s: float,
                 flight_state: bool = True):
        self.personality = personality
        self.imu_message = imu_message
        self._eps = 0.25 * sample_period_s
        self._lock = threading.Lock()
        self._interval: dict[str, float | None] = {}
        self._next_due: dict[str, float] = {}
        self._once: set[str] = set()
        kinds = personality.streams + (tuple(ON_REQUEST_STREAMS) if flight_state else ())
        for kind in kinds:
            self._interval[kind] = self.startup_interval(kind)

    def default_interval(self, kind: str) -> float | None:
        """The interval "the default rate" gives (NATURAL, OFF or seconds): the start-up
        one, or for a stream sent only on request its own."""
        if kind in ON_REQUEST_STREAMS:
            return ON_REQUEST_STREAMS[kind]
        return self.startup_interval(kind)

    def startup_interval(self, kind: str) -> float | None:
        """The personality's start-up interval (NATURAL, OFF or seconds)."""
        if kind in ON_REQUEST_STREAMS:
            return OFF
        p = self.personality
        if kind in p.defaults:
            return p.defaults[kind]
        if kind in p.imu_messages:
            return NATURAL if kind == self.imu_message else OFF
        return NATURAL

    def knows(self, kind: str) -> bool:
        return kind in self._interval

    def interval(self, kind: str) -> float | None:
        """NATURAL, OFF (0) or the interval [s]; OFF for streams it does not have."""
        with self._lock:
            return self._interval.get(kind, OFF)

    def active(self, kinds: Iterable[str]) -> list[str]:
        """Those of kinds that are on, or have a message requested."""
        with self._lock:
            return [k for k in kinds if self._interval.get(k, OFF) != OFF or k in self._once]

    def request_once(self, kind: str) -> None:
        """Send the next candidate of a stream the board has, whatever its interval
        (nothing to do for one sent with every sample already)."""
        if kind not in self._interval:
            raise KeyError(kind)
        with self._lock:
            if self._interval[kind] is not NATURAL:
                self._once.add(kind)

    def set_interval(self, kind: str, interval_s: float | None) -> None:
        """NATURAL, OFF or an interval [s] for a stream the board has."""
        if kind not in self._interval:
            raise KeyError(kind)
        if interval_s is not None and not (math.isfinite(interval_s) and interval_s >= 0.0):
            raise ValueError(f"bad interval {interval_s}")
        with self._lock:
            self._interval[kind] = interval_s
            self._next_due.pop(kind, None)  # the new rate starts with the next sample
            if interval_s is NATURAL:
                self._once.discard(kind)

    def due(self, kind: str, t: float) -> bool:
        """Whether the candidate of ``kind`` at time t goes out (advances the stream)."""
        with self._lock:
            if kind in self._once:  # a requested message, besides the stream's own
                self._once.discard(kind)
                return True
            interval = self._interval.get(kind, OFF)
            if interval is NATURAL:
                return True
            if interval == OFF:
                return False
            due = self._next_due.get(kind, -math.inf)
            if t < due - self._eps:
                return False
            nxt = due + interval
            self._next_due[kind] = nxt if nxt > t else t + interval
            return True
