"""Replaying a PX4 tlog with SCALED_IMU beside HIGHRES_IMU: the raw magnetometer, as live.

The two recordings (tests/data/px4_raw_mag, the first sortie of each PX4 plan, recorded with
``benchmarks/record_sitl_flights.py`` since it asks for SCALED_IMU and the calibration
parameters) carry PX4 SIH's uncalibrated magnetometer twice: raw in SCALED_IMU, and in
HIGHRES_IMU with EKF2's bias estimate taken out, which moved the field's azimuth by
3-6° for about 8 s after take-off. The numbers are README's ("With a real autopilot"):
in-sample, eskf with the defaults against the simulator's truth, whole recording.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from replay.evaluate import evaluate
from replay.readers import load

DATA = Path(__file__).parent / "data" / "px4_raw_mag"
# file: (eskf total° with the raw field, with HIGHRES_IMU's; PX4's own), measured: the
# raw field is 20 % better after the take-off where EKF2's estimate moved HIGHRES_IMU's
# field, and 9 % worse on the other flight (README reports the trade)
MEASURED = {
    "px4_sih_raw_mag_touchdown.tlog": (1.105, 1.374, 1.654),
    "px4_sih_raw_mag_dashes.tlog": (1.209, 1.114, 2.953),
}


def eskf_and_px4(path: Path, raw_mag: bool) -> tuple[float, float, tuple[str, ...]]:
    ev = evaluate(load(path, raw_mag=raw_mag), ["eskf"])
    return (ev.scores["eskf"].total_deg, ev.scores["autopilot"].total_deg,
            ev.recording.notes)


@pytest.mark.parametrize("name", sorted(MEASURED))
def test_the_raw_field_replaces_highres_where_px4_does_not_calibrate(name):
    raw_total, px4_total, notes = eskf_and_px4(DATA / name, raw_mag=True)
    own_total, px4_again, own_notes = eskf_and_px4(DATA / name, raw_mag=False)
    measured_raw, measured_own, measured_px4 = MEASURED[name]
    assert any("SCALED_IMU's raw field" in n for n in notes), notes
    assert not any("magnetometer:" in n for n in own_notes), own_notes
    # the replay is deterministic: the numbers README states, to rounding
    assert raw_total == pytest.approx(measured_raw, abs=0.002)
    assert own_total == pytest.approx(measured_own, abs=0.002)
    assert px4_total == px4_again == pytest.approx(measured_px4, abs=0.002)
    # better than PX4's own attitude either way (0.67x and 0.41x with the raw field)
    assert raw_total <= 0.7 * px4_total and own_total <= 0.85 * px4_total

