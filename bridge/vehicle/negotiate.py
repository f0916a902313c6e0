"""Which IMU stream to ask a vehicle for, at what rate, and whether it delivered.

Autopilots differ in what they stream and what they refuse, and a request sent into
the void looks exactly like one that worked until the samples fail to come. So the
bridge negotiates, per vehicle, from what its HEARTBEAT says it is:

* PX4: HIGHRES_IMU (SI floats, microsecond stamps), else SCALED_IMU. PX4 has no RAW_IMU
  stream: asked for one it answers MAV_RESULT_FAILED; unasked, it streams HIGHRES_IMU
  at 50 Hz on an onboard link.
* ArduPilot: RAW_IMU (mG, mrad/s, mGauss: board profile ``ardupilot``), else
  SCALED_IMU, SCALED_IMU2.
* anything else (the seeds' STM32 board, other firmware): RAW_IMU (board profile
  ``gy86``), else SCALED_IMU, HIGHRES_IMU.

``--imu-message NAME`` forces one message (``A,B``: this order of candidates). Each
candidate is asked for with MAV_CMD_SET_MESSAGE_INTERVAL at ``--imu-rate``, one command
at a time (a COMMAND_ACK does not say which message it answers): ACCEPTED settles it,
a refusal (FAILED, DENIED, UNSUPPORTED) is logged at WARNING and the next candidate is
asked, no answer after ``MAX_TRIES`` tries ``ACK_TIMEOUT_S`` apart is logged and the
bridge uses whatever the vehicle streams. ArduPilot's DENIED means something else: the
interval is shorter than its main loop allows (1.25 loop periods; it keeps intervals in
whole milliseconds), so the same message is asked again at the next whole-millisecond
interval, down to ``MIN_IMU_RATE_HZ``, before another message is tried.

The achieved rate is the mean rate on the stream's own time stamps (so a fast-forwarded
replay measures the same as a live link) over the last ``_RATE_STEPS`` steps; the
spread of the steps is reported beside it as jitter. ArduPilot sends its 333 Hz RAW_IMU
in uneven 2.5 ms / 5 ms steps: the median step would say 400 or 200 Hz. A rate below
``RATE_SHORTFALL`` of the request is logged at WARNING once it has held for
``RATE_JUDGED_AFTER_S`` of samples.

For PX4 and ArduPilot the velocity streams for aiding (:mod:`bridge.vehicle.aiding`) are asked
for too, after the IMU: LOCAL_POSITION_NED at 50 Hz and GPS_RAW_INT at 10 Hz; their
refusal is only noted (other sources may still come). Every vehicle is then asked for
EXTENDED_SYS_STATE at ``FLIGHT_STATE_HZ``: its landed state decides when the flight-only
models run (:mod:`imu.flight_state`); refused or unanswered, the estimator decides from
the data, which is noted in the log. Last, PX4 and ArduPilot are asked for the
references of the live comparison (``REFERENCE_STREAMS``): their own attitude
(ATTITUDE_QUATERNION) and, in a simulator, its true attitude (PX4 SIH:
HIL_STATE_QUATERNION, ArduPilot SITL: SIMSTATE). A real vehicle has no simulator: the
refusal (or silence) only means there is no truth to compare with.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..wire.mav import mavlink
from .ingest import IMU_MESSAGE_NAMES

log = logging.getLogger(__name__)

PX4, ARDUPILOT = mavlink.MAV_AUTOPILOT_PX4, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
IMU_CANDIDATES = {
    PX4: ("HIGHRES_IMU", "SCALED_IMU"),
    ARDUPILOT: ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2"),
}
OTHER_CANDIDATES = ("RAW_IMU", "SCALED_IMU", "HIGHRES_IMU")
#: Velocity streams asked from autopilots that have them, with the rate asked [Hz].
AIDING_STREAMS = (("LOCAL_POSITION_NED", 50.0), ("GPS_RAW_INT", 10.0))
#: The landed state (EXTENDED_SYS_STATE) is asked at this rate [Hz]: two agreeing reports
#: switch the flight state, so a switch follows the vehicle within 0.4 s.
FLIGHT_STATE_HZ = 5.0
FLIGHT_STATE_STREAM = "EXTENDED_SYS_STATE"
#: The live comparison's references asked from autopilots that have them: the autopilot's
#: own attitude at REFERENCE_HZ, and the simulator's true attitude in SITL at the IMU's
#: rate (every estimate gets its own truth; a real vehicle sends none whatever is asked).
REFERENCE_HZ = 50.0
REFERENCE_STREAMS = {
    PX4: ("ATTITUDE_QUATERNION", "HIL_STATE_QUATERNION"),
    ARDUPILOT: ("ATTITUDE_QUATERNION", "SIMSTATE"),
}
TRUTH_STREAMS = frozenset(("HIL_STATE_QUATERNION", "SIMSTATE"))
#: PX4's raw magnetometer (SCALED_IMU: without PX4's bias estimate, which HIGHRES_IMU's
#: has taken out; imu.px4_mag), asked beside HIGHRES_IMU at this rate [Hz]: SIH's
#: simulated magnetometer reads at 50 Hz.
RAW_MAG_STREAM, RAW_MAG_HZ = "SCALED_IMU", 50.0
#: Autopilots whose DENIED answer to SET_MESSAGE_INTERVAL means "interval too short".
DENIED_MEANS_TOO_FAST = frozenset((ARDUPILOT,))
#: Lowest rate an IMU stream is asked at when stepping down after DENIED [Hz].
MIN_IMU_RATE_HZ = 50.0
#: RAW_IMU units by autopilot (the board profile when ``--board`` is not given).
RAW_IMU_BOARD = {ARDUPILOT: "ardupilot"}
DEFAULT_BOARD = "gy86"

ACK_TIMEOUT_S = 1.0
MAX_TRIES = 3
#: Achieved below this fraction of the requested rate: logged as a shortfall.
RATE_SHORTFALL = 0.9
#: Share of the primary stream's recent messages refused here above which a slow rate
#: is put down to those refusals rather than to the sender (see StreamNegotiation).
REFUSED_SHARE = 0.05
RATE_JUDGED_AFTER_S = 1.0  # board time of samples before the rate is judged
_RATE_STEPS = 64  # mean rate and jitter over this many recent time steps

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
RETRY_LATER = frozenset((mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
                         mavlink.MAV_RESULT_IN_PROGRESS))
# States of the IMU negotiation.
WAITING, ASKING, SETTLED, REFUSED, NO_ANSWER = (
    "waiting", "asking", "accepted", "refused", "no_answer")


def _consequence(name: str) -> str:
    if name == FLIGHT_STATE_STREAM:
        return ": no landed state, eskf decides from the data when the vehicle flies"
    if name in TRUTH_STREAMS:
        return ": no simulator truth (a real vehicle), compared with its own attitude only"
    if name == RAW_MAG_STREAM:
        return ": HIGHRES_IMU's magnetometer (PX4's bias estimate taken out) is used"
    if name == "ATTITUDE_QUATERNION":
        return ": compared with its ATTITUDE if it sends one"
    return ""


def next_slower_rate(rate_hz: float) -> float:
    """The rate of the next whole-millisecond interval longer than ``rate_hz``'s."""
    return 1000.0 / (math.floor(1000.0 / rate_hz + 1e-9) + 1)


