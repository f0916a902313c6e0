"""What kind of vehicle the bridge serves, and what that changes in its estimators.

A vehicle's HEARTBEAT says what it is (MAV_TYPE). For a flying multirotor that matters
to the attitude: its horizontal specific force is rotor drag, proportional to its
velocity in the body frame, so ``eskf`` with its drag model (``drag`` = the prior of
the drag coefficient) can tell tilt from acceleration without any aiding. The rule
lives in ``estimators.vehicle_model``; whether the vehicle flies right now (and the
model is used) is ``imu.flight_state``'s.

The user's own setting wins: ``-e eskf:drag=0`` turns the model off on a multirotor.
"""

from __future__ import annotations

from typing import Any

from estimators.registry import estimator_class
from estimators.spec import EstimatorSpec
from estimators.vehicle_model import model_params
from imu.vehicles import MULTIROTOR_TYPES, is_multirotor
from imu.vehicles import type_name as _type_name

MULTIROTOR, OTHER, UNKNOWN = "multirotor", "other", "unknown"


def model_of(mav_type: int | None) -> str:
    """``multirotor`` (imu.vehicles' list: quad-, hexa-, octo-, tri-, dodeca-, decarotor;
    not helicopters or VTOLs), ``other``, or ``unknown`` (no heartbeat heard yet)."""
    if mav_type is None:
        return UNKNOWN
    return MULTIROTOR if is_multirotor(mav_type) else OTHER


def type_name(mav_type: int | None) -> str | None:
    """"quadrotor", "fixed wing", ... (None when no heartbeat was heard)."""
    return None if mav_type is None else _type_name(mav_type)


def model_defaults(spec: EstimatorSpec, model: str) -> dict[str, Any]:
    """Estimator parameters the vehicle model implies (the spec's own settings win:
    :meth:`EstimatorSpec.create` lets them override these)."""
    return model_params(spec.name, min(MULTIROTOR_TYPES) if model == MULTIROTOR else None)


def describe(spec: EstimatorSpec, model: str) -> str:
    """How the model shows in the table and on MQTT for one estimator."""
    if "drag" not in estimator_class(spec.name).param_names():
        return "-"
    drag = spec.params.get("drag", model_defaults(spec, model).get("drag", 0.0))
    return f"drag {float(drag):g}/s" if drag else "no drag model"
