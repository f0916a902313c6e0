"""RMS attitude error of an estimate series against a reference at many time shifts,
compiled.

The live comparison looks for the shift that best lines an estimate up with a reference
(an estimator's lag behind the truth, an autopilot's stamping offset): a hundred shifts
or more, each pairing a few hundred reference samples with the estimate interpolated at
their shifted times. It runs every status tick for every estimator against every
reference, on the vehicle's companion computer, so it is one compiled pass instead of a
stack of numpy temporaries per shift.

The pairing is :func:`estimators.quat.bracket` and :func:`estimators.quat.slerp`, the
error :func:`estimators.quat.angle_between`, per sample with the compiled quaternion
helpers of :mod:`estimators._core`.
"""

from __future__ import annotations

import math

import numpy as np

from ._core import kernel, quat_exp, quat_multiply, quat_normalized


@kernel
def _rms_at_shifts(t_est: np.ndarray, q_est: np.ndarray, t_ref: np.ndarray,
                   q_ref: np.ndarray, shifts: np.ndarray, max_gap: float,
                   min_pairs: int) -> np.ndarray:  # pragma: no cover - compiled
    n = t_est.shape[0]
    out = np.full(shifts.shape[0], np.nan)
    for s in range(shifts.shape[0]):
        total = 0.0
        pairs = 0
        for k in range(t_ref.shape[0]):
            t = t_ref[k] + shifts[s]
            if t < t_est[0] or t > t_est[n - 1]:
                continue
            i = min(max(np.searchsorted(t_est, t, side="right") - 1, 0), n - 2)
            span = t_est[i + 1] - t_est[i]
            if span > max_gap and t != t_est[i] and t != t_est[i + 1]:
                continue  # (on a sample itself nothing is interpolated: see Q.bracket)
            frac = min(max((t - t_est[i]) / max(span, 1e-12), 0.0), 1.0)
            aw, ax, ay, az = q_est[i, 0], q_est[i, 1], q_est[i, 2], q_est[i, 3]
            bw, bx, by, bz = q_est[i + 1, 0], q_est[i + 1, 1], q_est[i + 1, 2], q_est[i + 1, 3]
            # step = a* ⊗ b, sign-fixed, normalised
            sw, sx, sy, sz = quat_multiply(aw, -ax, -ay, -az, bw, bx, by, bz)
            sw, sx, sy, sz = quat_normalized(sw, sx, sy, sz)
            if sw < 0.0:
                sw, sx, sy, sz = -sw, -sx, -sy, -sz
            # its rotation vector, scaled by frac, back to a quaternion d
            vn = math.sqrt(sx * sx + sy * sy + sz * sz)
            scale = 2.0 / max(sw, 1e-300) if vn < 1e-9 else 2.0 * math.atan2(vn, sw) / vn
            dw, dx, dy, dz = quat_exp(frac * scale * sx, frac * scale * sy, frac * scale * sz)
            # estimate e = a ⊗ d, normalised
            ew, ex, ey, ez = quat_multiply(aw, ax, ay, az, dw, dx, dy, dz)
            ew, ex, ey, ez = quat_normalized(ew, ex, ey, ez)
            # error e ⊗ r*, r normalised
            cw, cx, cy, cz = quat_normalized(q_ref[k, 0], q_ref[k, 1], q_ref[k, 2],
                                             q_ref[k, 3])
            fw, fx, fy, fz = quat_multiply(ew, ex, ey, ez, cw, -cx, -cy, -cz)
            err = 2.0 * math.atan2(math.sqrt(fx * fx + fy * fy + fz * fz), abs(fw))
            total += err * err
            pairs += 1
        if pairs >= min_pairs and pairs > 0:
            out[s] = math.sqrt(total / pairs)
    return out


def rms_at_shifts(t_est: np.ndarray, q_est: np.ndarray, t_ref: np.ndarray,
                  q_ref: np.ndarray, shifts: np.ndarray, max_gap: float,
                  min_pairs: int) -> np.ndarray:
    """RMS angle [rad] between each reference sample and the estimate interpolated
    (slerp) at the sample's time + shift, for every shift; a pair only where the two
    estimates around that time are at most ``max_gap`` apart, or the time is an
    estimate's own (as :func:`estimators.quat.bracket`). NaN for a shift with
    fewer than ``min_pairs`` pairs. ``t_est`` sorted, 2 samples at least."""
    return _rms_at_shifts(np.ascontiguousarray(t_est, dtype=np.float64),
                          np.ascontiguousarray(q_est, dtype=np.float64),
                          np.ascontiguousarray(t_ref, dtype=np.float64),
                          np.ascontiguousarray(q_ref, dtype=np.float64),
                          np.ascontiguousarray(shifts, dtype=np.float64),
                          float(max_gap), int(min_pairs))