def _rate_hint(autopilot: int | None) -> str:
    """What a user can do about a slow IMU stream."""
    where = {PX4: " (PX4: IMU_INTEG_RATE)", ARDUPILOT: " (ArduPilot: SCHED_LOOP_RATE)"}
    return ("; an autopilot sends at most its own sample rate: ask for what it has with "
            f"--imu-rate, or raise its rate{where.get(autopilot, '')}")


def result_name(result: int) -> str:
    entry = mavlink.enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else f"MAV_RESULT {result}"


def board_for(autopilot: int | None) -> str:
    """What the integers of this autopilot's RAW_IMU mean (imu.boards profile name)."""
    return RAW_IMU_BOARD.get(autopilot, DEFAULT_BOARD)


def parse_forced(text: str | None) -> tuple[str, ...] | None:
    """``--imu-message``: None (negotiate), one name or a comma-separated order.

    An error names the unknown name(s) as typed, not the whole list: in
    ``RAW_IMU,FOO`` only FOO is wrong, and the user must see which.
    """
    if text is None:
        return None
    typed = [n.strip() for n in text.split(",") if n.strip()]
    valid = (f"valid: {sorted(IMU_MESSAGE_NAMES)} "
             f"(one, or several separated by commas in the order to try)")
    if not typed:
        raise ValueError(f"--imu-message {text!r} names no IMU message; {valid}")
    unknown = [n for n in typed if n.upper() not in IMU_MESSAGE_NAMES]
    if unknown:
        raise ValueError(f"unknown IMU message(s) {', '.join(map(repr, unknown))} in "
                         f"--imu-message {text!r}; {valid}")
    return tuple(n.upper() for n in typed)


