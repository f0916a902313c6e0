"""Is the vehicle flying? The one policy the bridge and the replay both follow.

A multirotor's accelerometer sees thrust and rotor drag only while it flies; on the
bench, carried by hand, on the ground before take-off or after a touchdown it sees
gravity. A model that assumes flight (``eskf``'s rotor drag) must therefore follow
what the vehicle is *doing*, not what it *is*. The vehicle tells us, in this order:

1. HEARTBEAT ``base_mode`` without MAV_MODE_FLAG_SAFETY_ARMED: a disarmed vehicle is
   never in the air (its motors are off);
2. EXTENDED_SYS_STATE ``landed_state``: TAKEOFF, IN_AIR and LANDING are airborne,
   ON_GROUND is not (PX4 and ArduPilot send it when asked; PX4's ULog has the land
   detector's ``landed`` / ``maybe_landed`` / ``ground_contact`` instead);
3. nothing (a bare IMU, an old log, an armed vehicle without a land detector): the
   estimator decides from the data itself (``eskf``'s thrust-vs-gravity detector).

The armed flag is believed only from a sender that is known to report it: a PX4 or
ArduPilot autopilot, or one that has sent EXTENDED_SYS_STATE or has been seen armed.
A bare board sends HEARTBEATs that are never armed although it may be flown.

Hysteresis: a new landed_state is taken when two reports in a row agree, so one odd
message never switches the model. A source that keeps changing its mind (``FLAP_LIMIT``
changes within ``FLAP_WINDOW_S``) is not believed: the state falls back to "unknown"
(the data decides), the fallback is counted and logged, and the source is trusted again
after a quiet ``FLAP_WINDOW_S``. The thresholds are hand-set (a real touch-and-go changes
the landed state about four times in 10 s, so twice as many is a broken source).
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

# MAVLink constants (common.xml), spelled out so this module needs no pymavlink.
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_PX4 = 3, 12
LANDED_UNDEFINED, LANDED_ON_GROUND, LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING = range(5)
AIRBORNE_LANDED_STATES = frozenset({LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING})
LANDED_NAMES = {LANDED_UNDEFINED: "undefined", LANDED_ON_GROUND: "on ground",
                LANDED_IN_AIR: "in air", LANDED_TAKEOFF: "taking off", LANDED_LANDING: "landing"}
#: Autopilots whose HEARTBEAT armed flag means "motors may spin" from the first message.
ARMING_AUTOPILOTS = frozenset({MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_PX4})

CONFIRM_REPORTS = 2  # agreeing landed_state reports in a row before a switch
FLAP_WINDOW_S = 10.0
FLAP_LIMIT = 8  # changes of the reported state within FLAP_WINDOW_S: source not believed

SOURCE_LANDED = "landed state"
SOURCE_ARMED = "armed flag"
SOURCE_DATA = "data"
SOURCE_FLAPPING = "data (landed state unreliable)"


def state_name(airborne: bool | None) -> str:
    return {True: "airborne", False: "on ground", None: "unknown"}[airborne]


@dataclass(frozen=True)
class Switch:
    """One change of the believed flight state."""

    t: float
    airborne: bool | None
    source: str


@dataclass
class FlightStateTracker:
    """The believed flight state of one vehicle from its own HEARTBEAT and
    EXTENDED_SYS_STATE messages (``t`` is any monotonic clock in seconds).

    ``airborne`` is True / False, or None when the data must decide; ``source`` names
    what decided. ``switches`` lists every change (bounded), ``flap_fallbacks`` counts
    the times the landed state was dropped for changing too often.
    """

    label: str = "vehicle"
    armed: bool | None = None
    landed_state: int | None = None
    airborne: bool | None = None
    source: str = SOURCE_DATA
    flap_fallbacks: int = 0
    reports: int = 0
    switches: deque[Switch] = field(default_factory=lambda: deque(maxlen=256))
    _arming_known: bool = False
    _candidate: int | None = None
    _candidate_count: int = 0
    _last_report: int | None = None
    _changes: deque[float] = field(default_factory=deque)
    _flapping: bool = False

    def on_heartbeat(self, t: float, base_mode: int, autopilot: int) -> None:
        armed = bool(int(base_mode) & MAV_MODE_FLAG_SAFETY_ARMED)
        if autopilot in ARMING_AUTOPILOTS or armed:
            self._arming_known = True
        self.armed = armed if self._arming_known else None
        self._update(t)

    def on_extended_sys_state(self, t: float, landed_state: int, confirmed: bool = False
                              ) -> None:
        """A landed_state report; ``confirmed``: the sender already debounced it (a land
        detector's published verdict), so one report is enough."""
        self._arming_known = True
        self.reports += 1
        landed_state = int(landed_state)
        self._note_change(t, landed_state)
        if landed_state == self._candidate:
            self._candidate_count += 1
        else:
            self._candidate, self._candidate_count = landed_state, 1
        if (confirmed or self._candidate_count >= CONFIRM_REPORTS
                or self.landed_state is None):
            # the first report is taken at once: there is no earlier belief to protect
            self.landed_state = landed_state
        self._update(t)

    def on_land_detector(self, t: float, landed: bool) -> None:
        """A land detector's verdict (PX4 ULog ``vehicle_land_detected``): landed or not.
        PX4 publishes it when it changes, after its own hysteresis."""
        self.on_extended_sys_state(t, LANDED_ON_GROUND if landed else LANDED_IN_AIR,
                                   confirmed=True)

    def on_armed(self, t: float, armed: bool) -> None:
        """An arming state from a source that always reports it (PX4 ULog
        ``vehicle_status.arming_state``)."""
        self._arming_known = True
        self.armed = bool(armed)
        self._update(t)

    def _note_change(self, t: float, report: int) -> None:
        if self._last_report is not None and report != self._last_report:
            self._changes.append(t)
        self._last_report = report
        while self._changes and self._changes[0] < t - FLAP_WINDOW_S:
            self._changes.popleft()
        if not self._flapping and len(self._changes) >= FLAP_LIMIT:
            self._flapping = True
            self.flap_fallbacks += 1
            log.warning("%s: landed state changed %d times in %.0f s; not believed, the "
                        "estimator decides from the data until it settles",
                        self.label, len(self._changes), FLAP_WINDOW_S)
        elif self._flapping and not self._changes:
            self._flapping = False
            log.warning("%s: landed state steady again; believed", self.label)

    def _update(self, t: float) -> None:
        airborne, source = self.decide()
        if airborne != self.airborne or source != self.source:
            changed = airborne != self.airborne
            self.airborne, self.source = airborne, source
            if changed:
                self.switches.append(Switch(t, airborne, source))
                log.info("%s: %s (%s)", self.label, state_name(airborne), source)

    def decide(self) -> tuple[bool | None, str]:
        if self.armed is False:
            return False, SOURCE_ARMED
        if self._flapping:
            return None, SOURCE_FLAPPING
        if self.landed_state in AIRBORNE_LANDED_STATES:
            return True, SOURCE_LANDED
        if self.landed_state == LANDED_ON_GROUND:
            return False, SOURCE_LANDED
        return None, SOURCE_DATA

    def status(self) -> dict[str, object]:
        """What the status report, the table and MQTT show."""
        return {"state": state_name(self.airborne), "source": self.source,
                "armed": self.armed,
                "landed_state": None if self.landed_state is None
                else LANDED_NAMES.get(self.landed_state, str(self.landed_state)),
                "reports": self.reports, "switches": len(self.switches),
                "flap_fallbacks": self.flap_fallbacks}
