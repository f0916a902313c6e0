"""The `flight` profile flies like a quadrotor: thrust-pointed attitude, rotor drag,
PX4-like manoeuvres (sustained 3-5 m/s², 30-45° tilt, circles, yaw turns, landing)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimators import quat
from hil.environment import GRAVITY_NED, G
from hil.motion import make_profile
from hil.multirotor import FLIGHT_GROUND_S

DT = 0.01


@pytest.fixture(scope="module")
def flight():
    """Long enough for two cycles and the landing."""
    profile = make_profile("flight", 160.0)
    t = np.arange(0.0, 160.0, DT)
    return profile, profile.truth(t)


def tilt_deg(q: np.ndarray) -> np.ndarray:
    """Angle between body z and the vertical."""
    return np.degrees(np.arccos(np.clip(quat.to_dcm(q)[:, 2, 2], -1.0, 1.0)))


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) index pairs of the True stretches of a boolean array."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int), [0]])))
    return list(zip(edges[::2], edges[1::2], strict=True))


def test_jerk_is_the_derivative_of_the_acceleration():
    profile = make_profile("flight", 160.0)
    t = np.arange(0.0, 160.0, 0.01)
    h = 1e-5
    a_lo, a_hi = profile.plan(t - h)[2], profile.plan(t + h)[2]
    _, _, _, jerk, _, _ = profile.plan(t)
    assert np.abs(jerk).max() > 5.0  # the manoeuvres are not gentle
    assert np.allclose((a_hi - a_lo) / (2 * h), jerk, atol=2e-3)
    # yaw rate is the derivative of the yaw
    y_lo, y_hi = profile.plan(t - h)[4], profile.plan(t + h)[4]
    assert np.allclose((y_hi - y_lo) / (2 * h), profile.plan(t)[5], atol=1e-6)


def test_accelerometer_sees_thrust_and_rotor_drag(flight):
    """Specific force in the body: x/y are -mu times the body velocity (rotor drag),
    z is the thrust (always pushing up), and R f_b + g is the planned acceleration."""
    profile, truth = flight
    f = truth.specific_force()
    r = quat.to_dcm(truth.q)
    v_body = np.einsum("nji,nj->ni", r, truth.velocity_ned)
    mu = profile.drag_per_s
    assert mu == pytest.approx(0.4)
    assert np.allclose(f[:, :2], -mu * v_body[:, :2], atol=1e-9)
    assert np.all(f[:, 2] < -0.5 * G)
    assert np.allclose(np.einsum("nij,nj->ni", r, f) + GRAVITY_NED, truth.accel_ned, atol=1e-9)


def test_at_constant_velocity_it_leans_into_the_drag_and_reads_gravity(flight):
    profile, truth = flight
    speed = np.linalg.norm(truth.velocity_ned[:, :2], axis=1)
    cruise = (speed > 4.99) & (np.linalg.norm(truth.accel_ned, axis=1) < 1e-9)
    assert cruise.sum() * DT > 10.0  # the legs cruise at 5 m/s
    expected = math.degrees(math.atan(profile.drag_per_s * 5.0 / G))
    assert tilt_deg(truth.q[cruise]) == pytest.approx(np.full(cruise.sum(), expected), abs=0.05)
    # the accelerometer reads gravity rotated into the tilted body: |f| = g, and the
    # accelerometer's own tilt (atan2 of its components) is the body's tilt
    f = truth.specific_force()[cruise]
    assert np.allclose(np.linalg.norm(f, axis=1), G)
    acc_tilt = np.degrees(np.arccos(-f[:, 2] / G))
    assert np.allclose(acc_tilt, expected, atol=0.05)
    # without rotor drag the same cruise is level
    level = make_profile("flight", 160.0, drag_per_s=0.0).truth(truth.t[cruise])
    assert tilt_deg(level.q).max() < 1e-6


def test_holds_px4_like_accelerations_and_tilts(flight):
    _, truth = flight
    ah = np.linalg.norm(truth.accel_ned[:, :2], axis=1)
    held = [(b - a) * DT for a, b in runs((ah >= 3.0) & (ah <= 5.5))]
    # speeding up and braking on the legs, and the circles, hold 3-5.5 m/s² for > 1 s
    assert sum(d > 1.0 for d in held) >= 12  # 6 per cycle, 2 cycles
    tilt = tilt_deg(truth.q)
    assert 30.0 <= tilt.max() <= 45.0
    assert (tilt > 25.0).sum() * DT > 20.0  # seconds spent steeply tilted
    assert np.degrees(np.abs(truth.rates).max()) < 300.0  # a quadrotor, not a flip


def test_circles_hold_centripetal_acceleration(flight):
    _, truth = flight
    v = truth.velocity_ned[:, :2]
    a = truth.accel_ned[:, :2]
    speed = np.linalg.norm(v, axis=1)
    # centripetal part: the acceleration across the velocity
    across = np.abs(v[:, 0] * a[:, 1] - v[:, 1] * a[:, 0]) / np.maximum(speed, 1e-9)
    circling = runs((across > 4.5) & (speed > 5.0))
    longest = max(circling, key=lambda r: r[1] - r[0])
    assert (longest[1] - longest[0]) * DT > 8.0
    course = np.unwrap(np.arctan2(v[longest[0]:longest[1], 1], v[longest[0]:longest[1], 0]))
    assert np.degrees(course[-1] - course[0]) > 540.0  # laps, turning right
    # the nose follows the track
    yaw = np.unwrap(quat.to_euler(truth.q[longest[0]:longest[1]])[:, 2])
    assert np.allclose(yaw - yaw[0], course - course[0], atol=1e-6)


def test_ground_take_off_yaw_turns_and_landing(flight):
    profile, truth = flight
    ground = truth.t < FLIGHT_GROUND_S
    assert np.all(truth.position_ned[ground] == 0.0) and np.all(truth.rates[ground] == 0.0)
    assert np.allclose(truth.specific_force()[ground], [0.0, 0.0, -G])
    assert truth.position_ned[:, 2].min() == pytest.approx(-15.0)  # 10 m plus a 5 m climb
    yaw = np.unwrap(quat.to_euler(truth.q)[:, 2])
    assert np.degrees(np.abs(np.diff(yaw)).sum()) > 2 * 1000.0  # turns, circles, spins
    assert np.degrees(np.abs(truth.rates[:, 2]).max()) > 140.0  # the yaw spin
    # it lands: back on the ground at home, at rest
    end = truth.t > profile.land_start + 10.0
    assert end.any()
    assert np.allclose(truth.position_ned[end], 0.0, atol=1e-9)
    assert np.allclose(truth.specific_force()[end], [0.0, 0.0, -G])


def test_any_duration_repeats_whole_cycles_then_lands():
    short = make_profile("flight", 20.0)
    assert short.cycles == 1 and short.land_start > 20.0  # too short to land
    hour = make_profile("flight", 3600.0)
    landed = hour.land_start + hour.epilogue.end
    assert landed <= 3600.0 < landed + hour.cycle_length  # as many cycles as fit
    # one cycle later the vehicle is in the same state (the cycle is periodic)
    t = hour.cycle_start + np.array([3.0, 17.0, 40.0, 55.0])
    a, b = hour.truth(t), hour.truth(t + 40 * hour.cycle_length)
    assert np.allclose(a.position_ned, b.position_ned, atol=1e-9)
    assert np.allclose(a.rates, b.rates, atol=1e-9)
    assert np.max(np.degrees(quat.angle_between(a.q, b.q))) < 1e-6
    assert np.allclose(hour.truth(np.array([3599.0])).position_ned, 0.0)  # landed


def test_rotor_drag_must_be_sane():
    with pytest.raises(ValueError, match="drag"):
        make_profile("flight", 60.0, drag_per_s=-1.0)
