"""Gyro-only direction-cosine-matrix integration with re-orthonormalisation.

The state is ``R`` (body FRD -> NED, ``v_world = R·v_body``), updated each step by the
body-frame rotation over the step, ``R ← R·ΔR`` with ``v = ω·dt``:

* ``exact=True``: Rodrigues ``ΔR = I + (sin a / a)[v×] + ((1 − cos a) / a²)[v×]²``,
  ``a = |v|`` — exact for a rate constant over the step;
* ``exact=False``: the classic first-order ``ΔR = I + [v×]`` (Premerlani & Bizard).

Rounding (and the first-order step) makes ``R`` drift from a rotation, so it is
re-orthonormalised every step with the Premerlani/Bizard error split: with columns
``x, y`` (body x/y axes in NED) scaled to unit length and ``e = x·y``,
``x ← x − (e/2)·y``, ``y ← y − (e/2)·x``, ``z ← x × y``, then each column is scaled to
unit length. The split shares the correction equally between x and y, so neither axis is
privileged, and leaves ``x·y = e³/4``. Unlike the 8-bit original we divide by the exact
norm instead of the Taylor ``(3 − n²)/2`` and also normalise before the split: a
first-order step of angle ``a`` inflates the norms by up to ``√(1 + a²)``, which the
Taylor form under-corrects and which would leave ``x·y ≈ e·a²`` after the split.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import _core
from . import quat as Q
from .base import CommonParams, Estimator, param
from .registry import register

R_START = _core.PRIVATE  # R row-major in state[R_START:R_START + 9]; zeros until set
STATE_SIZE = _core.PRIVATE + 9


@dataclass(frozen=True)
class DcmParams(CommonParams):
    exact: bool = param(True, "True: exact Rodrigues step R·exp([ω×]dt); False: the "
                              "first-order step R·(I + [ω×]dt) (both re-orthonormalised)")


@_core.kernel
def _r_from_q(state: np.ndarray) -> None:
    w, x, y, z = state[0], state[1], state[2], state[3]
    r = R_START
    state[r + 0] = 1.0 - 2.0 * (y * y + z * z)
    state[r + 1] = 2.0 * (x * y - w * z)
    state[r + 2] = 2.0 * (x * z + w * y)
    state[r + 3] = 2.0 * (x * y + w * z)
    state[r + 4] = 1.0 - 2.0 * (x * x + z * z)
    state[r + 5] = 2.0 * (y * z - w * x)
    state[r + 6] = 2.0 * (x * z - w * y)
    state[r + 7] = 2.0 * (y * z + w * x)
    state[r + 8] = 1.0 - 2.0 * (x * x + y * y)


@_core.kernel
def _rotate_r(state: np.ndarray, vx: float, vy: float, vz: float, exact: bool) -> None:
    """R ← R·ΔR for the rotation vector v = ω·dt (body frame)."""
    a2 = vx * vx + vy * vy + vz * vz
    if not exact:
        s, c = 1.0, 0.0
    elif a2 < 1e-12:
        # Series of sin(a)/a and (1 - cos a)/a²: full precision for tiny steps.
        s, c = 1.0 - a2 / 6.0, 0.5 - a2 / 24.0
    else:
        a = math.sqrt(a2)
        s, c = math.sin(a) / a, (1.0 - math.cos(a)) / a2
    # ΔR = I + s·K + c·K², K = [v×], K² = v vᵀ − a² I
    d00 = 1.0 + c * (vx * vx - a2)
    d11 = 1.0 + c * (vy * vy - a2)
    d22 = 1.0 + c * (vz * vz - a2)
    d01, d10 = c * vx * vy - s * vz, c * vx * vy + s * vz
    d02, d20 = c * vx * vz + s * vy, c * vx * vz - s * vy
    d12, d21 = c * vy * vz - s * vx, c * vy * vz + s * vx
    for i in range(3):
        k = R_START + 3 * i
        r0, r1, r2 = state[k], state[k + 1], state[k + 2]
        state[k] = r0 * d00 + r1 * d10 + r2 * d20
        state[k + 1] = r0 * d01 + r1 * d11 + r2 * d21
        state[k + 2] = r0 * d02 + r1 * d12 + r2 * d22


@_core.kernel
def _orthonormalise(state: np.ndarray) -> None:
    """Unit columns x, y; Premerlani/Bizard error split; z = x × y; unit columns again.

    With x, y of unit length and e = x·y, the split leaves x·y = e³/4 (an exact rotation
    step has e ~ 1e-16; a first-order step of angle a has |e| ≤ a²/2)."""
    r = R_START
    xx, xy, xz = state[r + 0], state[r + 3], state[r + 6]
    yx, yy, yz = state[r + 1], state[r + 4], state[r + 7]
    nx = math.sqrt(xx * xx + xy * xy + xz * xz)
    ny = math.sqrt(yx * yx + yy * yy + yz * yz)
    if not (nx > 1e-6 and ny > 1e-6 and math.isfinite(nx + ny)):
        _r_from_q(state)  # unrecoverable: fall back to the last good attitude
        return
    xx, xy, xz, yx, yy, yz = xx / nx, xy / nx, xz / nx, yx / ny, yy / ny, yz / ny
    half_err = 0.5 * (xx * yx + xy * yy + xz * yz)
    xx, xy, xz, yx, yy, yz = (xx - half_err * yx, xy - half_err * yy, xz - half_err * yz,
                              yx - half_err * xx, yy - half_err * xy, yz - half_err * xz)
    nx = math.sqrt(xx * xx + xy * xy + xz * xz)
    ny = math.sqrt(yx * yx + yy * yy + yz * yz)
    xx, xy, xz, yx, yy, yz = xx / nx, xy / nx, xz / nx, yx / ny, yy / ny, yz / ny
    zx, zy, zz = xy * yz - xz * yy, xz * yx - xx * yz, xx * yy - xy * yx
    nz = math.sqrt(zx * zx + zy * zy + zz * zz)
    state[r + 0], state[r + 3], state[r + 6] = xx, xy, xz
    state[r + 1], state[r + 4], state[r + 7] = yx, yy, yz
    state[r + 2], state[r + 5], state[r + 8] = zx / nz, zy / nz, zz / nz


@_core.kernel
def _step(state, params, gx, gy, gz, ax, ay, az, mx, my, mz, acc_ok, mag_ok, dt) -> None:
    r = R_START
    if state[r] == 0.0 and state[r + 1] == 0.0 and state[r + 2] == 0.0:
        # R not set yet (a rotation's rows are unit vectors, never zero): take it from q,
        # which the common kernel set from q0 or the first usable sample.
        _r_from_q(state)
    _rotate_r(state, gx * dt, gy * dt, gz * dt, params[0] > 0.0)
    _orthonormalise(state)
    _core.set_q_from_dcm(state, state[r], state[r + 1], state[r + 2], state[r + 3],
                         state[r + 4], state[r + 5], state[r + 6], state[r + 7], state[r + 8])


@register
class DcmIntegrator(Estimator):
    """Integrates the gyro on the rotation matrix (no correction)."""

    name = "dcm"
    Params = DcmParams
    _state_size = STATE_SIZE
    _update_one, _run_batch = (staticmethod(k) for k in _core.make_kernels(_step))

    def _pack_params(self, p: DcmParams) -> np.ndarray:
        return np.array([1.0 if p.exact else 0.0])

    @property
    def dcm(self) -> np.ndarray:
        """R, body FRD -> NED (``v_ned = R @ v_body``)."""
        r = self._state[R_START:R_START + 9].reshape(3, 3)
        if not r.any():
            return Q.to_dcm(self._state[0:4])
        return r.copy()
