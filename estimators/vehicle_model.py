"""What a vehicle's kind implies for an estimator's parameters: the one rule.

A multirotor (``imu.vehicles.MULTIROTOR_TYPES``) gets ``eskf``'s rotor-drag model
(``drag`` = the prior of the drag coefficient); every other kind, and an unknown one,
runs the estimator's defaults. The model only *may* apply: whether it is used at a given
moment follows the vehicle's flight state (``Estimator.set_flight_state`` /
``run(airborne=...)``, decided by ``imu.flight_state``), so a multirotor on the bench
or on the ground between flights runs without it. Bridge and replay both ask here; a
user's own setting (``-e eskf:drag=0``) overrides what this returns.
"""

from __future__ import annotations

from imu.vehicles import is_multirotor

from .eskf import MULTIROTOR_DRAG_PER_S
from .registry import estimator_class


def model_params(estimator: str, mav_type: int | None) -> dict[str, float]:
    """Parameters the vehicle's kind implies for ``estimator`` (empty when none)."""
    if is_multirotor(mav_type) and "drag" in estimator_class(estimator).param_names():
        return {"drag": MULTIROTOR_DRAG_PER_S}
    return {}
