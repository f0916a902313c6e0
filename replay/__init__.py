"""Offline evaluation: read logs and datasets, replay estimators, score, plot and tune.

    from replay import load, evaluate
    rec = load("flight.ulg")                 # -> Recording (IMU + reference, own time bases)
    result = evaluate(rec, ["mahony:kp=1.0"])
    result.scores["mahony:kp=1.0"].total_deg

The command line (``attitude-bridge replay`` / ``tune``) lives in ``replay.cli``.
"""

from __future__ import annotations

from estimators.spec import EstimatorSpec

from .dataset import Recording, Reference, ReplayInputError, TimeCleanup
from .evaluate import Evaluation, Score, evaluate
from .readers import load

__all__ = [
    "EstimatorSpec", "Evaluation", "Recording", "Reference", "ReplayInputError", "Score",
    "TimeCleanup", "evaluate", "load",
]
