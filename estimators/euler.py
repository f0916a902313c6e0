"""Gyro-only Euler-angle integration (seed 000: the Z-Y-X Euler-angle rate equation).

The state is roll φ, pitch θ, yaw ψ of the FRD body relative to NED (aerospace Z-Y-X,
``R = Rz(ψ)·Ry(θ)·Rx(φ)``); each step integrates, to first order (the seed's
"rate times T"),

    φ̇ = p + (q·sinφ + r·cosφ)·tanθ
    θ̇ = q·cosφ − r·sinφ
    ψ̇ = (q·sinφ + r·cosφ) / cosθ

with body rates ``(p, q, r)``. (The seed's body frame is X-right/Y-forward, so its
"pitch about X" is our roll about the forward axis; the equation is the same one
re-labelled.) The quaternion output is rebuilt from the angles every step.

Gimbal lock: at θ = ±90° the equation divides by cosθ = 0 and roll and yaw stop
being separately defined. Clamping cosθ would keep numbers finite but integrate a
wrong equation exactly where the rates it produces are largest. Instead, while
``|θ| > 90° − gimbal_margin`` the step is taken on the quaternion (exact axis-angle
step, which has no singularity) and the angles are re-extracted from it with the
gimbal-lock-safe Z-Y-X extraction (roll set to 0 only when cosθ underflows 1e-6).
Such steps raise :attr:`EulerIntegrator.in_gimbal_lock` and are counted in
:attr:`EulerIntegrator.gimbal_lock_steps`, so a consumer can see that the estimate was
not produced by the Euler equation there. Outside the band the method is the plain
Euler-angle ODE with its first-order error; the output is never NaN or inf.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import _core
from . import quat as Q
from .base import CommonParams, Estimator, param
from .registry import register

# Private state layout.
ROLL = _core.PRIVATE  # φ [rad], (-pi, pi]
PITCH = _core.PRIVATE + 1  # θ [rad], [-pi/2, pi/2]
YAW = _core.PRIVATE + 2  # ψ [rad], (-pi, pi]
ANGLES_SET = _core.PRIVATE + 3  # 1.0 once the angles hold the attitude (else take q)
LOCKED = _core.PRIVATE + 4  # 1.0 if the last step was taken near gimbal lock
LOCK_STEPS = _core.PRIVATE + 5  # number of steps taken near gimbal lock
STATE_SIZE = _core.PRIVATE + 6

_EXTRACT_LOCK_COS = 1e-6  # same threshold as quat.GIMBAL_LOCK_COS


@dataclass(frozen=True)
class EulerParams(CommonParams):
    gimbal_margin: float = param(math.radians(5.0), "[rad] within this of ±90° pitch the "
                                                    "step is taken on the quaternion and "
                                                    "flagged as gimbal lock (0 < margin < pi/2)")


@_core.kernel(inline="always")
def _wrap_pi(a: float) -> float:
    """Angle in (-pi, pi]."""
    if -math.pi < a <= math.pi:
        return a
    a -= 2.0 * math.pi * math.floor((a + math.pi) / (2.0 * math.pi))  # now in [-pi, pi)
    return math.pi if a <= -math.pi else a


@_core.kernel
def _q_from_angles(state: np.ndarray) -> None:
    """state[0:4] ← qz(ψ) ⊗ qy(θ) ⊗ qx(φ)."""
    hr, hp, hy = 0.5 * state[ROLL], 0.5 * state[PITCH], 0.5 * state[YAW]
    cr, sr = math.cos(hr), math.sin(hr)
    cp, sp = math.cos(hp), math.sin(hp)
    cy, sy = math.cos(hy), math.sin(hy)
    state[0] = cr * cp * cy + sr * sp * sy
    state[1] = sr * cp * cy - cr * sp * sy
    state[2] = cr * sp * cy + sr * cp * sy
    state[3] = cr * cp * sy - sr * sp * cy
    _core.normalize_q(state)


@_core.kernel
def _angles_from_q(state: np.ndarray) -> None:
    """Angles ← Z-Y-X Euler angles of state[0:4] (gimbal-lock safe, like quat.to_euler)."""
    w, x, y, z = state[0], state[1], state[2], state[3]
    r00 = 1.0 - 2.0 * (y * y + z * z)
    r10 = 2.0 * (x * y + w * z)
    r20 = 2.0 * (x * z - w * y)
    cos_pitch = math.sqrt(r00 * r00 + r10 * r10)
    # atan2 keeps full precision near ±90°, where asin(-r20) loses half the digits.
    state[PITCH] = math.atan2(-r20, cos_pitch)
    if cos_pitch < _EXTRACT_LOCK_COS:
        r01 = 2.0 * (x * y - w * z)
        r11 = 1.0 - 2.0 * (x * x + z * z)
        state[ROLL] = 0.0
        state[YAW] = _wrap_pi(math.atan2(-r01, r11))
    else:
        r21 = 2.0 * (y * z + w * x)
        r22 = 1.0 - 2.0 * (x * x + y * y)
        state[ROLL] = _wrap_pi(math.atan2(r21, r22))
        state[YAW] = _wrap_pi(math.atan2(r10, r00))
    state[ANGLES_SET] = 1.0


@_core.kernel
def _euler_ode_step(state: np.ndarray, p: float, q: float, r: float, dt: float) -> None:
    """One first-order step of the Euler-angle rate equation (|cosθ| well above 0)."""
    roll, pitch = state[ROLL], state[PITCH]
    sr, cr = math.sin(roll), math.cos(roll)
    cp = math.cos(pitch)
    tp = math.sin(pitch) / cp
    coupled = q * sr + r * cr
    roll += (p + coupled * tp) * dt
    pitch += (q * cr - r * sr) * dt
    yaw = state[YAW] + coupled / cp * dt
    # A long step may carry pitch over ±90°: (φ, θ, ψ) and (φ+π, ±π−θ, ψ+π) are the same
    # attitude, so fold back into the canonical range.
    if pitch > 0.5 * math.pi:
        pitch, roll, yaw = math.pi - pitch, roll + math.pi, yaw + math.pi
    elif pitch < -0.5 * math.pi:
        pitch, roll, yaw = -math.pi - pitch, roll + math.pi, yaw + math.pi
    state[ROLL], state[PITCH], state[YAW] = _wrap_pi(roll), pitch, _wrap_pi(yaw)


@_core.kernel
def _step(state, params, gx, gy, gz, ax, ay, az, mx, my, mz, acc_ok, mag_ok, dt) -> None:
    if state[ANGLES_SET] <= 0.0:
        _angles_from_q(state)  # first step after initialisation from q0 or a sample
    if abs(math.cos(state[PITCH])) < params[0]:
        # Near gimbal lock: exact quaternion step, then back to angles.
        _q_from_angles(state)
        _core.integrate_exact(state, gx, gy, gz, dt)
        _angles_from_q(state)
        state[LOCKED] = 1.0
        state[LOCK_STEPS] += 1.0
    else:
        _euler_ode_step(state, gx, gy, gz, dt)
        state[LOCKED] = 0.0
    _q_from_angles(state)


@register
class EulerIntegrator(Estimator):
    """Integrates the gyro through the Z-Y-X Euler-angle rate equation (no correction)."""

    name = "euler"
    Params = EulerParams
    _state_size = STATE_SIZE
    _update_one, _run_batch = (staticmethod(k) for k in _core.make_kernels(_step))

    def _pack_params(self, p: EulerParams) -> np.ndarray:
        if not 0.0 < p.gimbal_margin < 0.5 * math.pi:
            raise ValueError(f"gimbal_margin must be in (0, pi/2) rad, got {p.gimbal_margin}")
        # The kernel compares |cosθ| with sin(margin) = cos(90° - margin).
        return np.array([math.sin(p.gimbal_margin)])

    @property
    def euler(self) -> np.ndarray:
        """[roll, pitch, yaw] in radians of the body relative to NED (Z-Y-X)."""
        if self._state[ANGLES_SET] <= 0.0:
            return Q.to_euler(self._state[0:4])  # what the first step will start from
        return self._state[ROLL:YAW + 1].copy()

    @property
    def in_gimbal_lock(self) -> bool:
        """True if the last step was within ``gimbal_margin`` of ±90° pitch."""
        return bool(self._state[LOCKED] > 0.0)

    @property
    def gimbal_lock_steps(self) -> int:
        """How many steps were taken on the quaternion because of gimbal lock."""
        return int(self._state[LOCK_STEPS])
