"""PX4's raw magnetometer in place of HIGHRES_IMU's (imu.px4_mag): when, and when not.

HIGHRES_IMU's field has PX4's own bias estimate taken out; SCALED_IMU's is the sensor's,
uncalibrated. The raw one may replace it only where PX4 applies no calibration (its
parameters say so) and the two agree; a calibrated sensor, a disagreement, a stale or
missing raw stream keep HIGHRES_IMU's.
"""

from __future__ import annotations

import numpy as np
import pytest

from imu.px4_mag import (
    AGREE,
    CALIBRATED,
    CALIBRATION_PARAMS,
    RAW,
    STALE_S,
    WAITING,
    WINDOW_S,
    RawMagnetometer,
    calibration_free,
)

FIELD = np.array([0.21, 0.013, 0.43])  # gauss, SIH's at Zurich, body level and north
UNCALIBRATED = dict.fromkeys(CALIBRATION_PARAMS, 0.0)
HIGHRES_HZ, RAW_HZ = 14.0, 50.0


def stream(chooser: RawMagnetometer, seconds: float, raw_offset=(0.0, 0.0, 0.0),
           highres_offset=(0.0, 0.0, 0.0), start: float = 0.0, raw: bool = True,
           seed: int = 1) -> list[tuple[np.ndarray, np.ndarray]]:
    """Both streams interleaved by arrival, with SIH's noise (0.02 / 0.03 gauss raw,
    smoothed in HIGHRES_IMU); (HIGHRES_IMU's reading, the chosen field) per reading."""
    rng = np.random.default_rng(seed)
    events = [(start + k / RAW_HZ, "raw") for k in range(int(seconds * RAW_HZ))] if raw else []
    events += [(start + (k + 0.5) / HIGHRES_HZ, "highres")
               for k in range(int(seconds * HIGHRES_HZ))]
    out = []
    for t, kind in sorted(events):
        if kind == "raw":
            noise = rng.normal(0.0, (0.02, 0.02, 0.03))
            chooser.offer_raw(FIELD + raw_offset + noise, t)
        else:
            reading = FIELD + highres_offset + rng.normal(0.0, (0.01, 0.01, 0.015))
            out.append((reading, chooser.choose(reading, t)))
    return out


def test_the_parameters_tell_an_uncalibrated_sensor():
    assert calibration_free(UNCALIBRATED) is True
    assert calibration_free({**UNCALIBRATED, "CAL_MAG0_YOFF": 0.031}) is False
    assert calibration_free({"CAL_MAG0_XOFF": 0.0}) is None  # not all known yet


def test_an_uncalibrated_sensor_that_agrees_gives_its_raw_field_after_one_window():
    chooser = RawMagnetometer()
    chooser.set_parameters(UNCALIBRATED)
    pairs = stream(chooser, 3 * WINDOW_S)
    first_window = int(WINDOW_S * HIGHRES_HZ)
    # HIGHRES_IMU's own during the first window, then the raw reading
    assert all(chosen is own for own, chosen in pairs[:first_window - 1])
    assert all(chosen is not own for own, chosen in pairs[first_window + 1:])
    assert chooser.state == RAW and chooser.windows == 2
    assert chooser.difference < 0.02  # noise only: 0.5-1.5 % measured in SIH
    assert chooser.used == len(pairs) - first_window
    assert "SCALED_IMU's raw field" in chooser.describe()
    assert chooser.status()["source"] == "SCALED_IMU"


def test_px4s_bias_estimate_moving_highres_does_not_move_the_field_used():
    """EKF2's estimate changing after take-off shifts HIGHRES_IMU's field (5.6° of
    azimuth seen in SIH); the field used stays the sensor's."""
    chooser = RawMagnetometer()
    chooser.set_parameters(UNCALIBRATED)
    stream(chooser, 2 * WINDOW_S)
    shift = np.array([0.0, 0.021, 0.0])  # 5.6° of azimuth on SIH's horizontal field
    pairs = stream(chooser, 2 * WINDOW_S, highres_offset=shift, start=2 * WINDOW_S)
    assert chooser.state == RAW
    used = np.array([chosen for _, chosen in pairs])
    assert np.abs(used.mean(axis=0) - FIELD)[1] < 0.005
    assert np.abs(np.array([own for own, _ in pairs]).mean(axis=0) - FIELD)[1] > 0.015


