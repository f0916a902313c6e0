"""Which magnetic declination the estimators apply to a replayed log, and why.

Order: the user's ``--declination-deg``; the vehicle's own parameter (PX4
``EKF2_MAG_DECL`` in degrees, ArduPilot ``COMPASS_DEC`` in radians), which is what
the autopilot applied to its attitude, unless it is 0 (the default: not set); else the
World Magnetic Model at the vehicle's position on the log's date (today when the log has
none). A reference that is itself
relative to magnetic north (BROAD's optical reference is aligned to the IMU's magnetic
north) takes none: adding one would create the very error it is meant to remove.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .dataset import Recording

#: Vehicle parameters holding the declination, and their unit's factor to degrees.
PARAMETERS = (("EKF2_MAG_DECL", 1.0), ("COMPASS_DEC", math.degrees(1.0)))


@dataclass(frozen=True)
class Declination:
    """The value applied [deg, east positive] and a short account of where it came from."""

    deg: float
    source: str

    @property
    def rad(self) -> float:
        return math.radians(self.deg)

    def describe(self) -> str:
        return f"{self.deg:+.2f}° ({self.source})"


def check_against_reference(rec: Recording, deg: float, what: str) -> None:
    """ValueError for a declination asked of estimates scored against a reference that
    is relative to magnetic north: it would turn them away from it by just as much, a
    heading error of the user's making that the scores would blame on the filters."""
    if deg != 0.0 and rec.reference is not None and rec.reference.north == "magnetic":
        raise ValueError(f"{what}: the reference ({rec.reference.source}) is relative to "
                         f"magnetic north, so a declination would turn the estimates away "
                         f"from it by as much; leave it out")


def resolve(rec: Recording, given_deg: float | None = None) -> Declination:
    """The declination for ``rec``; ``given_deg`` (the command line) wins."""
    if given_deg is not None:
        if not math.isfinite(given_deg) or abs(given_deg) > 180.0:
            raise ValueError(f"--declination-deg must be within ±180, got {given_deg}")
        check_against_reference(rec, given_deg, f"--declination-deg {given_deg:g}")
        return Declination(float(given_deg), "--declination-deg")
    if rec.reference is not None and rec.reference.north == "magnetic":
        return Declination(0.0, f"none: the reference ({rec.reference.source}) is relative "
                                f"to magnetic north")
    unset = ""
    for name, to_deg in PARAMETERS:
        value = rec.params.get(name)
        if value == 0.0:
            # as the live bridge: 0 is the default, not a value (ArduPilot's
            # COMPASS_AUTODEC sets it only once it has a GPS position)
            unset = f"; {name} is 0 (not set by the autopilot)"
        elif value is not None and math.isfinite(value):
            return Declination(float(value) * to_deg, f"vehicle parameter {name}")
    if rec.position is not None:
        from imu.geomag import MODEL_NAME, declination_deg

        p = rec.position
        when = rec.when.date() if rec.when is not None else None
        try:
            deg = declination_deg(p.lat_deg, p.lon_deg, p.alt_m, when)
        except ValueError as exc:
            return Declination(0.0, f"none: {p.source} position unusable ({exc})")
        date = (f"{when.isoformat()} from {rec.when_source}" if when is not None
                else "today: the log has no date")
        ns, ew = ("S" if p.lat_deg < 0 else "N"), ("W" if p.lon_deg < 0 else "E")
        return Declination(deg, f"{MODEL_NAME} at {abs(p.lat_deg):.4f}°{ns} "
                                f"{abs(p.lon_deg):.4f}°{ew} ({p.source}), {date}{unset}")
    return Declination(0.0, "none: no --declination-deg, parameter or position in the log; "
                            f"headings are magnetic{unset}")
