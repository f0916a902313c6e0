"""The quaternion Kalman filter of seed 002 (Long, Chen, Teng): the state is the quaternion.

Per sample, with ``Ω(ω)`` the 4×4 matrix of ``q̇ = ½·Ω(ω)·q`` (i.e. ``½ q ⊗ [0, ω]``):

1. predict ``q⁻ = A·q``, ``P⁻ = A·P·Aᵀ + Q_k`` with ``A = I + ½Ω·dt`` (the paper's
   first-order transition, ``exact=False``) or ``A = exp(½Ω·dt)`` (``exact=True``);
2. measure a quaternion ``z`` from the accelerometer and the magnetometer:
   ``z = q_z(−ψ_m) ⊗ q⁻ ⊗ r`` where ``r`` is the shortest body rotation taking the
   measured down (``−a/|a|``) onto the predicted one, and ``ψ_m`` is the heading of the
   field's horizontal part as seen through ``q⁻`` (0 without a usable magnetometer, or when
   the field is within 2° of vertical). So the accelerometer sets the tilt of ``z`` and the
   magnetometer only its heading; without a magnetometer yaw is never pulled to 0;
3. flip ``z`` onto the hemisphere of ``q⁻`` (``z`` and ``−z`` are the same attitude, but
   the linear update ``q⁻ + K(z − q⁻)`` would cut through the origin);
4. update ``K = P⁻(P⁻ + R_k)⁻¹``, ``q = q⁻ + K(z − q⁻)``, ``P = (I − K)P⁻`` (H = I),
   then normalise ``q``.

Without a usable accelerometer the filter only predicts (the gyro always integrates).

Why not the paper's one-shot acc+mag attitude (as used for initialisation) as ``z``: that
takes the heading from the field projected on the *measured* horizontal, so every
acceleration tilts the measured horizontal and leaks into heading amplified by
tan(dip) (≈ 2.4 in Berlin), and the linear update then feeds that heading noise back into
the tilt. On the BROAD trials (9D, same noise parameters) the mean inclination RMSE drops
from 11.5° to 3.4° and the total from 17.6° to 8.9° with the decoupled ``z``.

Noise scaling: ``Q_k = process_noise·dt·I`` and ``R_k = (measurement_noise/dt)·I``, i.e.
both are given as densities. For a static attitude the steady-state gain is then
``K ≈ dt·√(process_noise/measurement_noise)``, a correction time constant
``τ = √(measurement_noise/process_noise)`` seconds *independent of the sample rate*, so the
same defaults work from 100 Hz to 8 kHz (per-sample variances would make the filter
80× faster at 8 kHz than at 100 Hz). Defaults: τ ≈ 3.2 s (robust to accelerations on
BROAD, mean inclination RMSE 3.3° 6D / 3.4° 9D, on par with Mahony's published gains).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from . import _core
from .base import CommonParams, Estimator, param
from .registry import register

P_START = _core.PRIVATE  # P, 4×4 row-major (16)
Z_START = P_START + 16  # last measurement quaternion (4), scratch for its construction
L_START = Z_START + 4  # scratch: Cholesky factor of S = P⁻ + R (16)
K_START = L_START + 16  # scratch: gain K (16)
STATE_SIZE = K_START + 16

# A magnetometer within this angle (sine) of the vertical gives no usable heading.
_MIN_MAG_HORIZONTAL = math.sin(math.radians(2.0))


@dataclass(frozen=True)
class KalmanParams(CommonParams):
    BOUNDS: ClassVar[dict[str, tuple[float, float]]] = {
        "process_noise": (1e-12, 1e3), "measurement_noise": (1e-12, 1e3), "p0": (1e-12, 1e3)}

    process_noise: float = param(1e-4, "Q density [1/s]: variance added to each quaternion "
                                       "component per second of prediction (Q_k = Q·dt·I); "
                                       "≈ σ_gyro²/4 for a gyro noise density σ in rad/s/√Hz")
    measurement_noise: float = param(1e-3, "R density [s]: variance of each component of the "
                                           "acc/mag quaternion times dt (R_k = R/dt·I); "
                                           "time constant √(R/Q) s")
    p0: float = param(1e-2, "initial covariance of each quaternion component (P_0 = p0·I)")
    exact: bool = param(True, "True: A = exp(½Ω·dt) (exact for constant rate); False: the "
                              "paper's A = I + ½Ω·dt (q normalised after each step)")


@_core.kernel
def _predict(state: np.ndarray, gx: float, gy: float, gz: float, dt: float, q_k: float,
             exact: bool) -> None:
    """q ← A·q, P ← A·P·Aᵀ + q_k·I with A = c·I + k·Ω(ω)."""
    if exact:
        angle = math.sqrt(gx * gx + gy * gy + gz * gz) * dt
        if angle < 1e-6:
            c, k = 1.0 - angle * angle / 8.0, 0.5 * dt * (1.0 - angle * angle / 24.0)
        else:
            c, k = math.cos(0.5 * angle), math.sin(0.5 * angle) / angle * dt
    else:
        c, k = 1.0, 0.5 * dt
    bx, by, bz = k * gx, k * gy, k * gz
    # A (row-major): q ⊗ [c, b] written as a matrix acting on q.
    a = (c, -bx, -by, -bz,
         bx, c, bz, -by,
         by, -bz, c, bx,
         bz, by, -bx, c)
    w, x, y, z = state[0], state[1], state[2], state[3]
    state[0] = a[0] * w + a[1] * x + a[2] * y + a[3] * z
    state[1] = a[4] * w + a[5] * x + a[6] * y + a[7] * z
    state[2] = a[8] * w + a[9] * x + a[10] * y + a[11] * z
    state[3] = a[12] * w + a[13] * x + a[14] * y + a[15] * z
    # AP into the K scratch, then P = (AP)·Aᵀ + q_k·I.
    for i in range(4):
        for j in range(4):
            s = 0.0
            for m in range(4):
                s += a[4 * i + m] * state[P_START + 4 * m + j]
            state[K_START + 4 * i + j] = s
    for i in range(4):
        for j in range(4):
            s = 0.0
            for m in range(4):
                s += state[K_START + 4 * i + m] * a[4 * j + m]
            state[P_START + 4 * i + j] = s + (q_k if i == j else 0.0)


@_core.kernel
def _measure(state: np.ndarray, ax: float, ay: float, az: float, mx: float, my: float,
             mz: float, mag_ok: bool) -> None:
    """state[Z:Z+4] ← z = q_z(−ψ_m) ⊗ q⁻ ⊗ r (see module docstring)."""
    na = math.sqrt(ax * ax + ay * ay + az * az)
    dx, dy, dz = -ax / na, -ay / na, -az / na  # measured down, body axes
    px, py, pz = _core.world_to_body(state, 0.0, 0.0, 1.0)  # predicted down
    rw = 1.0 + dx * px + dy * py + dz * pz
    rx, ry, rz = dy * pz - dz * py, dz * px - dx * pz, dx * py - dy * px
    n = math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
    if n < 1e-9:  # measured down opposite to the predicted one: no shortest arc
        rw, rx, ry, rz, n = 1.0, 0.0, 0.0, 0.0, 1.0
    rw, rx, ry, rz = rw / n, rx / n, ry / n, rz / n
    w, x, y, z = state[0], state[1], state[2], state[3]
    zw = w * rw - x * rx - y * ry - z * rz
    zx = w * rx + x * rw + y * rz - z * ry
    zy = w * ry - x * rz + y * rw + z * rx
    zz = w * rz + x * ry - y * rx + z * rw
    hc, hs = 1.0, 0.0  # cos, sin of −ψ_m/2
    if mag_ok:
        ex, ey, _ = _core.body_to_world(state, mx, my, mz)  # field seen by the prediction
        horizontal = math.sqrt(ex * ex + ey * ey)
        if horizontal > _MIN_MAG_HORIZONTAL * math.sqrt(mx * mx + my * my + mz * mz):
            half = -0.5 * math.atan2(ey, ex)
            hc, hs = math.cos(half), math.sin(half)
    state[Z_START] = hc * zw - hs * zz
    state[Z_START + 1] = hc * zx - hs * zy
    state[Z_START + 2] = hc * zy + hs * zx
    state[Z_START + 3] = hc * zz + hs * zw


@_core.kernel
def _update(state: np.ndarray, r_k: float) -> None:
    """K = P(P + r_k I)⁻¹, q += K(z − q), P = (I − K)P, via Cholesky of S = P + r_k I."""
    if state[0] * state[Z_START] + state[1] * state[Z_START + 1] + \
            state[2] * state[Z_START + 2] + state[3] * state[Z_START + 3] < 0.0:
        for i in range(4):
            state[Z_START + i] = -state[Z_START + i]
    # S = L Lᵀ (lower triangular L in scratch).
    for i in range(4):
        for j in range(i + 1):
            s = state[P_START + 4 * i + j] + (r_k if i == j else 0.0)
            for m in range(j):
                s -= state[L_START + 4 * i + m] * state[L_START + 4 * j + m]
            if i == j:
                state[L_START + 4 * i + i] = math.sqrt(max(s, 1e-300))
            else:
                state[L_START + 4 * i + j] = s / state[L_START + 4 * j + j]
    # Kᵀ = S⁻¹ P (P, S symmetric): solve L Lᵀ X = P column by column, K[j][i] = X[i][j].
    for col in range(4):
        for i in range(4):  # forward: L y = P[:, col]
            s = state[P_START + 4 * i + col]
            for m in range(i):
                s -= state[L_START + 4 * i + m] * state[K_START + 4 * col + m]
            state[K_START + 4 * col + i] = s / state[L_START + 4 * i + i]
        for i in range(3, -1, -1):  # backward: Lᵀ x = y
            s = state[K_START + 4 * col + i]
            for m in range(i + 1, 4):
                s -= state[L_START + 4 * m + i] * state[K_START + 4 * col + m]
            state[K_START + 4 * col + i] = s / state[L_START + 4 * i + i]
    # Now state[K + 4*col + i] = X[i][col] = K[col][i]: row `col` of K is stored contiguously.
    innov = (state[Z_START] - state[0], state[Z_START + 1] - state[1],
             state[Z_START + 2] - state[2], state[Z_START + 3] - state[3])
    for i in range(4):
        row = K_START + 4 * i
        state[i] += (state[row] * innov[0] + state[row + 1] * innov[1]
                     + state[row + 2] * innov[2] + state[row + 3] * innov[3])
    # P ← P − K·P, computed into L scratch (no longer needed), then symmetrised back.
    for i in range(4):
        for j in range(4):
            s = state[P_START + 4 * i + j]
            for m in range(4):
                s -= state[K_START + 4 * i + m] * state[P_START + 4 * m + j]
            state[L_START + 4 * i + j] = s
    for i in range(4):
        for j in range(4):
            state[P_START + 4 * i + j] = 0.5 * (state[L_START + 4 * i + j]
                                                + state[L_START + 4 * j + i])


@_core.kernel
def _step(state, params, gx, gy, gz, ax, ay, az, mx, my, mz, acc_ok, mag_ok, dt) -> None:
    _predict(state, gx, gy, gz, dt, params[0] * dt, params[3] > 0.0)
    _core.normalize_q(state)
    if acc_ok:
        _measure(state, ax, ay, az, mx, my, mz, mag_ok)
        _update(state, params[1] / dt)
        _core.normalize_q(state)


@register
class QuaternionKalman(Estimator):
    """Seed 002's linear Kalman filter on the quaternion (no bias, no disturbance logic)."""

    name = "kalman"
    Params = KalmanParams
    _state_size = STATE_SIZE
    _update_one, _run_batch = (staticmethod(k) for k in _core.make_kernels(_step))

    def _pack_params(self, p: KalmanParams) -> np.ndarray:
        return np.array([p.process_noise, p.measurement_noise, p.p0,
                         1.0 if p.exact else 0.0])

    def _init_private(self, state: np.ndarray, p: KalmanParams) -> None:
        state[P_START:P_START + 16] = (p.p0 * np.eye(4)).ravel()

    @property
    def covariance(self) -> np.ndarray:
        """P, the 4×4 covariance of the quaternion components."""
        return self._state[P_START:P_START + 16].reshape(4, 4).copy()

    @property
    def measurement(self) -> np.ndarray:
        """The last acc/mag measurement quaternion z (body -> NED, on q's hemisphere)."""
        return self._state[Z_START:Z_START + 4].copy()
