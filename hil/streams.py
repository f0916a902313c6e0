"""Message streams and their rates, as MAV_CMD_SET_MESSAGE_INTERVAL changes them.

Each stream is NATURAL (every sample, reading or fix the board has), off, or sent at an
interval: a candidate at time t goes out when t reaches the stream's next due time,
which then advances by the interval (so the average rate is the one asked, up to what
the sensor produces: at most one message per sample). This is how an autopilot's
stream scheduler behaves: it sends the newest data when the interval has elapsed.

The link's receiver (event loop) changes intervals while the firmware (a worker
thread) builds the next chunk; a lock keeps the two apart. A change applies from the
next chunk on (at most ~0.1 s later), like a real autopilot's next stream cycle.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterable

from .personality import NATURAL, Personality

OFF = 0.0


class StreamTable:
    def __init__(self, personality: Personality, imu_message: str, sample_period_s: float):
        self.personality = personality
        self.imu_message = imu_message
        self._eps = 0.25 * sample_period_s
        self._lock = threading.Lock()
        self._interval: dict[str, float | None] = {}
        self._next_due: dict[str, float] = {}
        for kind in personality.streams:
            self._interval[kind] = self.default_interval(kind)

    def default_interval(self, kind: str) -> float | None:
        """The personality's start-up interval (NATURAL, OFF or seconds)."""
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
        with self._lock:
            return [k for k in kinds if self._interval.get(k, OFF) != OFF]

    def set_interval(self, kind: str, interval_s: float | None) -> None:
        """NATURAL, OFF or an interval [s] for a stream the board has."""
        if kind not in self._interval:
            raise KeyError(kind)
        if interval_s is not None and not (math.isfinite(interval_s) and interval_s >= 0.0):
            raise ValueError(f"bad interval {interval_s}")
        with self._lock:
            self._interval[kind] = interval_s
            self._next_due.pop(kind, None)  # the new rate starts with the next sample

    def due(self, kind: str, t: float) -> bool:
        """Whether the candidate of ``kind`` at time t goes out (advances the stream)."""
        with self._lock:
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