@dataclass
class Request:
    """One SET_MESSAGE_INTERVAL waiting for its COMMAND_ACK."""

    name: str
    rate_hz: float
    imu: bool
    tries: int = 0
    sent_at: float = -math.inf

    @property
    def msg_id(self) -> int:
        return getattr(mavlink, f"MAVLINK_MSG_ID_{self.name}")

    @property
    def interval_us(self) -> float:
        return 1e6 / self.rate_hz


@dataclass
class StreamNegotiation:
    """The stream requests of one vehicle (see module docstring)."""

    sysid: int
    rate_hz: float
    forced: tuple[str, ...] | None = None
    aiding: bool = True
    autopilot: int | None = None
    candidates: tuple[str, ...] = ()
    index: int = 0  # current IMU candidate
    state: str = WAITING
    queue: deque = field(default_factory=deque)  # Requests not sent yet
    outstanding: Request | None = None
    refusals: list[str] = field(default_factory=list)
    aiding_results: dict[str, str] = field(default_factory=dict)
    flight_state_result: str | None = None  # the EXTENDED_SYS_STATE request's answer
    reference_results: dict[str, str] = field(default_factory=dict)
    raw_mag_result: str | None = None  # the raw magnetometer request's answer (PX4)
    imu_rate_hz: float | None = None  # rate the current IMU candidate is asked at
    commands_sent: int = 0
    acks: int = 0
    _steps: deque = field(default_factory=lambda: deque(maxlen=_RATE_STEPS))
    _last_t: float | None = None
    _judge_from: float | None = None  # board time from which the rate is judged
    _short: bool = False  # a shortfall has been logged (and not recovered)
    _msg_observed: int | None = None
    #: of the primary stream's recent messages, accepted (True) or refused here (False)
    _fates: deque = field(default_factory=lambda: deque(maxlen=_RATE_STEPS))
    _dropped_seen: int = 0  # the primary source's drop count when last told

    # --- plan -----------------------------------------------------------------------
    def start(self, autopilot: int) -> None:
        """The vehicle's autopilot is known: plan and queue the requests."""
        self.autopilot = autopilot
        self.candidates = self.forced or IMU_CANDIDATES.get(autopilot, OTHER_CANDIDATES)
        self.index = 0
        self.refusals.clear()
        self.queue.clear()
        self.outstanding = None
        self.state = ASKING
        self.imu_rate_hz = self.rate_hz
        self.queue.append(Request(self.candidates[0], self.rate_hz, imu=True))

    @property
    def message(self) -> str | None:
        """The IMU message asked for / settled on (None before the heartbeat)."""
        return self.candidates[self.index] if self.candidates else None

    @property
    def preferred_id(self) -> int:
        """Message id a primary IMU stream should be of (-1: any)."""
        if self.state in (ASKING, SETTLED) and self.message is not None:
            return IMU_MESSAGE_NAMES[self.message]
        return -1

    def repeat_imu(self) -> None:
        """Ask again for the settled (or current) IMU stream: it stopped coming."""
        if self.message is None or self.state == REFUSED:
            return
        if self.outstanding is None or not self.outstanding.imu:
            self.queue.appendleft(Request(self.message, self.asked_hz, imu=True))

    # --- the command exchange --------------------------------------------------------
    def next_send(self, now: float) -> Request | None:
        """The request to send now (new, or a retry), or None."""
        req = self.outstanding
        if req is not None:
            if now - req.sent_at < ACK_TIMEOUT_S:
                return None
            if req.tries >= MAX_TRIES:
                self._no_answer(req)
                req = None
        if req is None:
            if not self.queue:
                return None
            req = self.outstanding = self.queue.popleft()
        req.tries += 1
        req.sent_at = now
        self.commands_sent += 1
        return req

    def on_ack(self, result: int, now: float) -> None:
        """A COMMAND_ACK for SET_MESSAGE_INTERVAL from the vehicle."""
        req = self.outstanding
        self.acks += 1
        if req is None:
            return  # a late answer to a request already given up on
        if result in RETRY_LATER:
            req.sent_at = now  # keep waiting (IN_PROGRESS) or ask again after the timeout
            return
        self.outstanding = None
        if not req.imu:
            self._other_result(req.name, result_name(result))
            if result != ACCEPTED:
                log.info("vehicle %d: %s at %g Hz refused (%s)%s", self.sysid, req.name,
                         req.rate_hz, result_name(result), _consequence(req.name))
            return
        if result == ACCEPTED:
            if self.state != SETTLED:
                log.info("vehicle %d: %s at %g Hz accepted", self.sysid, req.name, req.rate_hz)
            self._settle(SETTLED)
            return
        self.refusals.append(f"{req.name} at {req.rate_hz:.4g} Hz: {result_name(result)}")
        slower = next_slower_rate(req.rate_hz)
        if result == mavlink.MAV_RESULT_DENIED and self.autopilot in DENIED_MEANS_TOO_FAST \
                and slower >= MIN_IMU_RATE_HZ:
            log.warning("vehicle %d denied %s at %.4g Hz (too fast for its main loop); "
                        "asking for %.4g Hz", self.sysid, req.name, req.rate_hz, slower)
            self.imu_rate_hz = slower
            self.queue.appendleft(Request(req.name, slower, imu=True))
            return
        if self.index + 1 < len(self.candidates):
            self.index += 1
            log.warning("vehicle %d refused %s at %g Hz (%s); asking for %s instead",
                        self.sysid, req.name, req.rate_hz, result_name(result), self.message)
            self.imu_rate_hz = self.rate_hz
            self.queue.appendleft(Request(self.message, self.rate_hz, imu=True))
        else:
            log.warning("vehicle %d refused %s at %g Hz (%s); no other IMU message to ask "
                        "for: using the IMU stream it sends", self.sysid, req.name,
                        req.rate_hz, result_name(result))
            self._settle(REFUSED)

    def _no_answer(self, req: Request) -> None:
        self.outstanding = None
        if req.imu:
            log.warning("vehicle %d does not answer SET_MESSAGE_INTERVAL (%s at %g Hz, %d "
                        "tries): using the IMU stream it sends", self.sysid, req.name,
                        req.rate_hz, req.tries)
            self._settle(NO_ANSWER)
        else:
            self._other_result(req.name, "no answer")
            log.info("vehicle %d: no answer to %s at %g Hz%s", self.sysid, req.name,
                     req.rate_hz, _consequence(req.name))

    def _other_result(self, name: str, result: str) -> None:
        if name == FLIGHT_STATE_STREAM:
            self.flight_state_result = result
        elif name == RAW_MAG_STREAM:
            self.raw_mag_result = result
        elif name in REFERENCE_STREAMS.get(self.autopilot, ()):
            self.reference_results[name] = result
        else:
            self.aiding_results[name] = result

    def _settle(self, state: str) -> None:
        first = self.state == ASKING
        self.state = state
        self._steps.clear()
        self._last_t = None
        self._judge_from = None
        self._short = False
        if first and self.aiding and self.autopilot in IMU_CANDIDATES:
            self.queue.extend(Request(name, rate, imu=False) for name, rate in AIDING_STREAMS)
        if first:
            self.queue.append(Request(FLIGHT_STATE_STREAM, FLIGHT_STATE_HZ, imu=False))
            self.queue.extend(Request(name, self.asked_hz if name in TRUTH_STREAMS
                                      else REFERENCE_HZ, imu=False)
                              for name in REFERENCE_STREAMS.get(self.autopilot, ()))
            if self.wants_raw_mag:
                self.queue.append(Request(RAW_MAG_STREAM, RAW_MAG_HZ, imu=False))

    @property
    def wants_raw_mag(self) -> bool:
        """A PX4 settled on HIGHRES_IMU: its raw magnetometer is worth asking for."""
        return (self.autopilot == PX4 and self.state == SETTLED
                and self.message == "HIGHRES_IMU")

    # --- the achieved rate -----------------------------------------------------------
    def observe(self, msg_id: int, t: float) -> None:
        """An accepted sample of the primary IMU stream at board time ``t``."""
        if msg_id != self._msg_observed:
            self._msg_observed = msg_id
            self._steps.clear()
            self._fates.clear()
            self._last_t = None
            self._judge_from = None
        self._fates.append(True)
        if self._last_t is not None:
            step = t - self._last_t
            if 0.0 < step < 1.0:  # longer: an outage, not a rate
                self._steps.append(step)
            elif step < -1.0:  # a new timeline: measure afresh
                self._steps.clear()
                self._judge_from = None
        self._last_t = t
        if self._judge_from is None:
            self._judge_from = t + RATE_JUDGED_AFTER_S
        elif t >= self._judge_from and self.state not in (WAITING, ASKING):
            self._judge()

    def refused(self, count: int) -> None:
        """``count`` messages of the primary stream were refused here (jumping, backwards
        or duplicated stamps, unusable values): they lower the accepted rate, and a
        warning about it must not send the user to the autopilot's settings."""
        self._fates.extend([False] * min(count, _RATE_STEPS))

    def note_dropped(self, total: int) -> None:
        """The primary source's drop count now (told only when a message gave no
        sample, so the hot path does no counting): the new drops are :meth:`refused`.
        A count lower than the last one is a new source's, counted from zero."""
        new = total - self._dropped_seen if total >= self._dropped_seen else total
        self._dropped_seen = total
        if new > 0:
            self.refused(new)

    @property
    def refused_share(self) -> float:
        """Share of the primary stream's recent messages refused here."""
        return self._fates.count(False) / len(self._fates) if self._fates else 0.0

    @property
    def achieved_hz(self) -> float | None:
        """Mean rate over the recent steps (None until there are a few)."""
        if len(self._steps) < 8:
            return None
        return len(self._steps) / float(sum(self._steps))

    @property
    def jitter_ms(self) -> float | None:
        """Standard deviation of the recent time steps [ms]."""
        if len(self._steps) < 8:
            return None
        return 1e3 * float(np.std(self._steps))

    def _judge(self) -> None:
        achieved = self.achieved_hz
        if achieved is None:
            return
        name = mavlink.mavlink_map[self._msg_observed].msgname
        short = achieved < RATE_SHORTFALL * self.asked_hz
        if short and not self._short:
            share = self.refused_share
            hint = (f"; {share:.0%} of its recent samples were refused here (drops in the "
                    f"status: stamps jumping, going back or repeated, unusable values), "
                    f"not missing from the stream" if share > REFUSED_SHARE
                    else _rate_hint(self.autopilot))
            log.warning("vehicle %d: IMU %s at %.0f Hz, below the %.4g Hz asked%s",
                        self.sysid, name, achieved, self.asked_hz, hint)
        elif self._short and not short:
            log.info("vehicle %d: IMU %s now at %.0f Hz", self.sysid, name, achieved)
        self._short = short

    @property
    def asked_hz(self) -> float:
        """The rate the IMU stream was last asked at (lower than ``--imu-rate`` after
        ArduPilot denied it)."""
        return self.imu_rate_hz or self.rate_hz

    def status(self) -> dict[str, Any]:
        achieved, jitter = self.achieved_hz, self.jitter_ms
        using = (mavlink.mavlink_map[self._msg_observed].msgname
                 if self._msg_observed is not None else None)
        return {"message": using, "asked": self.message, "requested_hz": self.rate_hz,
                "asked_hz": round(self.asked_hz, 2),
                "achieved_hz": round(achieved, 1) if achieved is not None else None,
                "jitter_ms": round(jitter, 3) if jitter is not None else None,
                "state": self.state, "below_request": self._short,
                "forced": self.forced is not None, "refused": list(self.refusals),
                "commands": self.commands_sent, "acks": self.acks,
                "aiding_streams": dict(self.aiding_results),
                "flight_state_stream": self.flight_state_result,
                "reference_streams": dict(self.reference_results),
                "raw_mag_stream": self.raw_mag_result}
