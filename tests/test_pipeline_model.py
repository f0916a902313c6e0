"""A vehicle model learned after the first samples (the autopilot's heartbeat comes after
its first IMU messages): the live estimate must be the one a replay of the same samples
gives, which knows the model from the start.

Before, the rebuilt estimators restarted and re-converged from whatever the
magnetometer said a second into the session; a PX4 flight's live heading then differed
from its replay's by up to 3° for seconds, which a real-autopilot test's live-vs-replay
check sometimes failed on.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from bridge.estimate import pipeline as P
from bridge.estimate.pipeline import SourcePipeline
from bridge.vehicle.imu_sample import ImuSample
from bridge.vehicle.ingest import SourceKey
from bridge.vehicle.model import MULTIROTOR, UNKNOWN
from estimators.spec import EstimatorSpec
from replay.synthetic import SyntheticConfig, generate

KEY = SourceKey(1, 1, 27, 0)
RATE_HZ = 200.0


def samples(seconds: float) -> list[ImuSample]:
    """A moving vehicle (replay.synthetic), as the bridge's ingest hands its samples on."""
    rec = generate(SyntheticConfig(duration_s=seconds, rate_hz=RATE_HZ, linear_acc=2.0))
    return [ImuSample(KEY, float(t), int(t * 1e3), 1.0 / RATE_HZ, g, a, m, 0.0)
            for t, g, a, m in zip(rec.t, rec.gyr, rec.acc, rec.mag, strict=True)]


def pipeline(model: str) -> SourcePipeline:
    specs = [EstimatorSpec.parse("eskf"), EstimatorSpec.parse("mahony")]
    return SourcePipeline(KEY, specs, RATE_HZ, 4096, math.radians(3.0), 0.5, model)


def run(src: SourcePipeline, given: list[ImuSample], model_at: int | None = None,
        airborne_at: int | None = None) -> list[np.ndarray]:
    """The primary's attitudes; the model becomes MULTIROTOR before sample ``model_at``,
    the vehicle airborne before ``airborne_at``."""
    out = []
    for k, s in enumerate(given):
        if k == model_at:
            src.set_model(MULTIROTOR)
        if k == airborne_at:
            src.set_flight_state(True)
        out.append(src.process(s).q.copy())
    return out


def test_a_model_learned_early_gives_the_estimate_of_a_model_known_from_the_start(caplog):
    given = samples(2.0)
    known = pipeline(MULTIROTOR)
    expected = run(known, given, airborne_at=150)
    learned = pipeline(UNKNOWN)
    with caplog.at_level(logging.INFO, logger="bridge.estimate.pipeline"):
        got = run(learned, given, model_at=100, airborne_at=150)
    assert [r.getMessage() for r in caplog.records] == [
        "vehicle 1: estimators rebuilt for a multirotor model, caught up on the 100 "
        "samples so far"]
    assert learned.estimators[0].params.drag == known.estimators[0].params.drag > 0.0
    assert learned.restarts == 0 and learned.caught_up == 1
    assert not learned.initialising  # nothing held: the estimate did not start over
    # every attitude from the model on, and every estimator's history (the live
    # comparison's), as if the model had been known from the first sample
    np.testing.assert_array_equal(np.array(got[100:]), np.array(expected[100:]))
    for label in known.labels:
        np.testing.assert_array_equal(learned.history[label].snapshot(-math.inf)[1],
                                      known.history[label].snapshot(-math.inf)[1])


def test_the_catch_up_gives_each_sample_the_flight_state_it_came_with():
    """Airborne from sample 50, model learned at 100: the rerun must switch the flight
    state where it switched, not run all of it airborne."""
    given = samples(1.0)
    known = pipeline(MULTIROTOR)
    expected = run(known, given, airborne_at=50)
    learned = pipeline(UNKNOWN)
    got = run(learned, given, model_at=100, airborne_at=50)
    np.testing.assert_array_equal(np.array(got[100:]), np.array(expected[100:]))
    wrong = pipeline(MULTIROTOR)
    wrong.set_flight_state(True)
    assert not np.array_equal(np.array(run(wrong, given)[100:]), np.array(got[100:]))


def test_a_model_learned_late_restarts_the_estimate_and_holds_it(monkeypatch, caplog):
    """Past CATCH_UP_S the samples are no longer kept: the rebuilt estimators start over
    from the next sample, held while they settle."""
    monkeypatch.setattr(P, "CATCH_UP_S", 0.5)
    given = samples(1.5)
    src = pipeline(UNKNOWN)
    run(src, given[:150])
    with caplog.at_level(logging.INFO, logger="bridge.estimate.pipeline"):
        src.set_model(MULTIROTOR)
    assert "multirotor model; the estimate restarts" in caplog.text
    est = src.process(given[150])
    assert src.restarts == 1 and src.caught_up == 0
    assert est.initialising
    assert src.estimators[0].params.drag > 0.0
    # after the restart the samples are kept again: a second change catches up
    run(src, given[151:170])
    src.set_model(UNKNOWN)
    assert src.caught_up == 1 and src.restarts == 1


@pytest.mark.parametrize("cap", [10, 120])
def test_the_kept_samples_are_bounded_by_count(monkeypatch, cap):
    monkeypatch.setattr(P, "CATCH_UP_SAMPLES", cap)
    src = pipeline(UNKNOWN)
    run(src, samples(1.0))
    src.set_model(MULTIROTOR)
    src.process(samples(1.01)[-1])
    assert src.caught_up == 0 and src.restarts == 1
