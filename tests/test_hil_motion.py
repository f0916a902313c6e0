"""Motion truth is self-consistent: rates integrate to the attitude, derivatives match."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimators import quat
from hil.environment import Environment, G
from hil.motion import TILT_PITCH_DEG, TILT_ROLL_DEG, make_profile


def integrate_rates(profile, t_end: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Attitude from the truth's body rates alone (midpoint rule), and the truth at t_end."""
    t = np.arange(0.0, t_end, dt)
    mid = profile.truth(t + 0.5 * dt).rates
    steps = quat.from_rotvec(mid * dt)
    q = profile.truth(np.array([0.0])).q[0]
    for step in steps:
        q = quat.multiply(q, step)
    return q, profile.truth(np.array([t[-1] + dt])).q[0]


@pytest.mark.parametrize("name", ["static", "tilt", "flight", "gentle", "aggressive"])
def test_integrating_true_rates_reproduces_true_attitude(name):
    profile = make_profile(name, 40.0)
    q, truth = integrate_rates(profile, 40.0, 1e-3)
    assert math.degrees(quat.angle_between(q, truth)) < 1e-3


def test_file_profile_rates_reproduce_the_file(tmp_path):
    """A CSV recorded from the flight profile replays with exact, consistent rates."""
    flight = make_profile("flight", 20.0)
    t = np.arange(0.0, 20.0, 0.01)
    q = flight.truth(t).q * np.where(np.arange(len(t)) % 7 == 0, -1.0, 1.0)[:, None]  # any sign
    path = tmp_path / "truth.csv"
    lines = ["# recorded truth", "time_s,qw,qx,qy,qz"]
    lines += [f"{a + 100.0:.4f},{w:.17g},{x:.17g},{y:.17g},{z:.17g}"
              for a, (w, x, y, z) in zip(t, q, strict=True)]
    path.write_text("\n".join(lines))
    replay = make_profile(f"file:{path}")
    got = replay.truth(t)
    assert np.max(np.degrees(quat.angle_between(got.q, flight.truth(t).q))) < 1e-9
    q_int, truth = integrate_rates(replay, 19.99, 1e-3)
    assert math.degrees(quat.angle_between(q_int, truth)) < 1e-6
    # piecewise-constant rates follow the smooth ones closely at 100 Hz
    err = np.abs(replay.truth(t[:-1] + 0.005).rates - flight.truth(t[:-1] + 0.005).rates)
    assert np.max(err) < math.radians(1.0)
    # after the last row it holds still
    after = replay.truth(np.array([25.0]))
    assert np.all(after.rates == 0.0)


@pytest.mark.parametrize(("text", "why"), [
    ("time_s,qw,qx,qy\n0,1,0,0\n1,1,0,0", "header"),
    ("time_s,qw,qx,qy,qz\n0,1,0,0,0", "2 rows"),
    ("time_s,qw,qx,qy,qz\n0,1,0,0,0\n0,1,0,0,0", "increasing"),
    ("time_s,qw,qx,qy,qz\n0,1,0,0,0\n1,0,0,0,0", "zero-length"),
    ("time_s,qw,qx,qy,qz\n0,1,0,0,0\n1,nan,0,0,0", "finite"),
    ("time_s,qw,qx,qy,qz\n0,1,0,0,0\n1,x,0,0,0", "non-numeric"),
])
def test_file_profile_rejects_bad_files(tmp_path, text, why):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=why):
        make_profile(f"file:{path}")


def test_unknown_profile_and_missing_file():
    with pytest.raises(ValueError, match="static"):
        make_profile("loop-the-loop")
    with pytest.raises(ValueError, match="cannot read"):
        make_profile("file:/nonexistent/truth.csv")


def test_static_and_tilt_specific_force():
    level = make_profile("static").truth(np.array([0.0, 5.0]))
    assert np.allclose(level.specific_force(), [0.0, 0.0, -G])
    tilt = make_profile("tilt").truth(np.array([1.0]))
    roll, pitch, _ = np.degrees(quat.to_euler(tilt.q[0]))
    assert roll == pytest.approx(TILT_ROLL_DEG) and pitch == pytest.approx(TILT_PITCH_DEG)
    f = tilt.specific_force()[0]
    # accelerometer tilt: roll = atan2(-fy, -fz), pitch = asin(fx / g)
    assert math.degrees(math.atan2(-f[1], -f[2])) == pytest.approx(TILT_ROLL_DEG)
    assert math.degrees(math.asin(f[0] / G)) == pytest.approx(TILT_PITCH_DEG)


