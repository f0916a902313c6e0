"""Rows beside the online estimators: the eskf smoothed over the whole recording
(``replay --smooth``) and the autopilot's own attitude.

The smoothed eskf (``estimators.smooth``) sees every sample before and after each
moment: the best attitude the data allows, to judge the online filters and the
autopilot after the flight. Against a truth it is scored like any estimator. A log
without a truth (a real flight) can only be scored against something that is not the
truth: then every online estimator and the autopilot's own attitude are also scored
against the smoothed eskf, labelled as such (``Evaluation.vs_smoothed``), never as truth.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

import estimators
from estimators.spec import EstimatorSpec

from .align import reference_at
from .evaluate import (
    Prepared,
    Run,
    Score,
    aiding_kwargs,
    autopilot_gap,
    flight_kwargs,
    placed,
    run_inputs,
    score,
)

SMOOTHED = " smoothed"  # label suffix of a smoothed run
AUTOPILOT = "autopilot"  # label of the autopilot's own attitude as a score row


def smoothed_run(prep: Prepared, spec: EstimatorSpec, init: str = "sensors") -> Run:
    """The estimator of ``spec`` (eskf) forward, then smoothed back, over the recording."""
    rec = prep.recording
    sl, q0, params = run_inputs(prep, spec, init)
    began = time.perf_counter()
    try:
        res = estimators.smooth(spec.name, rec.gyr[sl], rec.acc[sl],
                                None if rec.mag is None else rec.mag[sl],
                                rate_hz=rec.rate_hz, world=rec.world, q0=q0, dt=rec.dt[sl],
                                **aiding_kwargs(prep, sl), **flight_kwargs(prep, sl),
                                **params)
    except np.linalg.LinAlgError as exc:  # a forward pass whose covariance blew up
        raise ValueError(f"--smooth ({spec.label}): the forward filter's covariance is not "
                         f"usable for smoothing ({exc})") from None
    seconds = time.perf_counter() - began
    out = estimators.BatchResult(q=res.q, bias=res.bias, flags=res.online.flags)
    return placed(prep, spec, sl, out, res.counters, seconds)


def autopilot_attitude(prep: Prepared) -> np.ndarray | None:
    """The autopilot's own attitude on the IMU clock (None when the log has none)."""
    rec = prep.recording
    if rec.reference is not None and rec.reference.kind == "autopilot":
        return prep.q_ref
    if rec.autopilot is None:
        return None
    return reference_at(rec.autopilot, rec.t)


def autopilot_run(prep: Prepared) -> Run | None:
    """The autopilot's attitude as a run to score (only when the reference is another
    kind: against itself it would score zero)."""
    rec = prep.recording
    if rec.reference is None or rec.reference.kind == "autopilot" or rec.autopilot is None:
        return None
    q = reference_at(rec.autopilot, rec.t)
    return Run(EstimatorSpec("autopilot"), q, np.zeros(rec.n, dtype=np.uint8),
               np.full((rec.n, 3), np.nan), estimators.SampleCounters(), 0.0)


def against_smoothed(prep: Prepared, runs: dict[str, Run], smoothed: Run
                     ) -> dict[str, Score]:
    """Every other run and the autopilot's attitude scored against the smoothed one."""
    base = _smoothed_base(prep, smoothed)
    out = {label: score(base, run) for label, run in runs.items() if run is not smoothed}
    own = autopilot_attitude(prep)
    if own is not None:
        run = Run(EstimatorSpec("autopilot"), own, np.zeros(len(own), dtype=np.uint8),
                  np.full((len(own), 3), np.nan), estimators.SampleCounters(), 0.0)
        out[AUTOPILOT] = score(base, run, six_d=False, unscored=autopilot_gap(prep))
    return out


def against_smoothed_extra(prep: Prepared, smoothed: Run,
                           others: dict[str, tuple[Run, bool]]) -> dict[str, Score]:
    """Attitudes that are no estimator of ours (``replay --compare``'s reference
    filters), each given with its ``six_d``, scored against the smoothed run."""
    base = _smoothed_base(prep, smoothed)
    return {label: score(base, run, six_d=six_d) for label, (run, six_d) in others.items()}


def _smoothed_base(prep: Prepared, smoothed: Run) -> Prepared:
    """``prep`` with the smoothed attitude as its reference, scored where it exists."""
    ok = np.all(np.isfinite(smoothed.q), axis=1)
    if prep.recording.score_mask is not None:
        ok &= prep.recording.score_mask
    return dataclasses.replace(prep, q_ref=smoothed.q, scored=ok, unscored="")
