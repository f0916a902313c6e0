"""What every motion profile gives: the truth (attitude, body rates, translation) at any
times, in one container, so sensors and messages never care how a motion was made."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators import quat

from .environment import GRAVITY_NED


@dataclass(frozen=True)
class Truth:
    """Truth at a set of times: FRD body, NED world."""

    t: np.ndarray  # (N,) seconds since the start of the motion
    q: np.ndarray  # (N, 4) body -> NED
    rates: np.ndarray  # (N, 3) body rates [rad/s] FRD
    accel_ned: np.ndarray  # (N, 3) linear acceleration [m/s^2]
    velocity_ned: np.ndarray  # (N, 3) [m/s]
    position_ned: np.ndarray  # (N, 3) [m] relative to the take-off point

    def specific_force(self) -> np.ndarray:
        """What an ideal accelerometer reads, FRD [m/s^2]: R^T (a - g)."""
        r = quat.to_dcm(self.q)
        return np.einsum("nji,nj->ni", r, self.accel_ned - GRAVITY_NED)

    def to_body(self, v_ned: np.ndarray) -> np.ndarray:
        """A world vector (e.g. the Earth's field) in the body frame at each time."""
        r = quat.to_dcm(self.q)
        return np.einsum("nji,j->ni", r, np.asarray(v_ned, dtype=float))


class Profile:
    """A motion: truth at any times."""

    name = "profile"

    def truth(self, t: np.ndarray) -> Truth:
        raise NotImplementedError
