"""Gyro-only integrators (euler, dcm, quaternion) against closed-form rotations.

A rate ω constant in the body frame for time t gives exactly ``q(t) = q0 ⊗ exp(ω·t/2)``.
The expected errors of the approximate steps are derived, not measured:

* first-order quaternion step, renormalised: ``q ⊗ (1, ω·dt/2)/|·|`` is a rotation about
  the same axis by ``2·atan(|ω|·dt/2)``, so N steps rotate by ``N·2·atan(|ω|dt/2)``;
* first-order DCM step about one body axis: ``I + [v×]`` then has orthogonal columns of
  norms (√(1+a²), √(1+a²), 1), so re-orthonormalisation leaves a rotation by ``atan(a)``;
* Euler-angle ODE: for a single-axis rate from level the equation is linear in the angle
  that moves (φ̇ = p, θ̇ = q or ψ̇ = r), so forward Euler is exact; for a general rate it
  is a first-order method, so halving dt halves the error.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

import estimators
from estimators import quat as Q

AXES = {"x": np.array([1.0, 0.0, 0.0]), "y": np.array([0.0, 1.0, 0.0]),
        "z": np.array([0.0, 0.0, 1.0])}


def _gyro_only(name: str, rate_hz: float, w: np.ndarray, seconds: float,
               q0: np.ndarray, **params: float) -> tuple[estimators.Estimator, np.ndarray]:
    """Constant body rate, accelerometer unusable (NaN) so nothing but the gyro acts."""
    n = round(seconds * rate_hz)
    est = estimators.create(name, rate_hz=rate_hz, q0=q0, **params)
    result = est.run(np.tile(w, (n, 1)), np.full((n, 3), np.nan))
    return est, result.q


def _exact(q0: np.ndarray, w: np.ndarray, t: np.ndarray) -> np.ndarray:
    return Q.multiply(q0, Q.from_rotvec(np.outer(t, w)))


Q_START = Q.from_euler(0.3, -0.4, 2.0)  # a generic attitude, not the identity


@pytest.mark.parametrize("axis", AXES)
@pytest.mark.parametrize("name, params", [("quaternion", {"exact": True}),
                                          ("dcm", {"exact": True})])
def test_exact_steps_follow_constant_rate(name, params, axis):
    w = 2.5 * AXES[axis]
    rate = 200.0
    _, q = _gyro_only(name, rate, w, 2.0, Q_START, **params)
    t = np.arange(1, len(q) + 1) / rate
    assert Q.angle_between(q, _exact(Q_START, w, t)).max() < 1e-10


@pytest.mark.parametrize("axis", AXES)
def test_first_order_quaternion_angle_is_2atan_half_step(axis):
    w, rate, seconds = 3.0 * AXES[axis], 100.0, 2.0
    _, q = _gyro_only("quaternion", rate, w, seconds, Q_START, exact=False)
    n = np.arange(1, len(q) + 1)
    step_angle = 2.0 * math.atan(3.0 / rate / 2.0)
    expected = Q.multiply(Q_START, Q.from_rotvec(np.outer(n * step_angle, AXES[axis])))
    assert Q.angle_between(q, expected).max() < 1e-10
    # ... which lags the true rotation by N·(ω·dt − 2·atan(ω·dt/2)) ≈ N·(ω·dt)³/12.
    lag = Q.angle_between(q[-1], _exact(Q_START, w, np.array([seconds]))[0])
    assert lag == pytest.approx(len(q) * (3.0 / rate - step_angle), rel=1e-6)
    assert lag > 1e-5  # the first-order step really is different from the exact one


def test_first_order_quaternion_general_axis():
    """The 2·atan rule holds for any constant axis, not only the coordinate axes."""
    w, rate = np.array([1.0, -2.0, 0.5]), 100.0
    _, q = _gyro_only("quaternion", rate, w, 1.5, Q_START, exact=False)
    n = np.arange(1, len(q) + 1)
    norm = np.linalg.norm(w)
    angle = n * 2.0 * math.atan(norm / rate / 2.0)
    expected = Q.multiply(Q_START, Q.from_rotvec(np.outer(angle, w / norm)))
    assert Q.angle_between(q, expected).max() < 1e-10


@pytest.mark.parametrize("axis", AXES)
def test_first_order_dcm_angle_is_atan_step(axis):
    w, rate = 3.0 * AXES[axis], 100.0
    est, q = _gyro_only("dcm", rate, w, 2.0, Q_START, exact=False)
    n = np.arange(1, len(q) + 1)
    expected = Q.multiply(Q_START,
                          Q.from_rotvec(np.outer(n * math.atan(3.0 / rate), AXES[axis])))
    assert Q.angle_between(q, expected).max() < 1e-10
    r = est.dcm
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-14)
    assert np.allclose(r, Q.to_dcm(q[-1]), atol=1e-12)


def test_dcm_stays_orthonormal_under_long_first_order_steps():
    """0.2 rad steps about a general axis v = ω·dt = (0.08, -0.14, 0.12): I + [v×] has
    Gram matrix (1 + |v|²)I − vvᵀ, so unit columns have |x·y| ≤ max|v_i v_j| = 0.0168, and
    the error split leaves at most 0.0168³/4 = 1.2e-6; z is exactly orthogonal to both."""
    est, q = _gyro_only("dcm", 50.0, np.array([4.0, -7.0, 6.0]), 20.0, Q_START, exact=False)
    r = est.dcm
    gram = r.T @ r
    assert np.allclose(np.diag(gram), 1.0, atol=1e-14)
    assert abs(gram[0, 1]) < 0.0168**3 / 4.0
    assert abs(gram[0, 2]) < 1e-14 and abs(gram[1, 2]) < 1e-14
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-5)
    assert np.all(np.isfinite(q))


@pytest.mark.parametrize("axis", AXES)
def test_euler_single_axis_from_level_is_exact(axis):
    """x: roll wraps through ±180°; y: pitch stops at 57°, clear of gimbal lock; z: yaw."""
    w, rate = 1.0 * AXES[axis], 100.0
    if axis != "y":
        w = 4.0 * AXES[axis]
    est, q = _gyro_only("euler", rate, w, 1.0, Q.identity())
    t = np.arange(1, len(q) + 1) / rate
    assert Q.angle_between(q, _exact(Q.identity(), w, t)).max() < 1e-10
    assert est.gimbal_lock_steps == 0
    angles = est.euler
    expected = Q.to_euler(_exact(Q.identity(), w, np.array([1.0]))[0])
    assert np.allclose(angles, expected, atol=1e-10)


def test_euler_general_rate_is_first_order():
    """The forward-Euler step on a coupled rate: error ∝ dt (halving dt halves it)."""
    w = np.array([0.3, 0.2, 1.0])
    errors = []
    for rate in (250.0, 500.0, 1000.0):
        _, q = _gyro_only("euler", rate, w, 2.0, Q.identity())
        errors.append(Q.angle_between(q[-1], _exact(Q.identity(), w, np.array([2.0]))[0]))
    for coarse, fine in itertools.pairwise(errors):
        assert 1.8 < coarse / fine < 2.2
    assert errors[-1] < 1e-3  # and the constant is modest: < 0.06° after 2 s at 1 kHz


# --- passage through ±90° pitch ---------------------------------------------------------

@pytest.mark.parametrize("name", ["quaternion", "dcm"])
def test_singularity_free_integrators_pass_through_vertical(name):
    w, rate = np.array([0.0, 2.0, 0.0]), 1000.0  # pitch 0 -> 180° over pi/2 s
    _, q = _gyro_only(name, rate, w, math.pi / 2.0, Q.identity())
    t = np.arange(1, len(q) + 1) / rate
    assert Q.angle_between(q, _exact(Q.identity(), w, t)).max() < 1e-10


def test_euler_pure_pitch_through_vertical_is_exact_and_flagged():
    """Pure pitch rate from level: the ODE part is exact (θ̇ = q) and so is the quaternion
    step used inside the band, so the whole flip is exact. Steps are taken on the
    quaternion exactly while |cos θ| < sin(margin) at the step's start."""
    rate, w = 1000.0, np.array([0.0, 2.0, 0.0])
    margin = math.radians(5.0)
    n = round(math.pi / 2.0 * rate)
    est = estimators.create("euler", rate_hz=rate, q0=Q.identity(), gimbal_margin=margin)
    locked = np.zeros(n, dtype=bool)
    q = np.empty((n, 4))
    for i in range(n):
        q[i] = est.update(w, [np.nan] * 3)
        locked[i] = est.in_gimbal_lock
    t = np.arange(1, n + 1) / rate
    assert np.all(np.isfinite(q))
    assert Q.angle_between(q, _exact(Q.identity(), w, t)).max() < 1e-9
    pitch_at_step_start = np.arange(n) * 2.0 / rate  # unwrapped pitch angle
    expected_locked = np.abs(np.cos(pitch_at_step_start)) < math.sin(margin)
    # No step starts within rounding distance of the band edge, so the count is exact.
    assert np.min(np.abs(np.abs(np.cos(pitch_at_step_start)) - math.sin(margin))) > 1e-6
    assert np.array_equal(locked, expected_locked)
    assert est.gimbal_lock_steps == expected_locked.sum() > 0
    # After the flip the angles are the canonical set (roll ±180°, pitch ≈ 0, yaw ±180°).
    roll, pitch, yaw = est.euler
    assert abs(abs(roll) - math.pi) < 1e-9 and abs(abs(yaw) - math.pi) < 1e-9
    assert pitch == pytest.approx(math.pi - n * 2.0 / rate, abs=1e-9)


