"""Where a vehicle's magnetic declination comes from, without the user typing a number.

The estimators find magnetic north; MAVLink consumers, the truth and a GPS velocity
are in true north. The declination between them is, in order of preference:

1. ``--declination-deg`` when given (it is the user's word, for every vehicle);
2. the vehicle's own parameter, read with PARAM_REQUEST_READ: PX4 ``EKF2_MAG_DECL``
   [deg], ArduPilot ``COMPASS_DEC`` [rad]: what the autopilot's own estimator uses
   (both fill it from their World Magnetic Model tables). A value of exactly 0 is the
   parameters' default before the autopilot has set it, so it is not taken. Both
   autopilots fill it in on the ground without telling anyone (no PARAM_VALUE):
   ArduPilot once its GPS has a position, PX4 from its own tables once it has one, and
   again when it disarms. So it is asked for again every ``REREAD_S`` while it reads 0
   or the vehicle is not armed, and as it arms and disarms: the flight starts with the
   value the autopilot's own estimator uses;
3. the World Magnetic Model (``imu.geomag``, WMM2025, today's date) at the vehicle's
   position (GLOBAL_POSITION_INT, GPS_RAW_INT with a fix, or HIL_STATE_QUATERNION),
   computed again when the vehicle has moved more than ``RECOMPUTE_DEG`` of latitude
   or longitude. A place counts once ``CONFIRM_FIXES`` fixes in a row agree on it: a
   position that flips between two places (a faulty receiver) would otherwise turn the
   heading back and forth with each fix;
4. else 0 (magnetic north reported as true north), shown as ``none``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

from imu import geomag

from ..wire.mav import mavlink
from .param_query import ParamQuery

log = logging.getLogger(__name__)

OPTION, PARAMETER, WMM, NONE = "option", "parameter", "wmm", "none"
#: Declination parameter of each autopilot and its unit.
PARAMETERS = {mavlink.MAV_AUTOPILOT_PX4: ("EKF2_MAG_DECL", "deg"),
              mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: ("COMPASS_DEC", "rad")}
#: The WMM is evaluated again after the vehicle moved this far [deg of lat/lon]
#: (~50 km; the declination changes by well under 0.1° over such a distance at most
#: latitudes).
RECOMPUTE_DEG = 0.5
#: Consecutive fixes within RECOMPUTE_DEG of each other before a place is used.
CONFIRM_FIXES = 5
#: The declination parameter is asked for again this often while it reads 0 (not set
#: yet) or the vehicle is not armed [s].
REREAD_S = 10.0


@dataclass
class Declination:
    """The declination of one vehicle and where it came from."""

    sysid: int
    option_deg: float | None = None
    deg: float = 0.0
    source: str = NONE
    detail: str = ""
    param: tuple[str, str] | None = None  # (name, unit) to ask the autopilot for
    query: ParamQuery = field(default_factory=ParamQuery)
    wmm_at: tuple[float, float] | None = None  # (lat, lon) of the last WMM evaluation
    #: a new place not yet confirmed: (lat, lon) of its first fix, fixes agreeing so far
    candidate: tuple[float, float] | None = None
    candidate_fixes: int = 0
    #: repr of the last parameter value refused (warned about once, not per message)
    refused_value: str | None = None
    params_refused: int = 0
    unset_reported: bool = False  # "is 0 (not set)" logged once until a set value comes

    def __post_init__(self) -> None:
        if self.option_deg is not None:
            self.deg, self.source, self.detail = float(self.option_deg), OPTION, "--declination-deg"

    @property
    def rad(self) -> float:
        return math.radians(self.deg)

    def plan(self, autopilot: int) -> None:
        """The autopilot is known: which parameter to read (none with the option)."""
        self.param = None if self.option_deg is not None else PARAMETERS.get(autopilot)
        self.query.restart(None if self.param is None else self.param[0])

    def param_to_send(self, now: float) -> str | None:
        """The parameter name to ask for now (first try or a retry), else None."""
        return self.query.to_send(now)

    def on_param(self, name: str, value: float, now: float, armed: bool | None) -> bool:
        """A PARAM_VALUE from the autopilot (monotonic ``now``; ``armed``: the vehicle's
        state then, None unknown); True if the declination changed."""
        if self.param is None or not self.query.answer(name):
            return False
        if armed is not True or value == 0.0:  # not set yet, or may still change
            self.query.ask_again(now, REREAD_S)
        deg = value if self.param[1] == "deg" else math.degrees(value)
        if not (math.isfinite(deg) and abs(deg) <= 180.0):
            self.params_refused += 1
            if repr(value) != self.refused_value:
                self.refused_value = repr(value)
                log.warning("vehicle %d: %s = %r is no declination; not used (repeats "
                            "counted in declination.params_refused)", self.sysid, name, value)
            return False
        if deg == 0.0:
            if not self.unset_reported:
                self.unset_reported = True
                log.info("vehicle %d: %s is 0 (not set by the autopilot yet); not used, "
                         "asked again every %g s", self.sysid, name, REREAD_S)
            return False
        self.unset_reported = False  # a 0 after a set value (a reset autopilot) is news
        return self._set(deg, PARAMETER, name)

    def on_position(self, lat_deg: float, lon_deg: float, alt_m: float) -> bool:
        """A position of the vehicle; True if the declination changed (WMM)."""
        if self.source in (OPTION, PARAMETER):
            return False
        if not (math.isfinite(lat_deg) and math.isfinite(lon_deg) and abs(lat_deg) <= 90.0
                and abs(lon_deg) <= 180.0) or (lat_deg == 0.0 and lon_deg == 0.0):
            return False  # (0, 0): the "no position" value
        if self.wmm_at is not None and _near(self.wmm_at, lat_deg, lon_deg):
            self.candidate = None
            return False
        if self.candidate is None or not _near(self.candidate, lat_deg, lon_deg):
            self.candidate, self.candidate_fixes = (lat_deg, lon_deg), 0
        self.candidate_fixes += 1
        if self.candidate_fixes < CONFIRM_FIXES:
            return False
        self.candidate = None
        try:
            deg = geomag.declination_deg(lat_deg, lon_deg, alt_m if math.isfinite(alt_m)
                                         else 0.0)
        except ValueError:
            return False
        self.wmm_at = (lat_deg, lon_deg)
        return self._set(deg, WMM, f"{geomag.MODEL_NAME} at {lat_deg:.4f},{lon_deg:.4f}")

    def _set(self, deg: float, source: str, detail: str) -> bool:
        changed = deg != self.deg or source != self.source
        if changed:
            log.info("vehicle %d: magnetic declination %+.2f° from %s (%s)", self.sysid, deg,
                     source, detail)
        self.deg, self.source, self.detail = deg, source, detail
        return changed

    def status(self) -> dict[str, Any]:
        return {"deg": round(self.deg, 3), "source": self.source, "detail": self.detail,
                "params_refused": self.params_refused}


def _near(place: tuple[float, float], lat_deg: float, lon_deg: float) -> bool:
    return abs(lat_deg - place[0]) < RECOMPUTE_DEG and abs(lon_deg - place[1]) < RECOMPUTE_DEG