@pytest.mark.parametrize("name", ["flight", "gentle", "aggressive"])
def test_position_velocity_acceleration_are_derivatives(name):
    profile = make_profile(name, 30.0)
    dt = 1e-5  # the jerk steps at ramp ends limit a central difference to O(jerk * dt)
    t = np.arange(0.0, 30.0, 0.01)
    a, b = profile.truth(t - dt), profile.truth(t + dt)
    mid = profile.truth(t)
    assert np.allclose((b.position_ned - a.position_ned) / (2 * dt), mid.velocity_ned, atol=1e-5)
    assert np.allclose((b.velocity_ned - a.velocity_ned) / (2 * dt), mid.accel_ned, atol=1e-4)


def test_gentle_takes_off_and_manoeuvres():
    truth = make_profile("gentle", 60.0).truth(np.arange(0.0, 60.0, 0.01))
    euler = np.degrees(quat.to_euler(truth.q))
    assert truth.position_ned[:, 2].min() < -14.0  # take-off to 10 m plus a 5 m climb
    assert np.ptp(euler[:, 0]) > 40.0 and np.ptp(euler[:, 1]) > 30.0
    assert np.ptp(np.unwrap(np.radians(euler[:, 2]))) > math.radians(170.0)


def test_aggressive_flips_through_both_vertical_pitches():
    truth = make_profile("aggressive", 12.0).truth(np.arange(0.0, 13.0, 0.001))
    pitch = np.degrees(quat.to_euler(truth.q)[:, 1])
    assert pitch.max() > 89.0 and pitch.min() < -89.0
    assert np.degrees(np.abs(truth.rates).max()) < 2000.0  # inside the gyro range


def test_earth_field_direction():
    env = Environment(field_ut=50.0, inclination_deg=65.0, declination_deg=3.0)
    b = env.field_ned_gauss()
    assert np.linalg.norm(b) == pytest.approx(0.5)
    assert math.degrees(math.atan2(b[2], math.hypot(b[0], b[1]))) == pytest.approx(65.0)
    assert math.degrees(math.atan2(b[1], b[0])) == pytest.approx(3.0)
    with pytest.raises(ValueError):
        Environment(field_ut=0.0, inclination_deg=65.0, declination_deg=3.0)
    with pytest.raises(ValueError, match="together"):
        Environment(declination_deg=3.0)  # a field is given whole or not at all
    with pytest.raises(ValueError, match="home"):
        Environment(latitude_deg=95.0)


def test_default_field_is_the_world_magnetic_model_at_home():
    """The emulated compass sees the WMM field at its home position and date."""
    from bridge.app.emulator import emulator_declination_deg
    from imu import geomag

    env = Environment()
    wmm = geomag.field_at(env.latitude_deg, env.longitude_deg, env.ground_altitude_m, env.date)
    b = env.field_ned_gauss()
    assert b * 1e5 == pytest.approx(np.array([wmm.north_nt, wmm.east_nt, wmm.down_nt]), rel=1e-9)
    assert env.magnetic_declination_deg == pytest.approx(wmm.declination_deg)
    assert emulator_declination_deg() == pytest.approx(wmm.declination_deg)
    # another place, another field: Sydney's declination is ~13° east, dip upwards
    sydney = Environment(latitude_deg=-33.87, longitude_deg=151.21, ground_altitude_m=20.0)
    assert sydney.magnetic_declination_deg > 10.0 and sydney.field_ned_gauss()[2] < 0.0


def test_geodetic_position_of_offsets_from_home():
    env = Environment()
    lat, lon, alt = env.geodetic(np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0],
                                           [0.0, 1000.0, -10.0]]))
    assert (lat[0], lon[0], alt[0]) == (env.latitude_deg, env.longitude_deg, 488.0)
    # 1 km north is ~0.00899° of latitude at 47°N (WGS-84 meridian radius 6.367e6 m)
    assert lat[1] - lat[0] == pytest.approx(0.008993, abs=2e-6)
    assert lon[2] - lon[0] == pytest.approx(0.013254, abs=2e-5)
    assert alt[2] == pytest.approx(498.0)
