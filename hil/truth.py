"""What every motion profile gives: the truth (attitude, body rates, translation) at any
times, in one container, so sensors and messages never care how a motion was made."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators import quat

from .environment import GRAVITY_NED

# MAV_LANDED_STATE values (EXTENDED_SYS_STATE.landed_state), kept here without pymavlink.
LANDED_UNDEFINED, LANDED_ON_GROUND, LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING = range(5)
LANDED_NAMES = {LANDED_UNDEFINED: "undefined", LANDED_ON_GROUND: "on ground",
                LANDED_IN_AIR: "in air", LANDED_TAKEOFF: "takeoff", LANDED_LANDING: "landing"}


@dataclass(frozen=True)
class Truth:
    """Truth at a set of times: FRD body, NED world."""

    t: np.ndarray  # (N,) seconds since the start of the motion
    q: np.ndarray  # (N, 4) body -> NED
    rates: np.ndarray  # (N, 3) body rates [rad/s] FRD
    accel_ned: np.ndarray  # (N, 3) linear acceleration [m/s^2]
    velocity_ned: np.ndarray  # (N, 3) [m/s]
    position_ned: np.ndarray  # (N, 3) [m] relative to the take-off point

    def rows(self, index: slice) -> Truth:
        """The truth at a part of its times (copies: the callers' arithmetic then runs on
        contiguous arrays, as on a fresh evaluation)."""
        return Truth(**{name: np.ascontiguousarray(getattr(self, name)[index])
                        for name in ("t", "q", "rates", "accel_ned", "velocity_ned",
                                     "position_ned")})

    def specific_force(self) -> np.ndarray:
        """What an ideal accelerometer reads, FRD [m/s^2]: R^T (a - g)."""
        r = quat.to_dcm(self.q)
        return np.einsum("nji,nj->ni", r, self.accel_ned - GRAVITY_NED)

    def to_body(self, v_ned: np.ndarray) -> np.ndarray:
        """A world vector (e.g. the Earth's field) in the body frame at each time."""
        r = quat.to_dcm(self.q)
        return np.einsum("nji,j->ni", r, np.asarray(v_ned, dtype=float))


class Profile:
    """A motion: truth at any times, and the flight state a flight controller would
    report for it.

    The default flight state is that of a body moved by hand (or by anything but its
    own rotors): never armed, always ON_GROUND. Profiles that fly override it.
    """

    name = "profile"

    def truth(self, t: np.ndarray) -> Truth:
        raise NotImplementedError

    def flight_state(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(armed (N,) bool, landed_state (N,) uint8 MAV_LANDED_STATE) at times t."""
        t = np.asarray(t, dtype=float)
        return np.zeros(t.shape, dtype=bool), np.full(t.shape, LANDED_ON_GROUND, dtype=np.uint8)
