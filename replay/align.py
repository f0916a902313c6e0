"""Bring a reference attitude onto the IMU's time base, and measure lag between two.

Reference and IMU streams have different clocks and rates (PX4 attitude at 50–250 Hz,
a tlog's ATTITUDE at a few Hz), so the reference is interpolated at every IMU sample:
spherical linear interpolation (slerp) between the two neighbouring reference samples,
or the nearest one. Gaps longer than ``max_gap`` and times outside the reference give
NaN (not scored) rather than a made-up attitude.
"""

from __future__ import annotations

import numpy as np

from estimators import quat as Q

from .dataset import Reference

DEFAULT_MAX_GAP_S = 1.0
METHODS = ("slerp", "nearest")
#: More lag-grid points per IMU sample than this: the scored span is mostly time gap (a
#: clock that jumped), and gridding it would take memory and time without bound.
MAX_GRID_PER_SAMPLE = 4
GAP_STEPS = 10  # a step between scored samples longer than this many IMU steps is a gap


def reference_at(ref: Reference, t: np.ndarray, method: str = "slerp",
                 max_gap: float = DEFAULT_MAX_GAP_S) -> np.ndarray:
    """(N, 4) reference attitude at the times ``t``; NaN where it is unknown."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    t = np.asarray(t, dtype=float)
    if ref.t.shape == t.shape and np.array_equal(ref.t, t):
        return ref.q.copy()  # same clock (BROAD, CSV): nothing to interpolate
    out = np.full((t.shape[0], 4), np.nan)
    if ref.t.shape[0] == 0:
        return out
    if ref.t.shape[0] == 1:
        out[np.abs(t - ref.t[0]) <= max_gap / 2] = ref.q[0]
        return out
    i0, frac, inside = Q.bracket(ref.t, t, max_gap)
    q0, q1 = ref.q[i0], ref.q[i0 + 1]
    q = (np.where((frac < 0.5)[:, None], q0, q1) if method == "nearest"
         else Q.slerp(q0, q1, frac))
    out[inside] = q[inside]
    return out


def earlier_on_grid(q: np.ndarray, rate_hz: float, seconds: float) -> np.ndarray:
    """(N, 4) attitudes sampled at ``rate_hz``, each replaced by the attitude ``seconds``
    earlier (slerped between samples; NaN where that is before the first sample): a
    reference moved on its own clock, to see how much of a score is the timing between
    two recording systems."""
    shift = seconds * rate_hz
    whole = int(np.floor(shift))
    later = np.roll(q, whole, axis=0)
    earlier = np.roll(q, whole + 1, axis=0)
    out = Q.slerp(later, earlier, np.full(len(q), shift - whole))
    out[: whole + 1] = np.nan
    return out


def angles_for_lag(q: np.ndarray) -> np.ndarray:
    """Roll, pitch and unwrapped yaw (rad) of a stack of attitudes; NaN rows stay NaN."""
    e = Q.to_euler(np.where(np.isfinite(q), q, 1.0))
    e[~np.all(np.isfinite(q), axis=1)] = np.nan
    ok = np.all(np.isfinite(e), axis=1)
    if ok.any():
        e[ok] = np.unwrap(e[ok], axis=0)
    return e


def estimate_lag(t: np.ndarray, q_est: np.ndarray, q_ref: np.ndarray,
                 valid: np.ndarray | None = None, max_lag_s: float = 1.0,
                 min_motion_deg: float = 1.0) -> float:
    """Delay (s) of the estimate behind the reference; NaN when not measurable
    (:func:`measure_lag` says why)."""
    return measure_lag(t, q_est, q_ref, valid, max_lag_s, min_motion_deg)[0]


def measure_lag(t: np.ndarray, q_est: np.ndarray, q_ref: np.ndarray,
                valid: np.ndarray | None = None, max_lag_s: float = 1.0,
                min_motion_deg: float = 1.0) -> tuple[float, str]:
    """(delay [s] of the estimate behind the reference, "" or why it is NaN).

    Both attitudes become roll / pitch / unwrapped yaw, resampled on a uniform grid at
    the median IMU step; the shift within ±``max_lag_s`` that minimises the variance of
    their difference over the overlap (built from the cross-correlation, via FFT, and
    running sums) is refined by a parabola through the minimum. A minimum at the edge
    of the window gives NaN: the lag is larger than ``max_lag_s`` or not a lag at all.
    Positive: the estimate is late. NaN when the reference barely moves (std below
    ``min_motion_deg``): lag is not observable on a static log.
    """
    a_est, a_ref = angles_for_lag(q_est), angles_for_lag(q_ref)
    ok = np.all(np.isfinite(a_est), axis=1) & np.all(np.isfinite(a_ref), axis=1)
    if valid is not None:
        ok &= valid
    nan = float("nan")
    if ok.sum() < 16:
        return nan, "fewer than 16 scored samples"
    step = float(np.median(np.diff(t)))
    ok, span = _gridded_span(t, ok, step)
    ts = t[ok]
    grid = np.arange(ts[0], ts[-1], step)
    if grid.shape[0] < 16:
        return nan, f"{span} shorter than 16 IMU steps"
    est = np.stack([np.interp(grid, ts, a_est[ok, k]) for k in range(3)], axis=1)
    ref = np.stack([np.interp(grid, ts, a_ref[ok, k]) for k in range(3)], axis=1)
    est, ref = est - est.mean(axis=0), ref - ref.mean(axis=0)
    if np.degrees(ref.std(axis=0).max()) < min_motion_deg:
        return nan, f"reference moves less than {min_motion_deg:g}° (static): not observable"
    n = grid.shape[0]
    size = 1 << int(np.ceil(np.log2(2 * n)))
    spec = np.fft.rfft(est, size, axis=0) * np.conj(np.fft.rfft(ref, size, axis=0))
    xcorr = np.fft.irfft(spec, size, axis=0)  # xcorr[k] = sum_i est[i+k] * ref[i]
    max_k = min(round(max_lag_s / step), n // 2)
    lags = np.arange(-max_k, max_k + 1)
    # Variance of the difference over the overlap of the shifted signals: unlike the raw
    # cross-correlation it does not favour small lags for their longer overlap, and a
    # constant offset (a heading offset, slow drift) does not move the minimum.
    lo, hi = np.maximum(0, -lags), np.minimum(n, n - lags)
    m = (hi - lo)[:, None]

    def window_sums(x: np.ndarray, shift: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c1 = np.concatenate((np.zeros((1, 3)), np.cumsum(x, axis=0)))
        c2 = np.concatenate((np.zeros((1, 3)), np.cumsum(x**2, axis=0)))
        return c1[hi + shift] - c1[lo + shift], c2[hi + shift] - c2[lo + shift]

    s_est, s2_est = window_sums(est, lags)
    s_ref, s2_ref = window_sums(ref, np.zeros_like(lags))
    mean_sq = (s2_est + s2_ref - 2.0 * xcorr[lags % size]) / m
    mse = (mean_sq - ((s_est - s_ref) / m) ** 2).sum(axis=1)
    k = int(np.argmin(mse))
    if k in (0, len(mse) - 1):  # at the window's edge: the true lag is beyond ±max_lag_s
        side = ">" if lags[k] > 0 else "< -"
        return nan, (f"{side}{max_lag_s:g} s: best shift at the edge of the ±{max_lag_s:g} s "
                     f"search (not a lag, or a longer one)")
    shift = float(lags[k])
    # parabola through the minimum and its neighbours
    y0, y1, y2 = mse[k - 1], mse[k], mse[k + 1]
    denom = y0 - 2.0 * y1 + y2
    if denom > 0:
        shift += 0.5 * (y0 - y2) / denom
    return shift * step, ""


def _gridded_span(t: np.ndarray, ok: np.ndarray, step: float) -> tuple[np.ndarray, str]:
    """The scored samples to measure the lag on, and what they are called in a reason.

    All of them, unless the uniform grid over their span would hold more than
    ``MAX_GRID_PER_SAMPLE`` points per IMU sample: then the span is mostly a time gap (a
    clock that jumped by days gives billions of points) and only the longest stretch
    without a gap of over ``GAP_STEPS`` IMU steps is used, whose grid is bounded by its
    sample count.
    """
    idx = np.flatnonzero(ok)
    if (t[idx[-1]] - t[idx[0]]) / step <= MAX_GRID_PER_SAMPLE * t.shape[0]:
        return ok, "scored span"
    breaks = np.flatnonzero(np.diff(t[idx]) > GAP_STEPS * step) + 1
    stretches = np.split(idx, breaks)
    longest = max(stretches, key=len)
    out = np.zeros_like(ok)
    out[longest] = True
    return out, "longest scored stretch without a time gap"
