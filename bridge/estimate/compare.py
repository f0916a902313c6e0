"""Live comparison of the estimators with references: truth and the vehicle's own attitude.

References, per vehicle:

* ``truth`` — HIL_STATE_QUATERNION, stamped by the same board clock as the IMU, so
  errors are scored at zero shift; the lag is reported separately;
* ``vehicle`` — the autopilot's ATTITUDE_QUATERNION (or ATTITUDE): PX4 stamps these with
  their *publish* time, not the sample time, so the time offset between the two series
  is estimated (the shift that minimises the error) and errors are scored at it.

Errors are the BROAD total / heading / inclination RMS (``estimators.metrics``) over a
rolling window. The "lag" of a series against the reference is the shift ``τ`` that
best explains ``estimate(t) ≈ reference(t - τ)``, from a grid search. It is not always
measurable, and then it is reported as unknown with the reason (``lag_s`` None,
``lag_note``), never as a number: when the best shift is at an open end of the grid
(the lag is beyond it, or the series do not look alike at all) and when the reference
hardly moves in the window (on the ground every shift fits as well as any other).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators import metrics
from estimators import quat as Q
from estimators.shifted_error import rms_at_shifts

from ..vehicle.references import TRUTH, VEHICLE, References
from ..vehicle.ring import TimeRing


@dataclass(frozen=True)
class Comparison:
    """One estimator against one reference over the window."""

    total_deg: float
    heading_deg: float
    inclination_deg: float
    # Best shift τ in estimate(t + τ) ≈ reference(t). Truth: τ > 0 is the estimator's
    # lag. Vehicle: the offset used for scoring; τ < 0 means its stamps are late by -τ.
    # None when not measurable; lag_note then says why ("> 200 ms", "static").
    lag_s: float | None
    samples: int
    lag_note: str = ""

    def to_dict(self) -> dict[str, float | str | None]:
        out: dict[str, float | str | None] = {
            "total_deg": round(self.total_deg, 3), "heading_deg": round(self.heading_deg, 3),
            "inclination_deg": round(self.inclination_deg, 3),
            "lag_s": None if self.lag_s is None else round(self.lag_s, 4),
            "samples": self.samples}
        if self.lag_s is None:
            out["lag_note"] = self.lag_note
        return out


def pairs_at_shift(t_est: np.ndarray, q_est: np.ndarray, t_ref: np.ndarray,
                   q_ref: np.ndarray, shift: float, max_gap: float) -> tuple[np.ndarray, ...]:
    """Reference samples and the estimates at (their time + shift), interpolated between
    the two estimates around that time where those are no more than max_gap apart.
    Interpolated, not the nearest sample: the vehicle's own attitude comes at 50 Hz, and
    its nearest sample, up to 10 ms away in a turn, would charge it with an error that is
    the pairing's (as the replay does, ``replay.align.reference_at``)."""
    query = t_ref + shift
    i0, frac, ok = Q.bracket(t_est, query, max_gap)
    i0, frac = i0[ok], frac[ok]
    return Q.slerp(q_est[i0], q_est[i0 + 1], frac), q_ref[ok]


#: A reference turning less than this over the window shows no lag (on the ground).
MIN_MOTION_DEG = 1.0


def compare_series(t_est: np.ndarray, q_est: np.ndarray, t_ref: np.ndarray,
                   q_ref: np.ndarray, shifts: np.ndarray, score_at_best: bool,
                   max_points: int = 400, open_ends: tuple[bool, bool] = (True, True)
                   ) -> Comparison | None:
    """Score an estimate series against a reference series (both sorted by time).

    ``open_ends``: whether a best shift at the low / high end of ``shifts`` means the
    lag lies beyond the search (unknown). The truth grid starts at 0 and a causal
    estimator cannot lead the truth, so its low end is closed: 0 is a lag there.
    """
    if len(t_est) < 2 or len(t_ref) < 2:
        return None
    order = np.argsort(t_est, kind="stable")
    t_est, q_est = t_est[order], q_est[order]
    step = max(1, len(t_ref) // max_points)
    t_r, q_r = t_ref[::step], q_ref[::step]
    max_gap = 2.0 * float(np.median(np.diff(t_est))) + 1e-4
    rms_by_shift = rms_at_shifts(t_est, q_est, t_r, q_r, shifts, max_gap,
                                 min_pairs=max(3, len(t_r) // 4))
    if not np.isfinite(rms_by_shift).any():
        return None
    best = int(np.nanargmin(rms_by_shift))
    lag: float | None = float(shifts[best])
    note = ""
    if np.degrees(np.max(Q.angle_between(q_r, q_r[:1]))) < MIN_MOTION_DEG:
        lag, note = None, "not measurable: the reference does not move"
    elif best == 0 and open_ends[0]:
        lag, note = None, f"< {shifts[0] * 1e3:.0f} ms (end of the search)"
    elif best == len(shifts) - 1 and open_ends[1]:
        lag, note = None, f"> {shifts[-1] * 1e3:.0f} ms (end of the search)"
    at = lag if (score_at_best and lag is not None) else 0.0
    e, r = pairs_at_shift(t_est, q_est, t_ref, q_ref, at, max_gap)
    if len(e) == 0:
        return None
    err = metrics.rms_errors(e, r)
    return Comparison(err.total_deg, err.heading_deg, err.inclination_deg, lag,
                      err.samples, note)


#: Shift grids [s]: the estimate lags truth (>= 0); the vehicle's stamps may be late or
#: early relative to the IMU sample times, so its offset is searched both ways.
TRUTH_SHIFTS = np.arange(0.0, 0.2001, 0.002)
VEHICLE_SHIFTS = np.arange(-0.3, 0.3001, 0.004)


def vehicle_against_truth(refs: References, window_s: float = 10.0) -> Comparison | None:
    """The vehicle's own attitude scored against the truth, like the estimators are (at
    its stamps, zero shift; ``lag_s`` = the shift that would fit best, searched both
    ways since an autopilot may stamp with its publish time): how good the flight
    controller's estimate is, next to ours."""
    truth, own = refs.series[TRUTH], refs.series[VEHICLE]
    if len(truth) < 2 or len(own) < 2:
        return None
    t_ref, q_ref = truth.snapshot(truth.last_t - window_s)
    t_own, q_own = own.snapshot(truth.last_t - window_s - 1.0)
    valid = np.all(np.isfinite(q_own), axis=1)
    return compare_series(t_own[valid], q_own[valid], t_ref, q_ref, VEHICLE_SHIFTS,
                          score_at_best=False)  # both ends open


def compare_all(history: dict[str, TimeRing], refs: References,
                window_s: float = 10.0) -> dict[str, dict[str, Comparison]]:
    """{reference: {estimator label: Comparison}} over the last ``window_s`` seconds."""
    out: dict[str, dict[str, Comparison]] = {}
    for ref_name, ring in refs.series.items():
        if len(ring) < 2:
            continue
        t_ref, q_ref = ring.snapshot(ring.last_t - window_s)
        shifts = TRUTH_SHIFTS if ref_name == TRUTH else VEHICLE_SHIFTS
        results = {}
        for label, est_ring in history.items():
            t_est, q_est = est_ring.snapshot(ring.last_t - window_s - 1.0)
            valid = np.all(np.isfinite(q_est), axis=1)
            c = compare_series(t_est[valid], q_est[valid], t_ref, q_ref, shifts,
                               score_at_best=(ref_name == VEHICLE),
                               open_ends=(ref_name == VEHICLE, True))
            if c is not None:
                results[label] = c
        if results:
            out[ref_name] = results
    return out