@pytest.mark.parametrize("w, q0", [
    (np.array([0.3, 2.0, -0.4]), Q.identity()),  # climbs through +90° with coupling
    (np.array([0.3, 1.0, 0.4]), Q.from_euler(0.0, math.pi / 2.0, 0.0)),  # starts locked
])
def test_euler_coupled_passage_stays_finite_and_first_order(w, q0):
    errors = []
    for rate in (500.0, 1000.0):
        est, q = _gyro_only("euler", rate, w, 2.0, q0)
        assert np.all(np.isfinite(q))
        assert np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
        assert est.gimbal_lock_steps > 0
        t = np.arange(1, len(q) + 1) / rate
        errors.append(Q.angle_between(q, _exact(q0, w, t)).max())
    # Forward Euler stays first order through the band (error halves with dt).
    assert 1.8 < errors[0] / errors[1] < 2.2


def test_euler_exactly_vertical_start_extracts_finite_angles():
    est = estimators.create("euler", q0=Q.from_euler(0.0, -math.pi / 2.0, 0.7))
    _, pitch, _ = est.euler  # before any step: from q0
    assert pitch == pytest.approx(-math.pi / 2.0, abs=1e-7)
    est.update([0.0, 0.0, 0.0], [np.nan] * 3)
    assert est.in_gimbal_lock
    assert np.all(np.isfinite(est.euler))
    assert Q.angle_between(est.q, Q.from_euler(0.0, -math.pi / 2.0, 0.7))[()] < 1e-7


