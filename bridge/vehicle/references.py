"""The references of one vehicle's live comparison, as they arrive: the simulator's
truth and the vehicle's own attitude (ATTITUDE_QUATERNION, or ATTITUDE when it sends
no quaternion), each on the vehicle's board clock."""

from __future__ import annotations

import numpy as np

from estimators import quat as Q

from .ring import TimeRing

TRUTH, VEHICLE = "truth", "vehicle"


class References:
    """Reference attitudes of one vehicle, as they arrive."""

    def __init__(self, capacity: int = 20000) -> None:
        self.series = {TRUTH: TimeRing(capacity, 4), VEHICLE: TimeRing(capacity, 4)}
        self._vehicle_has_quaternion = False

    def add_truth(self, t: float, q: np.ndarray) -> None:
        self.series[TRUTH].push(t, q)

    def add_vehicle_quaternion(self, t: float, q: np.ndarray) -> None:
        self._vehicle_has_quaternion = True
        self.series[VEHICLE].push(t, q)

    def add_vehicle_euler(self, t: float, roll: float, pitch: float, yaw: float) -> None:
        """ATTITUDE is used only when the vehicle sends no ATTITUDE_QUATERNION."""
        if not self._vehicle_has_quaternion:
            self.series[VEHICLE].push(t, Q.from_euler(roll, pitch, yaw))
