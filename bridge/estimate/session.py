"""Whole-session scores against the truth: every truth sample counted once, for every
estimator and the vehicle's own attitude.

The live comparison (:mod:`.compare`) is a rolling window: it says how things stand now,
and at the end of a flight "now" is the vehicle standing on the ground. Someone running
two estimators side by side (``-e eskf -e vqf``) wants the other number too: over
everything so far, take-off, flight and landing included, which one was closer to the
truth. Each status tick scores the truth samples that arrived since the last one, at
zero shift like the rolling comparison, and adds their squared errors to running sums;
nothing is kept per sample, so a flight of any length costs the same memory.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimators import metrics

from ..vehicle.ring import TimeRing
from .compare import pairs_at_shift

#: The label of the vehicle's own attitude among the estimators' (as in the live table).
VEHICLE_OWN = "(vehicle own)"


@dataclass
class _Sums:
    samples: int = 0
    total: float = 0.0  # sums of squared errors [rad²]
    heading: float = 0.0
    inclination: float = 0.0

    def to_dict(self) -> dict[str, float | int]:
        n = self.samples

        def rms(s: float) -> float:
            return round(math.degrees(math.sqrt(s / n)), 3)

        return {"total_deg": rms(self.total), "heading_deg": rms(self.heading),
                "inclination_deg": rms(self.inclination), "samples": n}


class SessionScores:
    """Running RMS errors against the truth, per series label, since the bridge started."""

    def __init__(self) -> None:
        self._sums: dict[str, _Sums] = {}
        # per label: board time of the last truth sample counted for it. Per label because
        # a slower series (the vehicle's own attitude at 50 Hz) has not yet reached the
        # newest truth samples when the estimators have; those wait for its next sample.
        self._counted_to: dict[str, float] = {}

    def new_timeline(self) -> None:
        """The board clock started again (a reboot): count from its new beginning; the
        sums so far stay (they were scored right)."""
        self._counted_to.clear()

    def update(self, truth: TimeRing, estimators: dict[str, TimeRing],
               vehicle_own: TimeRing | None = None) -> None:
        """Score, for each series, the truth samples since its last count that it has
        reached: a truth sample is scored once its series has a sample on each side."""
        reached = [ring.last_t for ring in estimators.values() if len(ring) >= 2]
        if len(truth) < 2 or not reached:
            return
        upper = min(reached)  # the estimators are scored over the same samples
        series = dict(estimators)
        if vehicle_own is not None:
            series[VEHICLE_OWN] = vehicle_own
        series = {label: ring for label, ring in series.items() if len(ring) >= 2}
        counted = {label: self._counted_to.get(label, -math.inf) for label in series}
        t_truth, q_truth = truth.snapshot(min(counted.values()))  # bounded by the ring
        for label, ring in series.items():
            fresh = ((t_truth > counted[label]) & (t_truth <= min(upper, ring.last_t)))
            if not fresh.any():
                continue
            t_ref, q_ref = t_truth[fresh], q_truth[fresh]
            self._score(label, ring, t_ref, q_ref)
            self._counted_to[label] = float(t_ref[-1])

    def _score(self, label: str, ring: TimeRing, t_ref: np.ndarray,
               q_ref: np.ndarray) -> None:
        t_est, q_est = ring.snapshot(float(t_ref[0]) - 1.0)
        valid = np.all(np.isfinite(q_est), axis=1)
        t_est, q_est = t_est[valid], q_est[valid]
        if len(t_est) < 2:
            return
        order = np.argsort(t_est, kind="stable")
        t_est, q_est = t_est[order], q_est[order]
        # the vehicle's own attitude comes at tens of Hz: its own step sets the gap
        max_gap = 2.0 * float(np.median(np.diff(t_est))) + 1e-4
        est, ref = pairs_at_shift(t_est, q_est, t_ref, q_ref, 0.0, max_gap)
        e = metrics.attitude_errors(est, ref)
        keep = np.isfinite(e.total)
        sums = self._sums.setdefault(label, _Sums())
        sums.samples += int(keep.sum())
        sums.total += float(np.sum(e.total[keep] ** 2))
        sums.heading += float(np.sum(e.heading[keep] ** 2))
        sums.inclination += float(np.sum(e.inclination[keep] ** 2))

    def to_dict(self) -> dict[str, dict[str, float | int]]:
        """{label: total/heading/inclination RMS [deg] and samples} of what was scored."""
        return {label: s.to_dict() for label, s in self._sums.items() if s.samples}
