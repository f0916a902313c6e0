"""Time cleanup, reference interpolation, lag and convergence against known answers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from estimators import quat as Q
from replay.align import estimate_lag, reference_at
from replay.dataset import Reference
from replay.evaluate import convergence_time
from replay.synthetic import SyntheticConfig, truth_attitude
from replay.timebase import monotonic_mask, sample_and_hold


def test_monotonic_mask_drops_and_counts():
    t = np.array([0.0, 1.0, 1.0, 2.0, 1.5, 3.0, np.nan, 2.5, 4.0])
    keep, c = monotonic_mask(t)
    assert list(t[keep]) == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert (c.duplicates, c.backwards, c.non_finite, c.kept) == (1, 2, 1, 5)


def test_sample_and_hold_uses_last_reading():
    held = sample_and_hold(np.array([1.0, 2.0]), np.array([[1.0] * 3, [2.0] * 3]),
                           np.array([0.5, 1.0, 1.5, 2.0, 9.0]))
    assert np.isnan(held[0]).all()
    assert list(held[1:, 0]) == [1.0, 1.0, 2.0, 2.0]


def test_slerp_matches_scipy_and_gaps_are_nan():
    rng = np.random.default_rng(0)
    t_ref = np.cumsum(rng.uniform(0.01, 0.05, 40))
    t_ref[20:] += 2.0  # a 2 s gap: longer than the 1 s default
    q = Rotation.random(40, random_state=1)
    ref = Reference(t=t_ref, q=q.as_quat()[:, [3, 0, 1, 2]], kind="truth", source="test")
    t = np.linspace(t_ref[0] - 0.1, t_ref[-1] + 0.1, 500)
    got = reference_at(ref, t)
    inside = (t >= t_ref[0]) & (t <= t_ref[-1]) & ~((t > t_ref[19]) & (t < t_ref[20]))
    assert np.array_equal(np.all(np.isfinite(got), axis=1), inside)
    want = Slerp(t_ref, q)(t[inside]).as_quat()[:, [3, 0, 1, 2]]
    assert Q.angle_between(got[inside], want).max() < 1e-9


def test_lag_of_a_delayed_copy():
    cfg = SyntheticConfig(duration_s=30.0, rate_hz=200.0)
    t, q = truth_attitude(cfg)
    delay = 40  # samples = 0.2 s
    est = np.vstack([np.repeat(q[:1], delay, axis=0), q[:-delay]])
    assert estimate_lag(t, est, q) == pytest.approx(0.2, abs=0.5 / cfg.rate_hz)
    assert estimate_lag(t, q, est) == pytest.approx(-0.2, abs=0.5 / cfg.rate_hz)
    still = np.tile([1.0, 0, 0, 0], (len(t), 1))
    assert np.isnan(estimate_lag(t, still, still))  # nothing moves: not observable


def test_convergence_time():
    t = np.arange(0, 10, 0.01)
    err = np.where(t < 3.0, 20.0, 1.0)
    err[(t > 3.2) & (t < 3.3)] = 9.0  # a blip before it settles
    assert convergence_time(t, err) == pytest.approx(3.3, abs=0.011)
    assert np.isnan(convergence_time(t, np.full_like(t, 30.0)))
