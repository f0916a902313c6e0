"""Arrays for plotting, shared by the PNG figures and the interactive report.

Euler angles are unwrapped: a yaw going through ±180° would otherwise draw a vertical
line across the whole panel at every crossing (unreadable walls of lines in a spinning
flight). Each estimate is then shifted by whole turns to sit next to the reference, so
that unwrapping the two separately does not show a 360° "error".
"""

from __future__ import annotations

import numpy as np

from estimators import quat as Q

from .evaluate import Evaluation


def euler_deg(q: np.ndarray) -> np.ndarray:
    """(N, 3) roll, pitch, yaw [deg] (Z-Y-X), NaN rows where q is NaN."""
    q = np.asarray(q, dtype=float)
    ok = np.all(np.isfinite(q), axis=1)
    out = np.full((q.shape[0], 3), np.nan)
    if ok.any():
        out[ok] = np.degrees(Q.to_euler(q[ok]))
    return out


def unwrap_deg(angles: np.ndarray) -> np.ndarray:
    """Unwrap each column over its finite samples (period 360°)."""
    out = np.array(angles, dtype=float)
    for k in range(out.shape[1]):
        ok = np.isfinite(out[:, k])
        if ok.sum() > 1:
            out[ok, k] = np.unwrap(out[ok, k], period=360.0)
    return out


def near(angles: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``angles`` shifted per column by whole turns to be closest to ``target`` where
    both first exist."""
    out = np.array(angles, dtype=float)
    both = np.all(np.isfinite(out), axis=1) & np.all(np.isfinite(target), axis=1)
    if both.any():
        i = int(np.argmax(both))
        out += 360.0 * np.round((target[i] - out[i]) / 360.0)
    return out


def plot_angles(ev: Evaluation) -> tuple[np.ndarray | None, dict[str, np.ndarray]]:
    """(reference, {estimator: angles}) as unwrapped roll/pitch/yaw [deg]."""
    ref = None
    if ev.prepared.q_ref is not None:
        ref = unwrap_deg(euler_deg(ev.prepared.q_ref))
    out = {}
    for label, run in ev.runs.items():
        e = unwrap_deg(euler_deg(run.q))
        out[label] = near(e, ref) if ref is not None else e
    return ref, out


def decimation(n: int, max_points: int) -> slice:
    """Every k-th sample so that at most about ``max_points`` remain."""
    return slice(None, None, max(1, -(-n // max_points)))
