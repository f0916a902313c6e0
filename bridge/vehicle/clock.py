"""Board time of one IMU stream, and the verdict on each new timestamp.

Estimators integrate over the sensor's own time steps, so a timestamp that is repeated,
late, or far off would silently corrupt the attitude; and a hostile sender can forge
stamps. Each stamp gets a verdict:

* ``ok`` / ``first`` — use it; ``dt`` is the step since the previous accepted sample;
* ``gap`` — ahead by more than the jump threshold, by about as much as the local clock
  advanced since the previous accepted sample, with nothing received in between: the
  same timeline after an outage. Used (``dt`` = the typical period); the caller
  re-initialises after a long one;
* ``duplicate`` — a stamp seen recently with the same content (a repeated packet): drop;
* ``reordered`` — behind the last accepted stamp by at most ``reorder_s``: drop;
* ``jump`` / ``backwards`` — off the timeline (ahead out of proportion to the elapsed
  local time, or behind by more than ``reorder_s``): drop — unless it turns out to be
  the start of a new timeline.

A new timeline (the board clock was stepped, or the board rebooted) is adopted only on
sustained evidence, never on a few packets: candidate samples must follow each other
like a real stream for at least ``resync_s`` of board time, arrive at about real-time
pace, and the current timeline must have produced no sample meanwhile (a forger cannot
flip the clock of a vehicle that is still talking). Candidates are kept (bounded) and,
once the timeline is adopted, returned in order so that no data is lost to a genuine
clock step. The adoption is ``reboot`` when time went back to near zero (then the caller
re-initialises), else ``resync``. A boot time reported by the autopilot (SYSTEM_TIME)
that agrees with the candidates shortens the evidence needed for a reboot.

The unwrapped time only moves on accepted samples. Counters that wrap (uint32
milliseconds, 32-bit microsecond timers in a uint64 field) are unwrapped when the
previous accepted stamp sat in the counter's top quarter, the new one in its bottom
quarter, and the wrapped step agrees with the elapsed local time.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Any

OK, FIRST, GAP, RESYNC, REBOOT = "ok", "first", "gap", "resync", "reboot"
DUPLICATE, REORDERED, JUMP, BACKWARDS = "duplicate", "reordered", "jump", "backwards"
ACCEPTED = frozenset((OK, FIRST, GAP, RESYNC, REBOOT))
#: Verdicts after which the estimate must not continue from the old state.
RESTARTS = frozenset((REBOOT,))

WRAP_32 = 1 << 32
_PERIOD_GAIN = 0.01  # EMA weight of each new step in the typical-period estimate
_JUMP_PERIODS = 8.0
#: A step larger than the jump threshold is an outage on the same timeline when it agrees
#: with the local clock to within this (seconds, plus a fraction of the elapsed time).
GAP_TOLERANCE_S = 0.15
GAP_TOLERANCE_REL = 0.1
#: Candidates may run at most this many times faster than the stream ran so far (board
#: seconds per local second; a live stream runs at 1, a replay faster): a burst of forged
#: stamps spanning a second of board time in a few milliseconds is no evidence.
CANDIDATE_PACE = 2.0
_PACE_WINDOW_S = 0.25  # local time over which the stream's pace is measured
_PACE_GAIN = 0.3
#: A new timeline starting below this board time [s], behind the old one, is a reboot.
REBOOT_UPTIME_S = 300.0
#: With the autopilot's SYSTEM_TIME agreeing, a reboot needs this much evidence [s].
REBOOT_CORROBORATED_S = 0.25
BOOT_HINT_TOLERANCE_S = 0.5


@dataclass(slots=True)
class Accepted:
    """One sample to use: its unwrapped ticks, time step (None: nominal), payload."""

    ticks: int
    dt: float | None
    payload: Any


@dataclass(slots=True)
class Verdict:
    """What :meth:`SampleClock.classify` decided about one stamp."""

    verdict: str
    accepted: list[Accepted] = field(default_factory=list)  # in order; empty: dropped
    reclassified: list[str] = field(default_factory=list)  # earlier drops now used
    gap_s: float = 0.0  # local time between the last accepted sample and this timeline


@dataclass(slots=True)
class _Candidate:
    raw: int
    ticks: int  # on the candidate timeline
    arrival: float
    verdict: str
    content: object
    payload: Any


class SampleClock:
    """Unwraps and classifies the timestamps of one stream (see module docstring)."""

    def __init__(self, tick_s: float, wrap_ticks: int = WRAP_32, jump_s: float = 0.1,
                 reorder_s: float = 0.5, resync_s: float = 1.0, memory: int = 64,
                 max_candidates: int = 4096) -> None:
        self.tick_s = tick_s
        self.wrap = wrap_ticks
        self.jump_ticks_min = jump_s / tick_s
        self.reorder_ticks = reorder_s / tick_s
        self.resync_ticks = resync_s / tick_s
        self.max_candidates = max_candidates
        self.wraps = 0
        self.period_ticks: float | None = None  # typical accepted step
        self.last_ticks: int | None = None  # unwrapped ticks of the last accepted sample
        self.last_arrival = 0.0
        self.boot_hint: tuple[float, float] | None = None  # (board s, local arrival)
        self._last_raw = 0
        self._recent: deque[int] = deque(maxlen=memory)
        self._recent_content: dict[int, object] = {}  # stamp -> what the sample carried
        self._cand: list[_Candidate] = []
        self.candidates_dropped = 0  # oldest candidates discarded beyond max_candidates
        self.pace = 1.0  # board seconds per local second of the accepted stream
        self._pace_mark: tuple[int, float] | None = None

    @property
    def jump_ticks(self) -> float:
        if self.period_ticks is None:
            return self.jump_ticks_min
        return max(self.jump_ticks_min, _JUMP_PERIODS * self.period_ticks)

    @property
    def pending(self) -> int:
        """Samples held as evidence for a possible new timeline."""
        return len(self._cand)

    def _follow(self, prev_raw: int, prev_ticks: int, raw: int, elapsed: float) -> int:
        """Ticks of ``raw`` on the timeline whose latest stamp is ``prev_raw``: forward
        across a counter wrap only when the wrapped step agrees with ``elapsed``."""
        d = raw - prev_raw
        hi, lo = self.wrap - (self.wrap >> 2), self.wrap >> 2
        if d < 0 and prev_raw >= hi and raw < lo:
            wrapped = d + self.wrap
            if wrapped <= self.jump_ticks or self._agrees(wrapped, elapsed):
                return prev_ticks + wrapped
        return prev_ticks + d

    def _agrees(self, step_ticks: float, elapsed: float) -> bool:
        """A step of board time as long as the local time that passed."""
        board = step_ticks * self.tick_s
        return abs(board - elapsed) <= GAP_TOLERANCE_S + GAP_TOLERANCE_REL * elapsed

    def _remember(self, ticks: int, content: object) -> None:
        if len(self._recent) == self._recent.maxlen:
            self._recent_content.pop(self._recent[0], None)
        self._recent.append(ticks)
        self._recent_content[ticks] = content

    def _commit(self, raw: int, ticks: int, arrival: float, content: object) -> None:
        if self.last_ticks is not None and ticks - self.last_ticks != raw - self._last_raw \
                and ticks > self.last_ticks:
            self.wraps += 1  # only accepted samples move the unwrapping
        self.last_ticks = ticks
        self._last_raw = raw
        self.last_arrival = arrival
        self._remember(ticks, content)

    def _learn_pace(self, ticks: int, arrival: float) -> None:
        mark = self._pace_mark
        if mark is None:
            self._pace_mark = (ticks, arrival)
            return
        local = arrival - mark[1]
        if local >= _PACE_WINDOW_S:
            pace = (ticks - mark[0]) * self.tick_s / local
            self.pace += _PACE_GAIN * (max(pace, 1.0) - self.pace)
            self._pace_mark = (ticks, arrival)

    def _learn_period(self, step: int) -> None:
        self.period_ticks = step if self.period_ticks is None else \
            self.period_ticks + _PERIOD_GAIN * (step - self.period_ticks)

    def _nominal_dt(self) -> float | None:
        return None if self.period_ticks is None else self.period_ticks * self.tick_s

    def reset(self) -> None:
        """Forget the timeline (the next stamp is ``first``)."""
        self.last_ticks = None
        self._pace_mark = None
        self._cand = []
        self._recent.clear()
        self._recent_content.clear()

    def classify(self, raw: int, arrival: float, content: object = None,
                 payload: Any = None) -> Verdict:
        """The verdict on a new raw stamp that arrived at local time ``arrival`` [s].

        ``content`` (e.g. the sensor values) tells a repeated packet (same stamp, same
        content: duplicate) from a clock stepped back. ``payload`` is handed back in
        :class:`Accepted` when (and if) the sample is used.
        """
        if self.last_ticks is None:
            self._commit(raw, raw, arrival, content)
            return Verdict(FIRST, [Accepted(raw, None, payload)])
        elapsed = arrival - self.last_arrival
        ticks = self._follow(self._last_raw, self.last_ticks, raw, elapsed)
        step = ticks - self.last_ticks
        if 0 < step <= self.jump_ticks:
            self._learn_period(step)
            self._learn_pace(ticks, arrival)
            self._cand = []  # the current timeline is alive: no new one is adopted
            self._commit(raw, ticks, arrival, content)
            return Verdict(OK, [Accepted(ticks, step * self.tick_s, payload)])
        if step > 0 and not self._cand and self._agrees(step, elapsed):
            # (Only after silence: a stream that went off-timeline meanwhile needs the
            # full evidence, whatever the local clock says.)
            self._cand = []
            self._commit(raw, ticks, arrival, content)
            return Verdict(GAP, [Accepted(ticks, self._nominal_dt(), payload)],
                           gap_s=elapsed)
        if ticks in self._recent_content and self._recent_content[ticks] == content:
            return Verdict(DUPLICATE)
        verdict = REORDERED if -self.reorder_ticks <= step < 0 else \
            JUMP if step > 0 else BACKWARDS
        return self._candidate(raw, arrival, content, payload, verdict)

    # --- a possible new timeline --------------------------------------------------------
    def _candidate(self, raw: int, arrival: float, content: object, payload: Any,
                   verdict: str) -> Verdict:
        cand = self._cand
        if cand:
            last = cand[-1]
            ticks = self._follow(last.raw, last.ticks, raw, arrival - last.arrival)
            step = ticks - last.ticks
            if step == 0:
                return Verdict(DUPLICATE)
            if not 0 < step <= self.jump_ticks:
                cand.clear()  # not a stream: start over from this stamp
                ticks = raw
        else:
            ticks = raw
        if len(cand) >= self.max_candidates:
            del cand[0]
            self.candidates_dropped += 1
        cand.append(_Candidate(raw, ticks, arrival, verdict, content, payload))
        if not self._convincing():
            return Verdict(verdict)
        return self._adopt(content)

    def _convincing(self) -> bool:
        cand = self._cand
        first, last = cand[0], cand[-1]
        span = last.ticks - first.ticks
        needed = self.resync_ticks
        reboot = self._looks_like_reboot(first)
        if reboot and self._boot_corroborated(first):
            needed = min(needed, REBOOT_CORROBORATED_S / self.tick_s)
        if span < needed or span <= 0:
            return False
        local = last.arrival - first.arrival
        return span * self.tick_s <= CANDIDATE_PACE * max(self.pace, 1.0) * local

    def _looks_like_reboot(self, first: _Candidate) -> bool:
        return first.ticks * self.tick_s < REBOOT_UPTIME_S and self.last_ticks is not None \
            and first.ticks < self.last_ticks - self.reorder_ticks

    def _boot_corroborated(self, first: _Candidate) -> bool:
        if self.boot_hint is None:
            return False
        board_s, at = self.boot_hint
        expected = board_s + (first.arrival - at)
        return abs(first.ticks * self.tick_s - expected) <= BOOT_HINT_TOLERANCE_S

    def _adopt(self, content: object) -> Verdict:
        cand, self._cand = self._cand, []
        first = cand[0]
        kind = REBOOT if self._looks_like_reboot(first) else RESYNC
        gap = first.arrival - self.last_arrival
        accepted = [Accepted(first.ticks, self._nominal_dt(), first.payload)]
        for prev, c in pairwise(cand):
            accepted.append(Accepted(c.ticks, (c.ticks - prev.ticks) * self.tick_s,
                                     c.payload))
        # The last candidate is the sample being classified now; the others were
        # counted as dropped when they arrived.
        reclassified = [c.verdict for c in cand[:-1]]
        self._recent.clear()
        self._recent_content.clear()
        for c in cand[:-1]:
            self._remember(c.ticks, c.content)
        last = cand[-1]
        self.last_ticks = None
        self._pace_mark = None
        self._commit(last.raw, last.ticks, last.arrival, content)
        if kind == REBOOT:
            self.period_ticks = None
        return Verdict(kind, accepted, reclassified, gap_s=gap)


class ArrivalClock:
    """Board time for a message that carries none (ArduPilot's SIMSTATE) or a zero one
    (PX4 SIH's HIL_STATE_QUATERNION), from when it arrived.

    The board time of the newest IMU sample read before it, plus the wall time since
    that sample was read: a message sent along the same link, in sequence with the IMU
    stream, is placed where the stream says it was sent, as the replay places it (the
    board time of the IMU message before it). Nothing here assumes the board clock runs
    at the wall clock's rate: a simulator behind its real-time schedule (PX4 SIH on a
    loaded machine ran at 0.988× here) would otherwise place every truth sample tens of
    milliseconds late, several degrees in a fast turn. A backlog read at once is placed
    by its order too, not by when the bridge got round to reading it.

    The wall time added is at most the IMU stream's last step: a message is never placed
    past where the next IMU sample is due. A simulator starved of CPU can stop between
    two sends while its board clock stands still; placed by the wall clock, the truth
    sent after the stop would lie that far ahead of the IMU sample it followed, be
    compared with the wrong attitude, and make the live session scores take every truth
    sample before that time as counted already (``bridge.estimate.session``)."""

    def __init__(self) -> None:
        self._board: float | None = None  # newest IMU sample's board time [s]
        self._arrival = 0.0  # when it was read
        self._step = math.inf  # board time between the last two IMU samples [s]

    def observe(self, board_t: float, arrival: float) -> None:
        """An IMU sample; an older one (a second stream's) does not move the clock back."""
        if self._board is None or board_t >= self._board:
            if self._board is not None and board_t > self._board:
                self._step = board_t - self._board
            self._board, self._arrival = board_t, arrival

    def reset(self) -> None:
        """A new timeline (a reboot, a gap): forget the last sample."""
        self._board = None
        self._step = math.inf

    def board_time(self, arrival: float) -> float | None:
        """Board time of a message read at ``arrival`` (None before any sample)."""
        if self._board is None:
            return None
        return self._board + min(max(arrival - self._arrival, 0.0), self._step)
