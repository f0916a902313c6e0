"""BROAD regression: the paper's published Mahony and Madgwick numbers on one dev trial.

Started like the BROAD example code (replay.broad.broad_example_init), Mahony with
Kp = 0.74, Ki = 0.0012 and Madgwick with beta = 0.12 plus the original code's
magnetometer quirk reproduce published_case_study.csv to ~0.0002°; 0.05° is far inside
what any real change to the filters moves (e.g. the quirk alone is ~1° on this trial,
a correct initial orientation for Mahony ~0.35°).
"""

from __future__ import annotations

import numpy as np
import pytest

import estimators
from estimators import quat as Q
from replay.broad import (
    PUBLISHED_MADGWICK,
    PUBLISHED_MAHONY,
    broad_example_init,
    load_published,
    load_trials,
    run_estimator,
    score,
)

TRIAL = "01_undisturbed_slow_rotation_A"
TOLERANCE_DEG = 0.05


@pytest.fixture(scope="module")
def trial(data_dir):
    broad = data_dir / "broad"
    [t] = [t for t in load_trials(broad) if t.name == TRIAL]
    return t, load_published(broad)


def _assert_matches(got, published) -> None:
    assert got.total_deg == pytest.approx(published.total_deg, abs=TOLERANCE_DEG)
    assert got.heading_deg == pytest.approx(published.heading_deg, abs=TOLERANCE_DEG)
    assert got.inclination_deg == pytest.approx(published.inclination_deg, abs=TOLERANCE_DEG)


def test_mahony_reproduces_published_numbers(trial):
    t, published = trial
    q0 = broad_example_init(t.acc[0], t.mag[0])
    _assert_matches(score(t, run_estimator("mahony", t, q0=q0, **PUBLISHED_MAHONY)),
                    published["mahony"][TRIAL])


def test_madgwick_with_original_quirk_reproduces_published_numbers(trial):
    t, published = trial
    q0 = broad_example_init(t.acc[0], t.mag[0])
    _assert_matches(score(t, run_estimator("madgwick", t, q0=q0, **PUBLISHED_MADGWICK)),
                    published["madgwick"][TRIAL])
    # The correct reference field is what the quirk is about: it does not reproduce them.
    correct = score(t, run_estimator("madgwick", t, q0=q0,
                                     **{**PUBLISHED_MADGWICK, "original_mag_quirk": False}))
    assert abs(correct.total_deg - published["madgwick"][TRIAL].total_deg) > 0.5


def test_broad_example_init_is_the_inverse_attitude_relative_to_south_east_up(trial):
    """Documents why the example code's start is off by degrees on these trials."""
    t, _ = trial
    correct = estimators.create("mahony", world="ENU").update(t.gyr[0], t.acc[0], t.mag[0])
    q_z90 = np.array([np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)])  # NWU -> ENU
    q_z180 = np.array([0.0, 0.0, 0.0, 1.0])
    sensor_to_nwu = Q.multiply(Q.conjugate(q_z90), correct)
    expected = Q.multiply(q_z90, Q.conjugate(Q.multiply(q_z180, sensor_to_nwu)))
    assert float(Q.angle_between(broad_example_init(t.acc[0], t.mag[0]), expected)) < 1e-9
    assert np.degrees(float(Q.angle_between(expected, correct))) > 1.0
