"""The references of one vehicle's live comparison, as they arrive: the simulator's
truth and the vehicle's own attitude (ATTITUDE_QUATERNION, or ATTITUDE when it sends
no quaternion), each on the vehicle's board clock."""

from __future__ import annotations

import math

import numpy as np

from estimators import quat as Q

from .ring import TimeRing

TRUTH, VEHICLE = "truth", "vehicle"
#: A quaternion whose norm is further than this from 1 is no attitude (a zeroed or
#: corrupted message): refused rather than normalised into an arbitrary rotation.
UNIT_TOLERANCE = 0.05


def attitude(q: np.ndarray) -> np.ndarray | None:
    """``q`` normalised, or None when it is not (nearly) a unit quaternion."""
    q = np.asarray(q, dtype=float)
    if not np.all(np.isfinite(q)):
        return None
    norm = math.sqrt(float(q @ q))
    return q / norm if abs(norm - 1.0) <= UNIT_TOLERANCE else None


class References:
    """Reference attitudes of one vehicle, as they arrive. Each ``add_*`` returns False
    for a value that is no attitude (non-finite, or not a unit quaternion), not kept."""

    def __init__(self, capacity: int = 20000) -> None:
        self.series = {TRUTH: TimeRing(capacity, 4), VEHICLE: TimeRing(capacity, 4)}
        self._vehicle_has_quaternion = False

    def add_truth(self, t: float, q: np.ndarray) -> bool:
        q = attitude(q)
        if q is None:
            return False
        self.series[TRUTH].push(t, q)
        return True

    def add_vehicle_quaternion(self, t: float, q: np.ndarray) -> bool:
        q = attitude(q)
        if q is None:
            return False
        self._vehicle_has_quaternion = True
        self.series[VEHICLE].push(t, q)
        return True

    def add_vehicle_euler(self, t: float, roll: float, pitch: float, yaw: float) -> bool:
        """ATTITUDE is used only when the vehicle sends no ATTITUDE_QUATERNION."""
        if not all(math.isfinite(a) for a in (roll, pitch, yaw)):
            return False
        if not self._vehicle_has_quaternion:
            self.series[VEHICLE].push(t, Q.from_euler(roll, pitch, yaw))
        return True
