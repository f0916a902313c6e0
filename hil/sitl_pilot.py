"""Flying a real SITL autopilot from a ground-station link (:class:`hil.sitl.Link`): the
steps PX4 and ArduPilot Copter need (their README in ``../shared/autopilots`` lists them),
for tests and for ``benchmarks/record_sitl_flights.py``.

* PX4 SIH: NAV_TAKEOFF, arm, offboard velocity set-points, NAV_LAND (it disarms itself).
* ArduPilot Copter, with GPS (GUIDED): mode, arm, NAV_TAKEOFF, velocity set-points, LAND.
  Its EKF takes about 40 s after a fresh start to use the GPS (its gyro bias must settle).
"""

from __future__ import annotations

import time

from .sitl import Leg, Link, fly_legs, mav

NAN = float("nan")
ON_GROUND = 1  # MAV_LANDED_STATE_ON_GROUND
PX4_OFFBOARD = 6  # PX4 custom main mode
AP_GUIDED, AP_LAND = 4, 9  # ArduCopter custom modes


class FlightError(RuntimeError):
    """The autopilot did not do what a flight step asked."""


def log(msg: str) -> None:
    print(msg, flush=True)


def require(ok: bool, what: str) -> None:
    if not ok:
        raise FlightError(what)


# --------------------------------------------------------------------------- common steps
def set_rates(link: Link, rates: dict[str, float]) -> None:
    for name, hz in rates.items():
        if name == "HEARTBEAT":
            continue
        result = link.set_rate(getattr(mav, f"MAVLINK_MSG_ID_{name}"), hz)
        if result != 0:
            log(f"  note: SET_MESSAGE_INTERVAL {name} {hz:g} Hz -> result {result}")


def wait_landed_and_disarmed(link: Link, timeout: float = 60.0) -> None:
    require(link.wait_for(lambda: link.landed == ON_GROUND, timeout), "never landed")
    t_landed = time.time()
    require(link.wait_for(lambda: link.armed is False, 20.0), "did not disarm after landing")
    log(f"  landed; disarmed {time.time() - t_landed:.1f} s later")


def ground_z(link: Link) -> float:
    """LOCAL_POSITION_NED's z where the vehicle stands (it is relative to the EKF's
    origin, which a barometer's drift puts off the ground by up to a metre)."""
    require(link.wait_for(lambda: link.pos is not None, 5.0), "no LOCAL_POSITION_NED")
    return link.pos[2]


def wait_climb(link: Link, alt: float, z0: float, timeout: float = 30.0) -> None:
    """Until the vehicle is ``alt`` (90 % of it) above ``z0``, where it stood."""
    require(link.wait_for(lambda: link.pos[2] < z0 - 0.9 * alt, timeout),
            f"did not climb to {alt} m (z {link.pos[2]:.2f} m, {z0:.2f} m on the ground)")


def arm(link: Link, timeout: float = 60.0) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if link.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1, retries=2) == 0:
            require(link.wait_for(lambda: link.armed, 5.0), "arm accepted but not armed")
            return
        time.sleep(1.0)
    raise FlightError("arming refused: " + "; ".join(t for _, t in link.statustext[-3:]))


# --------------------------------------------------------------------------- PX4
def px4_ready(link: Link, timeout: float = 60.0, settle_s: float = 5.0) -> None:
    require(link.wait_for(lambda: link.fix >= 3 and link.lat != 0, timeout), "no GPS position")
    time.sleep(settle_s)


def px4_takeoff(link: Link, alt: float) -> None:
    z0 = ground_z(link)
    require(link.command(mav.MAV_CMD_NAV_TAKEOFF, NAN, 0, 0, NAN, NAN, NAN, NAN) == 0,
            "NAV_TAKEOFF refused")
    arm(link)
    wait_climb(link, alt, z0)
    time.sleep(1.5)


def px4_offboard(link: Link, legs: list[Leg], alt: float) -> None:
    fly_legs(link, [Leg(1.0)], -alt)  # set-points must stream before the switch
    require(link.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                         PX4_OFFBOARD) == 0, "offboard refused")
    fly_legs(link, legs, -alt)


def px4_land(link: Link) -> None:
    require(link.command(mav.MAV_CMD_NAV_LAND, NAN, 0, 0, NAN, NAN, NAN, NAN) == 0,
            "NAV_LAND refused")
    wait_landed_and_disarmed(link)


# --------------------------------------------------------------------------- ArduPilot
def ap_mode(link: Link, mode: int) -> None:
    require(link.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                         mode) == 0, f"mode {mode} refused")


def ap_ready(link: Link, timeout: float = 120.0, settle_s: float = 3.0) -> None:
    # LOCAL_POSITION_NED only flows once the EKF has its GPS origin and position.
    require(link.wait_for(lambda: link.fix >= 3 and link.pos is not None, timeout),
            "no GPS fix / EKF position")
    require(link.wait_for(lambda: any("using GPS" in t for _, t in link.statustext), 30.0),
            "EKF not using GPS")
    time.sleep(settle_s)


def ap_takeoff(link: Link, alt: float) -> None:
    z0 = ground_z(link)
    ap_mode(link, AP_GUIDED)
    for _ in range(5):
        arm(link)
        if link.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt) == 0:
            break
        time.sleep(1.0)
    else:
        raise FlightError("takeoff refused")
    wait_climb(link, alt, z0)
    time.sleep(1.5)


def ap_guided(link: Link, legs: list[Leg], alt: float) -> None:
    fly_legs(link, legs, -alt)


def ap_land(link: Link) -> None:
    ap_mode(link, AP_LAND)
    wait_landed_and_disarmed(link)
