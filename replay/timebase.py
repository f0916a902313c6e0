"""Time-stamp hygiene and resampling between streams with different clocks."""

from __future__ import annotations

import numpy as np

from .dataset import TimeCleanup


def monotonic_mask(t: np.ndarray) -> tuple[np.ndarray, TimeCleanup]:
    """Keep samples whose time is later than every kept sample before them.

    Logs carry duplicated messages and occasional time going backwards (reboots,
    reordering); both would give the estimators a zero or negative ``dt``. They are
    dropped and counted instead, never silently reordered.
    """
    t = np.asarray(t, dtype=float)
    finite = np.isfinite(t)
    # A sample is kept iff it is later than everything before it (the running maximum of
    # all earlier samples equals that of the kept ones, since each new maximum is kept).
    clean = np.where(finite, t, -np.inf)
    prev_max = np.concatenate(([-np.inf], np.maximum.accumulate(clean)[:-1]))
    keep = finite & (clean > prev_max)
    dup = int(np.count_nonzero(finite & (clean == prev_max)))
    back = int(np.count_nonzero(finite & (clean < prev_max)))
    cleanup = TimeCleanup(kept=int(keep.sum()), duplicates=dup, backwards=back,
                          non_finite=int((~finite).sum()))
    return keep, cleanup


def sample_and_hold(t_src: np.ndarray, values: np.ndarray, t_dst: np.ndarray) -> np.ndarray:
    """The latest source value at or before each destination time; NaN before the first.

    This is what an onboard estimator sees from a slower sensor (a 15–100 Hz
    magnetometer next to a 200 Hz IMU): the last reading, not an interpolated future one.
    """
    idx = np.searchsorted(t_src, t_dst, side="right") - 1
    out = np.full((t_dst.shape[0], values.shape[1]), np.nan)
    ok = idx >= 0
    out[ok] = values[idx[ok]]
    return out
