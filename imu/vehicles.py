"""What kind of vehicle a MAVLink HEARTBEAT (or a PX4 ``MAV_TYPE`` parameter) names.

The estimators need one fact about the vehicle: whether it is a multirotor, whose
accelerometer measures thrust along body z plus rotor drag *while it flies* — the model
``eskf`` uses to see its tilt without aiding (whether it flies is ``imu.flight_state``'s
question). Bridge and replay both ask here (through ``estimators.vehicle_model``).
"""

from __future__ import annotations

#: MAV_TYPE values of vehicles lifted by several rotors whose thrust is along body z and
#: whose horizontal force is rotor drag: quad-, hexa-, octo-, tri-, dodeca-, decarotors
#: and the generic multirotor. Left out: helicopters (a single rotor hovers with a
#: lateral force that balances the tail rotor's, so drag is not the horizontal force)
#: and VTOLs (in forward flight their wing carries them).
MULTIROTOR_TYPES = frozenset({2, 13, 14, 15, 29, 35, 43})

_NAMES = {0: "generic", 1: "fixed wing", 2: "quadrotor", 3: "coaxial helicopter",
          4: "helicopter", 10: "ground rover", 11: "surface boat", 12: "submarine",
          13: "hexarotor", 14: "octorotor", 15: "tricopter", 19: "VTOL duorotor",
          20: "VTOL quadrotor", 21: "VTOL tiltrotor", 22: "VTOL", 29: "dodecarotor",
          35: "decarotor", 43: "multirotor"}


def is_multirotor(mav_type: int | None) -> bool:
    return mav_type is not None and int(mav_type) in MULTIROTOR_TYPES


def type_name(mav_type: int | None) -> str:
    if mav_type is None:
        return "unknown"
    return _NAMES.get(int(mav_type), f"MAV_TYPE {int(mav_type)}")
