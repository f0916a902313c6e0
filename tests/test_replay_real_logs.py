"""Replay reads what real logs contain: old ULog magnetometer fields, the emulator's own
tlog recorded over UDP (board detected), PX4 SITL flights with truth and no time stamps,
and the command line prints a number or a one-line reason for every column."""

from __future__ import annotations

import asyncio
import re
import time

import numpy as np
import pytest
from hil_support import Receiver

import replay
from bridge.app.cli import main
from estimators import metrics
from replay.align import measure_lag, reference_at

TAGGED = "pyulog_sample_logging_tagged_and_default_params.ulg"
CELL = re.compile(r"^-?\d+\.\d+$|^\(\d+\)$")


def test_ulog_magnetometer_from_old_sensor_combined(data_dir, tmp_path):
    """PX4 <= 1.9 logs keep the magnetometer in sensor_combined.magnetometer_ga; the same
    readings moved there (and vehicle_magnetometer removed) replay to the same scores."""
    from pyulog import ULog

    src = data_dir / "logs" / TAGGED
    log = ULog(str(src))
    vm = next(d for d in log.data_list if d.name == "vehicle_magnetometer")
    sc = next(d for d in log.data_list if d.name == "sensor_combined")
    t_sc = sc.data["timestamp"].astype(np.int64)
    t_vm = vm.data["timestamp_sample"].astype(np.int64)
    idx = np.searchsorted(t_vm, t_sc, side="right") - 1  # latest reading at each row
    held = idx >= 0
    rel = np.where(held, t_vm[np.maximum(idx, 0)] - t_sc, 2147483647).astype(np.int32)
    fmt = log.message_formats["sensor_combined"]
    fmt.fields = [f for f in fmt.fields if not f[2].startswith("_padding")] + [
        ("int32_t", 0, "magnetometer_timestamp_relative"), ("float", 3, "magnetometer_ga")]
    sc.field_data.append(ULog._FieldData("magnetometer_timestamp_relative", "int32_t"))
    sc.data["magnetometer_timestamp_relative"] = rel
    for i in range(3):
        sc.field_data.append(ULog._FieldData(f"magnetometer_ga[{i}]", "float"))
        values = vm.data[f"magnetometer_ga[{i}]"][np.maximum(idx, 0)]
        sc.data[f"magnetometer_ga[{i}]"] = np.where(held, values, 0).astype(np.float32)
    log.data_list.remove(vm)
    old = tmp_path / "old.ulg"
    log.write_ulog(str(old))

    assert not any(d.name == "vehicle_magnetometer" for d in ULog(str(old)).data_list)
    before, after = replay.load(src), replay.load(old)
    assert any("sensor_combined.magnetometer_ga" in n for n in after.notes)
    assert after.n == before.n
    np.testing.assert_allclose(after.mag, before.mag, rtol=1e-6)
    a = replay.evaluate(after, ["mahony"]).scores["mahony"]
    b = replay.evaluate(before, ["mahony"]).scores["mahony"]
    assert a.total_deg == pytest.approx(b.total_deg, rel=1e-9)


def record_emulator_tlog(path, profile: str, duration_s: float, rate_hz: float) -> None:
    """Run the HIL emulator over real UDP and write what arrives as a tlog (arrival µs,
    big-endian, then the MAVLink frame), as a ground station would."""
    from hil import EmulatorConfig
    from hil.link import Emulator

    async def run() -> list:
        rx = Receiver.open()
        frames = []
        rx.handle = lambda data, now, kernel_s=None: frames.append((time.time(), data))  # raw
        loop = asyncio.get_running_loop()
        rx.attach(loop)
        cfg = EmulatorConfig(profile=profile, rate_hz=rate_hz, duration_s=duration_s,
                             fast=True, seed=3)
        await Emulator(cfg).run([("127.0.0.1", rx.port)])
        await asyncio.sleep(0.2)
        rx.detach(loop)
        return frames

    frames = asyncio.run(run())
    with path.open("wb") as f:
        for stamp, data in frames:
            f.write(int(stamp * 1e6).to_bytes(8, "big") + data)


def test_emulator_tlog_replays_with_the_board_detected(tmp_path):
    """RAW_IMU from our GY-86 emulator read as ArduPilot's mG is 4 g at rest and ~180°
    wrong; replay detects gy86, and warns when told the wrong board."""
    path = tmp_path / "emulator.tlog"
    record_emulator_tlog(path, "flight", duration_s=12.0, rate_hz=250.0)
    rec = replay.load(path)
    assert rec.board == "gy86" and rec.warnings == ()
    assert rec.reference.kind == "truth" and rec.reference.timing == ""  # own board time
    ev = replay.evaluate(rec, ["mahony"])
    # HIL_STATE_QUATERNION carries the emulator's position: the WMM gives the declination
    assert "HIL_STATE_QUATERNION" in ev.prepared.declination.source
    assert ev.scores["mahony"].total_deg < 10.0
    wrong = replay.load(path, board="ardupilot")
    assert len(wrong.warnings) == 1 and "4.1" in wrong.warnings[0]
    assert replay.evaluate(wrong, ["mahony"]).scores["mahony"].total_deg > 60.0


@pytest.fixture(scope="module")
def sih_box(data_dir):
    path = data_dir / "px4_sih" / "sih_box.tlog"
    return replay.load(path), replay.load(path, reference="autopilot")


