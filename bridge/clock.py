"""Board time of one IMU stream, and the verdict on each new timestamp.

Estimators integrate over the sensor's own time steps, so a timestamp that is repeated,
late, or far off would silently corrupt the attitude. Each stamp gets a verdict:

* ``ok`` / ``first`` — use it; ``dt`` is the step since the previous accepted sample;
* ``duplicate`` — a stamp seen recently with the same content (a repeated packet): drop;
* ``reordered`` — behind the last accepted stamp by at most ``reorder_s`` (a packet that
  arrived late): drop, the estimator has already moved past it;
* ``jump`` / ``backwards`` — ahead by more than the jump threshold, or behind by more
  than ``reorder_s``: drop.

A stamp off the current timeline may also be the first of a *new* timeline (the board
clock was stepped, or the board rebooted). When ``resync_after`` consecutive off-timeline
stamps agree with each other, the clock adopts the new timeline: the last one is
accepted as ``resync`` (with the typical sample period as its ``dt``), and the verdicts
of the ones dropped while confirming it are returned in ``reclassified`` so that the
caller can count them as ``clock_step`` instead of as isolated glitches.

The jump threshold is ``max(jump_s, 8 × typical period)``: a gap that long is either a
clock step or a link outage, and in both cases integrating the gyro over it would be
wrong, so it goes through the same confirmation.

Counters that wrap (uint32 milliseconds, 32-bit microsecond timers in a uint64 field)
are unwrapped when the previous stamp sat in the counter's top quarter and the new one
in its bottom quarter.
"""

from __future__ import annotations

from collections import deque

OK, FIRST, RESYNC = "ok", "first", "resync"
DUPLICATE, REORDERED, JUMP, BACKWARDS = "duplicate", "reordered", "jump", "backwards"
ACCEPTED = frozenset((OK, FIRST, RESYNC))

WRAP_32 = 1 << 32
_PERIOD_GAIN = 0.01  # EMA weight of each new step in the typical-period estimate
_JUMP_PERIODS = 8.0


class SampleClock:
    """Unwraps and classifies the timestamps of one stream (see module docstring)."""

    def __init__(self, tick_s: float, wrap_ticks: int = WRAP_32, jump_s: float = 0.1,
                 reorder_s: float = 0.5, resync_after: int = 3, memory: int = 64) -> None:
        self.tick_s = tick_s
        self.wrap = wrap_ticks
        self.jump_ticks_min = jump_s / tick_s
        self.reorder_ticks = reorder_s / tick_s
        self.resync_after = resync_after
        self.wraps = 0
        self.period_ticks: float | None = None  # typical accepted step
        self.last_ticks: int | None = None  # unwrapped ticks of the last accepted sample
        self.reclassified: list[str] = []  # set on RESYNC: verdicts of the candidates
        self._epoch = 0  # ticks added by unwrapping
        self._last_raw = 0
        self._recent: deque[int] = deque(maxlen=memory)
        self._recent_content: dict[int, object] = {}  # stamp -> what the sample carried
        self._candidate: int | None = None  # last stamp of a possible new timeline
        self._candidate_verdicts: list[str] = []

    @property
    def jump_ticks(self) -> float:
        if self.period_ticks is None:
            return self.jump_ticks_min
        return max(self.jump_ticks_min, _JUMP_PERIODS * self.period_ticks)

    def _unwrap(self, raw: int) -> int:
        hi, lo = self.wrap - (self.wrap >> 2), self.wrap >> 2
        last = self._last_raw
        if hi <= last < self.wrap and raw < lo:
            self._epoch += self.wrap  # the counter rolled over
            self.wraps += 1
        elif self._epoch and last < lo and hi <= raw < self.wrap:
            return raw + self._epoch - self.wrap  # a late sample from before the wrap
        return raw + self._epoch

    def _remember(self, ticks: int, content: object) -> None:
        if len(self._recent) == self._recent.maxlen:
            self._recent_content.pop(self._recent[0], None)
        self._recent.append(ticks)
        self._recent_content[ticks] = content

    def _accept(self, raw: int, ticks: int, verdict: str,
                content: object) -> tuple[str, int, float | None]:
        dt: float | None = None
        if verdict == OK:
            step = ticks - self.last_ticks
            dt = step * self.tick_s
            self.period_ticks = step if self.period_ticks is None else \
                self.period_ticks + _PERIOD_GAIN * (step - self.period_ticks)
        elif verdict == RESYNC and self.period_ticks is not None:
            dt = self.period_ticks * self.tick_s
        self.last_ticks = ticks
        self._last_raw = raw
        self._candidate = None
        self._candidate_verdicts = []
        self._remember(ticks, content)
        return verdict, ticks, dt

    def classify(self, raw: int, content: object = None) -> tuple[str, int, float | None]:
        """(verdict, unwrapped ticks, dt seconds or None) for a new raw stamp.

        ``content`` (e.g. the sensor values) tells a repeated packet (same stamp, same
        content: duplicate) from a clock stepped back (same stamp, other content).
        """
        if self.last_ticks is None:
            return self._accept(raw, raw, FIRST, content)
        ticks = self._unwrap(raw)
        step = ticks - self.last_ticks
        if 0 < step <= self.jump_ticks:
            self.reclassified = []
            return self._accept(raw, ticks, OK, content)
        if ticks in self._recent_content and self._recent_content[ticks] == content:
            return DUPLICATE, ticks, None
        verdict = REORDERED if -self.reorder_ticks <= step < 0 else JUMP if step > 0 else BACKWARDS
        # Off the current timeline: a glitch, or the start of a new timeline?
        cand = self._candidate
        if cand is None or not 0 < ticks - cand <= self.jump_ticks:
            self._candidate_verdicts = []
        self._candidate = ticks
        if len(self._candidate_verdicts) + 1 >= self.resync_after:
            self.reclassified = self._candidate_verdicts
            self._epoch = ticks - raw  # keep unwrapping consistent with the new base
            return self._accept(raw, ticks, RESYNC, content)
        self._candidate_verdicts.append(verdict)
        return verdict, ticks, None