def test_euler_long_step_over_vertical_folds_angles_back():
    """One 0.5 s step at 4 rad/s from pitch 80° lands at 'pitch 194°': the angles are folded
    to the canonical range and the attitude is still the exact one for pure pitch."""
    q0 = Q.from_euler(0.0, math.radians(80.0), 0.0)
    est = estimators.create("euler", q0=q0, gimbal_margin=math.radians(1.0))
    q = est.update([0.0, 4.0, 0.0], [np.nan] * 3, dt=0.5)
    assert not est.in_gimbal_lock
    roll, pitch, yaw = est.euler
    assert -math.pi / 2.0 <= pitch <= math.pi / 2.0
    assert -math.pi < roll <= math.pi and -math.pi < yaw <= math.pi
    assert Q.angle_between(q, _exact(q0, np.array([0.0, 4.0, 0.0]), np.array([0.5]))[0]) < 1e-12


@pytest.mark.parametrize("bad", [0.0, math.pi / 2.0, -0.1, float("inf")])
def test_euler_rejects_invalid_margin(bad):
    with pytest.raises(ValueError, match="gimbal_margin"):
        estimators.create("euler", gimbal_margin=bad)


def test_integrators_start_from_first_accelerometer_sample():
    """q0=None: the integrators take their initial attitude from the first usable sample
    (here pitched 30° nose-up with a field giving yaw 50°) and then integrate from it."""
    truth = Q.from_euler(0.0, math.radians(30.0), math.radians(50.0))
    acc = Q.rotate(Q.conjugate(truth), np.array([0.0, 0.0, -9.81]))
    mag = Q.rotate(Q.conjugate(truth), np.array([0.4, 0.0, 0.3]))
    w = np.array([0.0, 0.5, 0.0])  # pure pitch from roll 0: exact for all three
    for name in ("euler", "dcm", "quaternion"):
        est = estimators.create(name, rate_hz=100.0)
        first = est.update(w, acc, mag)
        assert Q.angle_between(first, truth) < 1e-12
        q = est.run(np.tile(w, (100, 1)), np.full((100, 3), np.nan), np.tile(mag, (100, 1))).q
        expected = _exact(truth, w, np.array([1.0]))[0]
        assert Q.angle_between(q[-1], expected) < 1e-9
