"""Madgwick's gradient-descent filter, IMU (6D) and MARG (9D).

Each step takes the gyro's quaternion rate and subtracts ``beta`` times the *normalised*
gradient of the squared error between the measured unit vectors and their predictions
from the current attitude::

    q̇ = ½ q ⊗ [0, ω] − beta · ∇f / |∇f|,   f = |Rᵀ·ĝ − â|² [+ |Rᵀ·b − m̂|²]

so ``beta`` [rad/s] is the largest rate at which the measurements can rotate the
estimate (Madgwick 2010; his ``beta = sqrt(3/4)·gyro noise`` rule of thumb).

Frames. The objective and its Jacobian are Madgwick's closed forms, written for his
world frame with x along magnetic north and z up (north-west-up). The state is kept in
NED like every estimator here; each step maps ``q_NWU = [0, 1, 0, 0] ⊗ q_NED`` (180°
about north), applies the formulas, and maps back. This is an exact linear change of
variables, so the filter behaves exactly as the original in its own frame.

The magnetometer reference ``b = (b_h, 0, b_v)`` is re-derived every step from the
measured field rotated into the world frame. In Madgwick's original MadgwickAHRS.c the
variables named ``_2bx``/``_2bz`` hold ``b_h``/``b_v`` (not twice them) while the
objective uses them as ``2·b``: the predicted field is half the measured one, which
halves the magnetometer's pull relative to the accelerometer's. ``original_mag_quirk``
reproduces that (it is what the BROAD paper's published Madgwick numbers used).

Bad samples: without a usable accelerometer the gyro alone integrates (as the original
does; the magnetometer is only used together with gravity).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from . import _core
from .base import CommonParams, Estimator, param
from .registry import register

_BETA, _QUIRK = 0, 1


@dataclass(frozen=True)
class MadgwickParams(CommonParams):
    BOUNDS: ClassVar[dict[str, tuple[float, float]]] = {"beta": (0.0, 10.0)}

    beta: float = param(0.1, "gradient step [rad/s]: the largest correction rate the "
                             "accelerometer/magnetometer can apply (Madgwick's default 0.1)")
    original_mag_quirk: bool = param(False, "True: the original C code's magnetometer "
                                            "reference of half the measured field (as used "
                                            "for the BROAD paper's published numbers)")


@_core.kernel
def _gradient(p0, p1, p2, p3, ax, ay, az, use_mag, mx, my, mz, half_reference):
    """Jᵀf for the NWU objective, with q = (p0, p1, p2, p3) and unit ``a``, ``m``."""
    # Gravity (specific force "up" = +z in NWU): f_g = Rᵀ·ẑ − a.
    f0 = 2.0 * (p1 * p3 - p0 * p2) - ax
    f1 = 2.0 * (p0 * p1 + p2 * p3) - ay
    f2 = 2.0 * (0.5 - p1 * p1 - p2 * p2) - az
    s0 = -2.0 * p2 * f0 + 2.0 * p1 * f1
    s1 = 2.0 * p3 * f0 + 2.0 * p0 * f1 - 4.0 * p1 * f2
    s2 = -2.0 * p0 * f0 + 2.0 * p3 * f1 - 4.0 * p2 * f2
    s3 = 2.0 * p1 * f0 + 2.0 * p2 * f1
    if use_mag:
        # Measured field in the world frame: h = R·m.
        hx = ((p0 * p0 + p1 * p1 - p2 * p2 - p3 * p3) * mx + 2.0 * (p1 * p2 - p0 * p3) * my
              + 2.0 * (p1 * p3 + p0 * p2) * mz)
        hy = (2.0 * (p1 * p2 + p0 * p3) * mx + (p0 * p0 - p1 * p1 + p2 * p2 - p3 * p3) * my
              + 2.0 * (p2 * p3 - p0 * p1) * mz)
        hz = (2.0 * (p1 * p3 - p0 * p2) * mx + 2.0 * (p2 * p3 + p0 * p1) * my
              + (p0 * p0 - p1 * p1 - p2 * p2 + p3 * p3) * mz)
        scale = 1.0 if half_reference else 2.0
        bx2 = scale * math.sqrt(hx * hx + hy * hy)  # "2·b_x" of the formulas
        bz2 = scale * hz
        # f_b = Rᵀ·b − m
        g0 = bx2 * (0.5 - p2 * p2 - p3 * p3) + bz2 * (p1 * p3 - p0 * p2) - mx
        g1 = bx2 * (p1 * p2 - p0 * p3) + bz2 * (p0 * p1 + p2 * p3) - my
        g2 = bx2 * (p0 * p2 + p1 * p3) + bz2 * (0.5 - p1 * p1 - p2 * p2) - mz
        s0 += -bz2 * p2 * g0 + (-bx2 * p3 + bz2 * p1) * g1 + bx2 * p2 * g2
        s1 += bz2 * p3 * g0 + (bx2 * p2 + bz2 * p0) * g1 + (bx2 * p3 - 2.0 * bz2 * p1) * g2
        s2 += ((-2.0 * bx2 * p2 - bz2 * p0) * g0 + (bx2 * p1 + bz2 * p3) * g1
               + (bx2 * p0 - 2.0 * bz2 * p2) * g2)
        s3 += ((-2.0 * bx2 * p3 + bz2 * p1) * g0 + (-bx2 * p0 + bz2 * p2) * g1
               + bx2 * p1 * g2)
    return s0, s1, s2, s3


@_core.kernel
def _step(state, params, gx, gy, gz, ax, ay, az, mx, my, mz, acc_ok, mag_ok, dt) -> None:
    # NED -> NWU: p = [0, 1, 0, 0] ⊗ q
    p0, p1, p2, p3 = -state[1], state[0], -state[3], state[2]
    d0 = 0.5 * (-p1 * gx - p2 * gy - p3 * gz)
    d1 = 0.5 * (p0 * gx + p2 * gz - p3 * gy)
    d2 = 0.5 * (p0 * gy - p1 * gz + p3 * gx)
    d3 = 0.5 * (p0 * gz + p1 * gy - p2 * gx)
    if acc_ok:
        n = math.sqrt(ax * ax + ay * ay + az * az)
        ax, ay, az = ax / n, ay / n, az / n
        if mag_ok:
            n = math.sqrt(mx * mx + my * my + mz * mz)
            mx, my, mz = mx / n, my / n, mz / n
        s0, s1, s2, s3 = _gradient(p0, p1, p2, p3, ax, ay, az, mag_ok, mx, my, mz,
                                   params[_QUIRK] > 0.0)
        n = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2 + s3 * s3)
        if n > 0.0 and math.isfinite(n):
            beta = params[_BETA] / n
            d0 -= beta * s0
            d1 -= beta * s1
            d2 -= beta * s2
            d3 -= beta * s3
    p0 += d0 * dt
    p1 += d1 * dt
    p2 += d2 * dt
    p3 += d3 * dt
    # NWU -> NED: q = [0, -1, 0, 0] ⊗ p
    state[0], state[1], state[2], state[3] = p1, -p0, p3, -p2
    _core.normalize_q(state)
    state[_core.ACC_REJ] = 0.0
    state[_core.MAG_REJ] = 0.0


@register
class Madgwick(Estimator):
    """Madgwick gradient-descent filter (beta in rad/s), IMU or MARG."""

    name: ClassVar[str] = "madgwick"
    Params = MadgwickParams
    _update_one, _run_batch = (staticmethod(k) for k in _core.make_kernels(_step))

    def _pack_params(self, p: MadgwickParams) -> np.ndarray:
        return np.array([p.beta, 1.0 if p.original_mag_quirk else 0.0])
