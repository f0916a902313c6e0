"""What kind of vehicle a MAVLink HEARTBEAT (or a PX4 ``MAV_TYPE`` parameter) names.

The estimators need one fact about the vehicle: whether it is a multirotor, whose
accelerometer measures thrust along body z plus rotor drag — the model ``eskf`` uses to
see its tilt without aiding. Bridge and replay both ask here.
"""

from __future__ import annotations

#: MAV_TYPE values of vehicles lifted by rotors whose thrust is along body z: quad-, hexa-,
#: octo-, tri-, dodeca-, decarotors, the generic multirotor, coaxial and single-rotor
#: helicopters. VTOL types are left out: in forward flight their wing carries them.
MULTIROTOR_TYPES = frozenset({2, 3, 4, 13, 14, 15, 29, 35, 43})

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
