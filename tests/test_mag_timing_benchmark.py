"""benchmarks/mag_timing.py finds how old a magnetometer reading is: a board that turns
at a varying rate, its magnetometer refreshed every few samples with readings a known
time old, is measured at that age, and the refresh interval is the one sent."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from estimators import quat as Q

_SPEC = importlib.util.spec_from_file_location(
    "mag_timing_benchmark", Path(__file__).resolve().parents[1] / "benchmarks" / "mag_timing.py")
mag_timing = importlib.util.module_from_spec(_SPEC)
sys.modules[_SPEC.name] = mag_timing
_SPEC.loader.exec_module(mag_timing)

RATE_HZ = 400.0


def _turning_board(age_samples: int, refresh_samples: int, world: str) -> tuple:
    """Truth, magnetometer readings (sample-and-hold, each ``age_samples`` old when it
    first appears) and the moving mask, for 20 s of turning and rocking."""
    n = int(20 * RATE_HZ)
    t = np.arange(n) / RATE_HZ
    yaw = 1.5 * np.sin(0.9 * t) + 0.8 * np.sin(2.3 * t)  # up to ~3.7 rad/s
    truth = Q.from_euler(0.2 * np.sin(1.3 * t), 0.15 * np.sin(0.7 * t), yaw)
    field = np.array([0.2, 0.05, 0.45]) if world == "NED" else np.array([0.05, 0.2, -0.45])
    rng = np.random.default_rng(3)
    body_field = Q.rotate(Q.conjugate(truth), np.tile(field, (n, 1)))
    body_field += rng.normal(0.0, 0.001, body_field.shape)
    mag = np.empty_like(body_field)
    for k in range(n):
        fresh = k - k % refresh_samples  # when the reading shown at k first appeared
        mag[k] = body_field[max(fresh - age_samples, 0)]
    return truth, mag, np.ones(n, dtype=bool)


@pytest.mark.parametrize(("age_samples", "refresh_samples", "world"),
                         [(20, 40, "NED"), (0, 1, "NED"), (6, 4, "ENU")])
def test_the_age_of_a_fresh_reading_and_the_refresh_interval_are_found(
        age_samples: int, refresh_samples: int, world: str) -> None:
    truth, mag, moving = _turning_board(age_samples, refresh_samples, world)
    idx = mag_timing.fresh_readings(mag, moving)
    assert np.median(np.diff(idx)) == refresh_samples
    spreads = [mag_timing.heading_spread_deg(truth, mag, idx, lag, world)
               for lag in range(int(mag_timing.MAX_AGE_S * RATE_HZ) + 1)]
    assert int(np.argmin(spreads)) == age_samples
    assert spreads[age_samples] < 0.3  # the magnetometer's noise alone


def test_ardupilot_raw_imu_magnetometer_is_refreshed_at_10_hz_and_51_ms_old(tmp_path: Path
                                                                             ) -> None:
    """docs/accuracy.md's figures for the recorded ArduPilot SITL flight: refreshed every
    99 ms, a fresh reading 51 ms old, the fresh readings' heading spread 2.04° as they
    come and 0.14° at that age."""
    flight = Path(__file__).parent / "data" / "sitl" / "arducopter_touchdown.tlog"
    (tmp_path / flight.name).symlink_to(flight)
    (trial,) = mag_timing.sitl_trials([tmp_path])  # benchmarks/accuracy.py's loader
    row = mag_timing.reading_age(trial, mag_timing.moving_samples(trial))
    assert 95.0 <= row["refresh_ms"] <= 103.0
    assert 45.0 <= row["age_ms"] <= 57.0
    assert row["spread_at_age_deg"] <= 0.21
    assert row["spread_at_0_deg"] >= 2.04 / 1.5
