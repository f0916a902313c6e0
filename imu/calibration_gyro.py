"""Gyro scale and cross-axis errors from the turns between static poses.

The method of Tedaldi, Pretto and Menegatti ("A robust and easy to implement method for
IMU calibration without external equipments", ICRA 2014): between two still poses the
board turns, and the turn is known without any turntable — the calibrated accelerometer
gives the gravity direction in the body at each pose and the calibrated magnetometer the
field direction (which fixes the turn about gravity). Integrating the offset-corrected
gyro through the right correction matrix ``M`` must carry each pose's reference
directions onto the next pose's; ``M`` (all 9 entries) is the least-squares solution,
found by Gauss-Newton on those direction residuals with the exact quaternion step
``exp(ω dt / 2)`` per sample.

Why the directions and not the rotation: a pose without a usable magnetometer reading
still contributes its gravity direction (two of the three components of the turn).

The turns must rotate the board substantially about every axis, otherwise a column of
``M`` is not seen; such data, and turns the gyro cannot reproduce even after the fit
(the board crept during a "still" pose, samples are missing, the rate is wrong), are
refused with the reason rather than fitted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Fewer turns than this cannot pin 9 parameters down with gravity alone (2 per turn).
MIN_TURNS = 6
#: The turns' rotation vectors must add up to at least this much rotation about the
#: weakest direction (sqrt of the smallest eigenvalue of sum φ φ^T): below it the matrix
#: column for that direction is hardly seen and its fit is noise.
MIN_AXIS_ROTATION_DEG = 90.0
#: Column-scaled Jacobian condition beyond which the turns do not determine M.
MAX_JACOBIAN_CONDITION = 1e3
#: After the fit the turns must be reproduced to within this (RMS over all directions).
MAX_TURN_ERROR_DEG = 0.5
#: A fitted entry further than this from the identity is beyond any MEMS gyro's errors
#: (MPU6050 datasheet: ±3 % sensitivity, ±2 % cross-axis): a wrong sample rate or data.
MAX_DISTORTION = 0.1
FD_STEP = 1e-6  # finite-difference step on the matrix entries (they are ~1)
CHUNK = 1024  # samples integrated at once


@dataclass(frozen=True)
class Turn:
    """One turn from a still pose to the next one.

    ``rates``: (L, 3) gyro samples with the offset already removed, from the middle of
    the first pose to the middle of the second; ``start``/``end``: (2, 3) unit reference
    directions in the body at the two poses (gravity, field); ``weight``: (2,) 1 where a
    reference is valid, 0 where not (no magnetometer reading).
    """

    rates: np.ndarray
    start: np.ndarray
    end: np.ndarray
    weight: np.ndarray


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) quaternions [w, x, y, z]."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def _rotate_into_end(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R(q)^T v: a vector fixed in the world, seen from the body after the turn q."""
    w, u = q[..., :1], -q[..., 1:]  # conjugate
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _ordered_product(q: np.ndarray) -> np.ndarray:
    """q[..., 0, :] ⊗ q[..., 1, :] ⊗ ... for (..., L, 4), by pairwise halving (the product
    is associative), so a long turn costs log2(L) numpy calls, not L."""
    while q.shape[-2] > 1:
        if q.shape[-2] % 2:
            pad = np.zeros((*q.shape[:-2], 1, 4))
            pad[..., 0] = 1.0
            q = np.concatenate([q, pad], axis=-2)
        q = _qmul(q[..., 0::2, :], q[..., 1::2, :])
    return q[..., 0, :]


def integrate(rates: np.ndarray, valid: np.ndarray, matrices: np.ndarray,
              dt: float) -> np.ndarray:
    """(C, K, 4) turn quaternions for C candidate matrices and K padded turns.

    ``rates`` (K, L, 3), ``valid`` (K, L) marks real samples (padding is no rotation);
    each sample contributes the exact step ``exp(M ω dt / 2)``. Worked through in time
    chunks so memory stays bounded for long turns at high rates.
    """
    q = np.zeros((len(matrices), rates.shape[0], 4))
    q[..., 0] = 1.0
    for k in range(0, rates.shape[1], CHUNK):
        w = np.einsum("cij,klj->ckli", matrices, rates[:, k:k + CHUNK]) * dt
        angle = np.linalg.norm(w, axis=-1, keepdims=True)
        half_sinc = 0.5 * np.sinc(angle / (2.0 * np.pi))  # sin(θ/2)/θ, finite at θ = 0
        steps = np.concatenate([np.cos(angle / 2.0), w * half_sinc], axis=-1)
        steps[:, ~valid[:, k:k + CHUNK]] = (1.0, 0.0, 0.0, 0.0)
        q = _qmul(q, _ordered_product(steps))
    return q