def take_off_time(rec) -> float:
    """First time the vehicle is 0.5 m above the ground level, from the aiding velocity
    (LOCAL_POSITION_NED). The EKF's height settles by 0.8 m on the ground first, so the
    ground level is the median height before the vehicle is surely flying (2 m above the
    first tenth's median), not the height at the start nor a fixed z threshold."""
    v = rec.velocity
    rows = np.flatnonzero(np.isfinite(v.vel[:, 2]))
    t, vz = rec.t[rows], v.vel[rows, 2]
    height = -np.concatenate(([0.0], np.cumsum(0.5 * (vz[1:] + vz[:-1]) * np.diff(t))))
    flying = int(np.argmax(height > np.median(height[: len(height) // 10]) + 2.0))
    ground = float(np.median(height[:flying]))
    return float(t[np.argmax(height > ground + 0.5)])


@pytest.mark.xdist_group("sih_box_log")  # one worker builds the fixture once
def test_sih_truth_aligned_by_arrival_matches_px4s_own_accuracy(sih_box):
    """PX4's own EKF2 attitude against the truth placed by arrival: the accuracy measured
    for it by hand (1.70° total / 1.08° inclination) with no lag left over."""
    truth, autopilot = sih_box
    assert "aligned by arrival" in truth.reference.timing
    airborne = take_off_time(truth)
    assert 13.0 < airborne - truth.t[0] < 16.0
    q_true = reference_at(truth.reference, truth.t)
    q_px4 = reference_at(autopilot.reference, truth.t)
    keep = (truth.t > airborne) & np.all(np.isfinite(q_true) & np.isfinite(q_px4), axis=1)
    r = metrics.rms_errors(q_px4[keep], q_true[keep])
    assert r.total_deg == pytest.approx(1.70, abs=0.1)
    assert r.inclination_deg == pytest.approx(1.08, abs=0.1)
    lag, why = measure_lag(truth.t, q_px4, q_true, keep, max_lag_s=0.2)
    assert why == "" and abs(lag) < 0.005


@pytest.mark.xdist_group("sih_box_log")  # one worker builds the fixture once
def test_sih_scores_against_truth_in_true_north(sih_box):
    from pygeomag import GeoMag

    truth, _ = sih_box
    ev = replay.evaluate(truth, ["madgwick"])
    p = truth.position
    assert p.source == "GPS_RAW_INT" and p.lat_deg == pytest.approx(47.3978, abs=1e-3)
    wmm = GeoMag(coefficients_file="wmm/WMM_2025.COF").calculate(
        glat=p.lat_deg, glon=p.lon_deg, alt=p.alt_m / 1000, time=2026.9,
        allow_date_outside_lifespan=True)
    assert ev.prepared.declination.deg == pytest.approx(wmm.d, abs=0.01)  # ~3.66°
    s = ev.scores["madgwick"]
    assert s.samples > 0.95 * truth.n and np.isfinite(s.lag_s)
    assert 0.5 < s.inclination_deg < 10.0 and s.heading_deg < 5.0
    # Without the declination the simulated magnetometer's 3.66° shows up in heading.
    plain = replay.evaluate(truth, ["madgwick"], declination_deg=0.0).scores["madgwick"]
    assert plain.heading_deg > s.heading_deg + 1.0
    v = truth.velocity
    assert v.source == "LOCAL_POSITION_NED" and v.count > 3000
    ages = v.age[np.isfinite(v.age)]
    assert ages.min() >= 0 and np.median(ages) < 0.01


def table_of(out: str) -> tuple[list[list[str]], list[str]]:
    lines = out.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("estimator"))
    end = next((i for i, line in enumerate(lines) if line.startswith("by phase")), len(lines))
    rows = [line.split() for line in lines[start + 1:end] if line and not line.startswith(" ")]
    notes = [line.strip() for line in lines[start + 1:] if line.startswith("  (")]
    return rows, notes


@pytest.mark.parametrize("name", [
    "logs/pyulog_sample_log_small.ulg", f"logs/{TAGGED}", "logs/pyulog_sample_px4_events.ulg",
    "px4_sih/sih_aggressive.tlog", "broad/28_disturbed_stationary_magnet_A.npz",
])
def test_every_column_is_a_number_or_a_reason(data_dir, name, capsys):
    assert main(["replay", str(data_dir / name)]) == 0
    out = capsys.readouterr().out
    assert "declination:" in out and "aiding:" in out
    rows, notes = table_of(out)
    # the default estimators, and the autopilot's own attitude when truth is the reference
    own = ["autopilot"] if replay.load(data_dir / name).autopilot is not None else []
    assert [r[0] for r in rows] == ["eskf", "mahony", "madgwick", "kalman", *own]
    marks = set()
    for row in rows:
        assert len(row) == 6 and all(CELL.match(c) for c in row[1:]), row
        marks |= {c for c in row[1:] if c.startswith("(")}
    assert sorted(marks) == sorted(n.split()[0] for n in notes)  # each mark explained


def test_too_slow_imu_is_one_line(data_dir, capsys):
    path = data_dir / "logs" / "dronekit_flight_replay_flight.tlog"
    assert main(["replay", str(path)]) == 0
    out = capsys.readouterr().out
    assert "declination: +12.32° (vehicle parameter COMPASS_DEC)" in out
    assert "not scored: IMU at 2.8 Hz is too slow" in out and "estimator " not in out
