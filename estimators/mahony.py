"""Mahony's nonlinear complementary (PI) filter, IMU and MARG (seeds 000/002).

The correction is a rotation rate built from the cross products of each measured unit
vector with its prediction from the current attitude::

    e      = â × v̂(q)  [+ m̂ × ŵ(q)]            (unit vectors: |e| = sin(angle))
    I     += ki · e · dt     (clamped to ±bias_limit per axis: anti-windup)
    ω_corr = ω_gyro + I + kp · e

Gains are in Mahony's units: ``kp`` [rad/s per unit error], ``ki`` [rad/s² per unit
error]. Mahony's reference C code stores ``twoKp = 2·Kp`` and multiplies *half* error
vectors, which is the same thing; the seeds' ``exInt += ex·Ki`` (no ``dt``) is not: its
gain silently scales with the sample rate.

The integral ``I`` is what the filter adds to the gyro, i.e. minus the gyro bias. It is
exposed as ``bias = -I`` (state[4:7]), with the convention ``true rate = gyro - bias``.

Frames: internally NED; the accelerometer's predicted direction is ``Rᵀ·[0, 0, -1]``
(specific force points up), the magnetometer's is ``Rᵀ·b`` with ``b = (b_h, 0, b_v)``
re-derived every step from the measured field rotated into the world frame (Mahony's
reference AHRS), so the filter needs no magnetic dip parameter.

Bad samples: when the accelerometer is unusable the gyro (minus the learned bias) still
integrates and a usable magnetometer only corrects heading (without gravity its field
error would tilt the estimate); nothing is integrated into ``I`` from a missing vector.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from . import _core
from .base import CommonParams, Estimator, param
from .registry import register

MAG_MODES = ("full", "heading")

# Parameter vector indices.
_KP, _KI, _BIAS_LIMIT, _MAG_HEADING, _EXACT = 0, 1, 2, 3, 4


@dataclass(frozen=True)
class MahonyParams(CommonParams):
    BOUNDS: ClassVar[dict[str, tuple[float, float]]] = {
        "kp": (0.0, 100.0), "ki": (0.0, 100.0), "bias_limit": (0.0, 35.0)}

    kp: float = param(0.5, "proportional gain [rad/s per unit cross-product error]; the "
                           "attitude error decays as exp(-kp·t) for small errors")
    ki: float = param(0.005, "integral gain [rad/s² per unit error]: the integral "
                            "ki·∫e·dt is the (negative) gyro bias estimate; 0 disables it")
    bias_limit: float = param(math.radians(20.0), "anti-windup: each axis of the integral "
                                                  "(bias estimate) is clamped to ±this "
                                                  "[rad/s] (MPU6050 zero-rate tolerance)")
    mag_mode: str = param("heading", "'heading': the field error projected on the vertical, "
                                     "corrects yaw only (a disturbed field cannot tilt the "
                                     "estimate); 'full': Mahony's reference AHRS, whole-field "
                                     "error, also pulls on tilt")
    exact: bool = param(False, "False: first-order step q + ½ q ⊗ ω·dt as Mahony's "
                               "reference code; True: exact axis-angle step")


@_core.kernel
def _step(state, params, gx, gy, gz, ax, ay, az, mx, my, mz, acc_ok, mag_ok, dt) -> None:
    kp, ki = params[_KP], params[_KI]
    ex, ey, ez = 0.0, 0.0, 0.0
    # Estimated "up" (specific force at rest) in body axes: Rᵀ · [0, 0, -1].
    ux, uy, uz = _core.world_to_body(state, 0.0, 0.0, -1.0)
    if acc_ok:
        r = 1.0 / math.sqrt(ax * ax + ay * ay + az * az)
        ax, ay, az = ax * r, ay * r, az * r
        ex += ay * uz - az * uy
        ey += az * ux - ax * uz
        ez += ax * uy - ay * ux
    if mag_ok:
        r = 1.0 / math.sqrt(mx * mx + my * my + mz * mz)
        mx, my, mz = mx * r, my * r, mz * r
        hx, hy, hz = _core.body_to_world(state, mx, my, mz)
        wx, wy, wz = _core.world_to_body(state, math.sqrt(hx * hx + hy * hy), 0.0, hz)
        mex = my * wz - mz * wy
        mey = mz * wx - mx * wz
        mez = mx * wy - my * wx
        if params[_MAG_HEADING] > 0.0 or not acc_ok:
            # Keep only the rotation about the vertical: the yaw part of the error.
            along = mex * ux + mey * uy + mez * uz
            mex, mey, mez = along * ux, along * uy, along * uz
        ex += mex
        ey += mey
        ez += mez
    if ki > 0.0:
        lim = params[_BIAS_LIMIT]
        # state holds bias = -integral, so the integral step is subtracted.
        state[_core.B0] = min(max(state[_core.B0] - ki * ex * dt, -lim), lim)
        state[_core.B0 + 1] = min(max(state[_core.B0 + 1] - ki * ey * dt, -lim), lim)
        state[_core.B0 + 2] = min(max(state[_core.B0 + 2] - ki * ez * dt, -lim), lim)
    wx = gx - state[_core.B0] + kp * ex
    wy = gy - state[_core.B0 + 1] + kp * ey
    wz = gz - state[_core.B0 + 2] + kp * ez
    if params[_EXACT] > 0.0:
        _core.integrate_exact(state, wx, wy, wz, dt)
    else:
        _core.integrate_first_order(state, wx, wy, wz, dt)
    state[_core.ACC_REJ] = 0.0
    state[_core.MAG_REJ] = 0.0


@register
class Mahony(Estimator):
    """Mahony PI complementary filter (kp, ki in Mahony's units), optional magnetometer."""

    name: ClassVar[str] = "mahony"
    Params = MahonyParams
    _update_one, _run_batch = (staticmethod(k) for k in _core.make_kernels(_step))

    @classmethod
    def make_params(cls, **params: float | str) -> MahonyParams:
        """As the base, plus ``mag_mode`` given as 'full'/'heading' (or 0/1)."""
        mode = params.pop("mag_mode", "heading")
        if isinstance(mode, int | float) and not isinstance(mode, bool) and mode in (0, 1):
            mode = MAG_MODES[int(mode)]
        if mode not in MAG_MODES:
            raise ValueError(f"mag_mode must be one of {MAG_MODES}, got {mode!r}")
        p = super().make_params(**params)
        return dataclasses.replace(p, mag_mode=mode)

    def _pack_params(self, p: MahonyParams) -> np.ndarray:
        return np.array([p.kp, p.ki, p.bias_limit, 1.0 if p.mag_mode == "heading" else 0.0,
                         1.0 if p.exact else 0.0])