class _Problem:
    """The turns padded into arrays, and the residuals for candidate matrices."""

    def __init__(self, turns: list[Turn], dt: float):
        length = max(len(t.rates) for t in turns)
        self.rates = np.zeros((len(turns), length, 3))
        self.valid = np.zeros((len(turns), length), bool)
        for k, t in enumerate(turns):
            self.rates[k, :len(t.rates)] = t.rates
            self.valid[k, :len(t.rates)] = True
        self.start = np.stack([t.start for t in turns])  # (K, 2, 3)
        self.end = np.stack([t.end for t in turns])
        self.weight = np.stack([t.weight for t in turns])  # (K, 2)
        self.dt = dt

    def differences(self, matrices: np.ndarray) -> np.ndarray:
        """(C, K, 2, 3) predicted minus measured end directions (weighted)."""
        q = integrate(self.rates, self.valid, matrices, self.dt)
        predicted = _rotate_into_end(q[:, :, None, :], self.start[None])
        return (predicted - self.end[None]) * self.weight[None, :, :, None]

    def residuals(self, matrices: np.ndarray) -> np.ndarray:
        d = self.differences(matrices)
        return d.reshape(len(matrices), -1)

    def rms_error_deg(self, matrix: np.ndarray) -> float:
        """RMS angle between predicted and measured directions over the valid ones."""
        d = np.linalg.norm(self.differences(matrix[None])[0], axis=-1)
        angles = 2.0 * np.arcsin(np.clip(d / 2.0, 0.0, 1.0))
        return float(np.degrees(np.sqrt(np.sum(angles**2) / np.sum(self.weight))))

    def rotation_vectors(self) -> np.ndarray:
        """(K, 3) each turn's summed rate × dt (offset-corrected, uncorrected scale)."""
        return np.sum(self.rates * self.valid[..., None], axis=1) * self.dt


def weakest_rotation(rotvecs: np.ndarray) -> tuple[float, np.ndarray]:
    """(degrees, unit axis): how much the turns rotate about their least-turned axis."""
    evals, evecs = np.linalg.eigh(rotvecs.T @ rotvecs)
    return float(np.degrees(np.sqrt(max(evals[0], 0.0)))), evecs[:, 0]


def fit_gyro_matrix(turns: list[Turn], rate_hz: float, iterations: int = 10
                    ) -> tuple[np.ndarray, dict]:
    """(correction matrix M, report fields) with corrected rate = M @ (raw - offset).

    ValueError (saying why) when the turns cannot determine M or M cannot reproduce them.
    """
    if len(turns) < MIN_TURNS:
        raise ValueError(f"gyro matrix: {len(turns)} turn(s) between still poses, need "
                         f"{MIN_TURNS}; turn the board from pose to pose about all axes "
                         "(or fit the offset only with --no-gyro-matrix)")
    problem = _Problem(turns, 1.0 / rate_hz)
    weakest_deg, axis = weakest_rotation(problem.rotation_vectors())
    if weakest_deg < MIN_AXIS_ROTATION_DEG:
        raise ValueError(f"gyro matrix: the turns between poses do not excite all axes "
                         f"(only {weakest_deg:.0f}° of rotation about body axis "
                         f"{np.round(axis, 2).tolist()}, need {MIN_AXIS_ROTATION_DEG:g}°); "
                         "turn the board about every axis between poses (or fit the "
                         "offset only with --no-gyro-matrix)")
    m = np.eye(3)
    before = problem.rms_error_deg(m)
    basis = np.eye(9).reshape(9, 3, 3) * FD_STEP
    for _ in range(iterations):
        r = problem.residuals(np.concatenate([m[None], m[None] + basis]))
        jac = (r[1:] - r[0]).T / FD_STEP  # (residuals, 9)
        scale = np.linalg.norm(jac, axis=0)
        scale[scale == 0.0] = 1.0
        sv = np.linalg.svd(jac / scale, compute_uv=False)
        cond = sv[0] / sv[-1] if sv[-1] > 0 else np.inf
        if cond > MAX_JACOBIAN_CONDITION:
            raise ValueError(f"gyro matrix: the turns do not determine the scale and "
                             f"cross-axis errors (condition {cond:.3g}); turn the board "
                             "about every axis between poses (or fit the offset only with "
                             "--no-gyro-matrix)")
        step = np.linalg.lstsq(jac / scale, -r[0], rcond=None)[0] / scale
        m = m + step.reshape(3, 3)
        if np.max(np.abs(step)) < 1e-10:
            break
    after = problem.rms_error_deg(m)
    if after > MAX_TURN_ERROR_DEG:
        raise ValueError(f"gyro matrix: even the best matrix leaves the turns between poses "
                         f"{after:.2f}° RMS off (limit {MAX_TURN_ERROR_DEG:g}°): the board "
                         "moved during a still pose, samples are missing, or the sample "
                         "rate is wrong (or fit the offset only with --no-gyro-matrix)")
    distortion = float(np.max(np.abs(m - np.eye(3))))
    if distortion > MAX_DISTORTION:
        raise ValueError(f"gyro matrix: the fit is {100 * distortion:.1f} % from identity, "
                         f"more than a MEMS gyro's errors ({100 * MAX_DISTORTION:g} %); "
                         "check the sample rate of the log")
    report = {"gyro_turns": len(turns), "gyro_weakest_rotation_deg": weakest_deg,
              "gyro_turn_error_before_deg": before, "gyro_turn_error_after_deg": after}
    return m, report