def test_a_calibrated_sensor_keeps_highres_whatever_the_data():
    chooser = RawMagnetometer()
    chooser.set_parameters({**UNCALIBRATED, "CAL_MAG0_XOFF": -0.004})
    pairs = stream(chooser, 3 * WINDOW_S)
    assert chooser.state == CALIBRATED and chooser.used == 0
    assert all(chosen is own for own, chosen in pairs)
    assert "are not 0" in chooser.describe()


def test_without_the_parameters_nothing_is_replaced():
    chooser = RawMagnetometer()
    pairs = stream(chooser, 3 * WINDOW_S)
    assert chooser.state == WAITING and chooser.used == 0
    assert all(chosen is own for own, chosen in pairs)
    assert "not known" in chooser.describe()


@pytest.mark.parametrize("offset_share", [1.2 * AGREE, 0.5])
def test_a_raw_field_far_from_the_calibrated_one_is_never_used(offset_share):
    """Parameters that say "uncalibrated" about another sensor than SCALED_IMU's."""
    chooser = RawMagnetometer()
    chooser.set_parameters(UNCALIBRATED)
    offset = np.array([1.0, 0.0, 0.0]) * offset_share * np.linalg.norm(FIELD)
    pairs = stream(chooser, 3 * WINDOW_S, raw_offset=offset)
    assert chooser.state == CALIBRATED and chooser.used == 0
    assert all(chosen is own for own, chosen in pairs)
    assert chooser.difference == pytest.approx(offset_share, rel=0.1)


def test_a_raw_field_that_stops_agreeing_is_dropped_for_good():
    """An offset that stays (a calibration made while the bridge runs: 42 % of the
    field) is seen within half a minute, and the raw field is not taken again."""
    chooser = RawMagnetometer()
    chooser.set_parameters(UNCALIBRATED)
    stream(chooser, 2 * WINDOW_S)
    assert chooser.state == RAW
    offset = np.array([0.0, 0.0, 0.2])
    stream(chooser, 4 * WINDOW_S, raw_offset=offset, start=2 * WINDOW_S)
    assert chooser.state == CALIBRATED
    used = chooser.used
    pairs = stream(chooser, 2 * WINDOW_S, start=6 * WINDOW_S)  # agrees again: not taken
    assert chooser.state == CALIBRATED and chooser.used == used
    assert all(chosen is own for own, chosen in pairs)


def test_one_window_of_px4_realigning_its_field_keeps_the_raw_one():
    """EKF2's estimate jumping for a few seconds and coming back (one window of PX4 SIH
    under load: 16 % of the field, the raw field steady) is not a missing calibration:
    the raw field stays in use, and the jump is shown."""
    chooser = RawMagnetometer()
    chooser.set_parameters(UNCALIBRATED)
    stream(chooser, 4 * WINDOW_S)
    jump = np.array([0.0, 0.19, 0.0])  # 40 % of the field, for one window's time
    stream(chooser, WINDOW_S, highres_offset=jump, start=4 * WINDOW_S)
    pairs = stream(chooser, 3 * WINDOW_S, start=5 * WINDOW_S)
    assert chooser.state == RAW
    assert all(chosen is not own for own, chosen in pairs[1:])
    assert chooser.largest_window > 2 * AGREE > chooser.difference
    assert chooser.status()["largest_window_pct"] > chooser.status()["difference_pct"]


def test_a_stale_raw_stream_gives_highres_back():
    chooser = RawMagnetometer()
    chooser.set_parameters(UNCALIBRATED)
    stream(chooser, 2 * WINDOW_S)
    assert chooser.state == RAW
    late = 2 * WINDOW_S + STALE_S + 0.1
    pairs = stream(chooser, 1.0, start=late, raw=False)
    assert all(chosen is own for own, chosen in pairs)


def test_a_missing_or_disturbed_reading_stays_missing():
    chooser = RawMagnetometer()
    chooser.set_parameters(UNCALIBRATED)
    stream(chooser, 2 * WINDOW_S)
    assert chooser.choose(None, 2 * WINDOW_S) is None


def test_a_reboot_starts_over():
    chooser = RawMagnetometer()
    chooser.set_parameters(UNCALIBRATED)
    stream(chooser, 2 * WINDOW_S)
    chooser.reset()
    assert chooser.state == WAITING and chooser.uncalibrated is None
    own = FIELD.copy()
    assert chooser.choose(own, 2 * WINDOW_S + 0.01) is own
