"""The emulator's optional GPS: u-blox-like noise, ~100 ms late, on a real UDP link."""

from __future__ import annotations

import asyncio
import math
from dataclasses import replace

import numpy as np
import pytest
from hil_support import Receiver

from hil import Emulator, EmulatorConfig, GpsConfig, simulate
from hil.gps import GpsReceiver
from hil.motion import make_profile

GPS = GpsConfig(rate_hz=10.0, latency_s=0.1)
CFG = EmulatorConfig(profile="flight", rate_hz=250.0, duration_s=12.0, seed=4, gps=GPS,
                     fast=True)


@pytest.fixture(scope="module")
def sim():
    return simulate(CFG)


@pytest.fixture(scope="module")
def wire():
    rx = Receiver.open()

    async def run() -> None:
        loop = asyncio.get_running_loop()
        rx.attach(loop)
        try:
            await Emulator(CFG).run([("127.0.0.1", rx.port)])
            await asyncio.sleep(0.05)
        finally:
            rx.detach(loop)

    asyncio.run(run())
    return rx


def test_rate_and_latency_in_simulate(sim):
    assert len(sim.gps_t_s) == pytest.approx(12.0 * 10.0, abs=1)
    assert np.allclose(np.diff(sim.gps_t_s), 0.1)
    assert np.allclose(sim.gps_sent_t_s - sim.gps_t_s, 0.1)
    # stamped on the board clock at the instant it is valid for (2 s after boot first)
    assert np.array_equal(sim.gps_time_us, 2_000_000 + np.round(sim.gps_t_s * 1e6))


def test_velocity_noise_and_the_aiding_arrays(sim):
    err = sim.gps_vel_ned - sim.gps_truth_vel_ned
    assert np.std(err[:, :2]) == pytest.approx(GPS.vel_noise_h_mps, rel=0.15)
    assert np.std(err[:, 2]) == pytest.approx(GPS.vel_noise_v_mps, rel=0.15)
    vel, age = sim.gps_aiding()
    rows = np.flatnonzero(~np.isnan(vel[:, 0]))
    assert len(rows) == len(sim.gps_t_s)
    # given at the first IMU sample at or after sending, aged from the board stamps
    assert np.all(age[rows] >= 0.1 - 1e-9) and np.all(age[rows] < 0.1 + 1.0 / 250.0)
    assert np.array_equal(vel[rows], sim.gps_vel_ned)


def test_position_noise_wanders_slowly():
    """Position error: configured size, correlated over tens of seconds (not white)."""
    cfg = GpsConfig(rate_hz=5.0, pos_noise_h_m=0.7, pos_noise_v_m=1.0, pos_correlation_s=20.0)
    gps = GpsReceiver(cfg, make_profile("static"), np.random.default_rng(1))
    fixes = gps.fixes_until(4000.0, lambda t: np.round(t * 1e6).astype(np.int64))
    err = fixes.pos_ned  # the vehicle sits at home
    assert np.std(err[:, :2]) == pytest.approx(0.7, rel=0.15)
    assert np.std(err[:, 2]) == pytest.approx(1.0, rel=0.2)
    lag1 = np.corrcoef(err[1:, 0], err[:-1, 0])[0, 1]
    assert lag1 == pytest.approx(math.exp(-1.0 / (5.0 * 20.0)), abs=0.01)
    vel_lag1 = np.corrcoef(fixes.vel_ned[1:, 0], fixes.vel_ned[:-1, 0])[0, 1]
    assert abs(vel_lag1) < 0.05  # Doppler velocity noise is white


def test_gps_messages_on_the_wire(sim, wire):
    raw = wire.of_type("GPS_RAW_INT")
    local = wire.of_type("LOCAL_POSITION_NED")
    glob = wire.of_type("GLOBAL_POSITION_INT")
    assert len(raw) == len(local) == len(glob) == len(sim.gps_t_s)
    assert [m.time_usec for m in raw] == sim.gps_time_us.tolist()
    assert [m.time_boot_ms for m in local] == (sim.gps_time_us // 1000).tolist()
    # LOCAL_POSITION_NED carries exactly the recorded measurement
    assert np.array_equal(np.array([[m.vx, m.vy, m.vz] for m in local]), sim.gps_vel_ned)
    assert np.array_equal(np.array([[m.x, m.y, m.z] for m in local]), sim.gps_pos_ned)
    env = CFG.environment
    lat, lon, alt = env.geodetic(sim.gps_pos_ned)
    assert all(m.fix_type == 3 and m.satellites_visible >= 6 for m in raw)
    assert np.array_equal([m.lat for m in raw], np.round(lat * 1e7))
    assert np.array_equal([m.lon for m in glob], np.round(lon * 1e7))
    assert np.array_equal([m.alt for m in raw], np.round(alt * 1e3))
    ground = np.hypot(sim.gps_vel_ned[:, 0], sim.gps_vel_ned[:, 1])
    assert np.allclose([m.vel / 100 for m in raw], ground, atol=0.006)
    moving = ground > 2.0
    cog = np.degrees(np.arctan2(sim.gps_vel_ned[:, 1], sim.gps_vel_ned[:, 0])) % 360
    got = np.array([m.cog / 100 for m in raw])
    assert np.allclose(((got - cog + 180) % 360 - 180)[moving], 0.0, atol=0.006)
    assert np.allclose([m.vz / 100 for m in glob], sim.gps_vel_ned[:, 2], atol=0.006)
    assert all(m.h_acc == 700 and m.vel_acc == 80 and m.eph > 0 for m in raw)


def test_on_the_link_a_fix_arrives_latency_after_its_stamp(wire):
    """Each GPS message follows the IMU sample of 100 ms later on the board clock."""
    last_imu = None
    ages = []
    for r in wire.valid:
        kind = r.msg.get_type()
        if kind == "RAW_IMU":
            last_imu = r.msg.time_usec
        elif kind == "GPS_RAW_INT" and last_imu is not None:
            ages.append((last_imu - r.msg.time_usec) * 1e-6)
    assert len(ages) > 100
    ages = np.array(ages)
    assert np.all(ages >= 0.1 - 1e-9) and np.all(ages <= 0.1 + 1.0 / 250.0)


def test_the_gps_does_not_change_the_other_samples():
    a = simulate(replace(CFG, duration_s=3.0))
    b = simulate(replace(CFG, duration_s=3.0, gps=None))
    assert np.array_equal(a.gyr_counts, b.gyr_counts) and np.array_equal(a.time_us, b.time_us)
    assert len(b.gps_t_s) == 0 and len(a.gps_t_s) == 29  # the fix of 2.9 s is sent at 3 s


@pytest.mark.parametrize("kwargs", [{"rate_hz": 0.1}, {"latency_s": -0.1},
                                    {"vel_noise_h_mps": float("nan")}])
def test_bad_gps_settings(kwargs):
    with pytest.raises(ValueError, match="GPS"):
        GpsConfig(**kwargs)
