"""Attitude error metrics (BROAD definitions), shared by benchmarks, replay and the bridge.

``q_err = q_est ⊗ q_ref⁻¹`` is the error expressed in the world frame, so its rotation
about the world vertical (z, in both NED and ENU) is the heading error and the rest is
the inclination error:

* total       ``2·acos|w|``
* heading     ``2·atan|z/w|``
* inclination ``2·acos√(w² + z²)``
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import quat as Q


@dataclass(frozen=True)
class AttitudeErrors:
    """Per-sample errors in radians."""

    total: np.ndarray
    heading: np.ndarray
    inclination: np.ndarray


@dataclass(frozen=True)
class ErrorRms:
    """RMS errors in degrees over the scored samples."""

    total_deg: float
    heading_deg: float
    inclination_deg: float
    samples: int


def attitude_errors(q_est: np.ndarray, q_ref: np.ndarray) -> AttitudeErrors:
    """Per-sample total/heading/inclination errors (radians); NaN where q_ref is NaN."""
    err = Q.multiply(q_est, Q.conjugate(q_ref))
    w, z = np.abs(err[..., 0]), err[..., 3]
    vec = np.linalg.norm(err[..., 1:], axis=-1)
    total = 2.0 * np.arctan2(vec, w)
    heading = 2.0 * np.arctan2(np.abs(z), w)
    inclination = 2.0 * np.arccos(np.clip(np.sqrt(w * w + z * z), 0.0, 1.0))
    return AttitudeErrors(total=total, heading=heading, inclination=inclination)


def rms_errors(q_est: np.ndarray, q_ref: np.ndarray,
               mask: np.ndarray | None = None) -> ErrorRms:
    """RMS over ``mask`` (default: all samples), skipping samples with a NaN reference."""
    e = attitude_errors(q_est, q_ref)
    keep = np.isfinite(e.total)
    if mask is not None:
        keep &= np.asarray(mask, dtype=bool)
    n = int(keep.sum())
    if n == 0:
        return ErrorRms(float("nan"), float("nan"), float("nan"), 0)

    def rms(x: np.ndarray) -> float:
        return float(np.degrees(np.sqrt(np.mean(x[keep] ** 2))))

    return ErrorRms(rms(e.total), rms(e.heading), rms(e.inclination), n)
