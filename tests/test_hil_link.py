"""The emulator on the wire: a real pymavlink receiver on loopback UDP sockets."""

from __future__ import annotations

import asyncio
import json
import math
import os
import socket
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hil_support import Receiver, unwrap_seq

from bridge.app.cli import main as cli_main
from hil import Emulator, EmulatorConfig, FaultConfig, simulate

REPO = Path(__file__).resolve().parents[1]
G = 9.80665


async def _run(cfg: EmulatorConfig, receivers: list[Receiver],
               extra_targets: list[tuple[str, int]] = ()) -> Emulator:
    loop = asyncio.get_running_loop()
    for rx in receivers:
        rx.attach(loop)
    emu = Emulator(cfg)
    try:
        await emu.run([("127.0.0.1", rx.port) for rx in receivers] + list(extra_targets))
        await asyncio.sleep(0.05)
    finally:
        for rx in receivers:
            rx.detach(loop)
    return emu


def stream(cfg: EmulatorConfig) -> tuple[Emulator, Receiver]:
    rx = Receiver.open()
    emu = asyncio.run(_run(cfg, [rx]))
    return emu, rx


def test_realtime_rates_from_the_command_line(tmp_path):
    """`attitude-bridge hil` at 1 kHz for 5 s: rates within 2 %, time_usec monotonic."""
    rx = Receiver.open()
    stats_path = tmp_path / "stats.json"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen(
        [sys.executable, "-m", "bridge.app.cli", "hil", "--target", f"udp:127.0.0.1:{rx.port}",
         "--profile", "flight", "--rate", "1000", "--duration", "5", "--sysid", "7",
         "--stats-json", str(stats_path)],
        env=env, stderr=subprocess.PIPE, text=True)
    try:
        rx.blocking_collect(seconds_idle=1.0, limit_s=60.0)
    finally:
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    stats = json.loads(stats_path.read_text())
    imu = [r for r in rx.valid if r.msg.get_type() == "RAW_IMU"]
    assert len(imu) == 5000 == stats["messages"]["RAW_IMU"]
    # the rate the emulator sent at: the kernel's arrival stamps, not when this process
    # (one of several on 2 cores in the suite) got round to reading them
    arrival = np.array([r.kernel_s for r in imu])
    rate = (len(imu) - 1) / (arrival[-1] - arrival[0])
    assert abs(rate / 1000.0 - 1.0) < 0.02
    counts = {kind: len(rx.of_type(kind)) for kind in
              ("HEARTBEAT", "SCALED_PRESSURE", "HIL_STATE_QUATERNION")}
    assert counts == {"HEARTBEAT": 5, "SCALED_PRESSURE": 250, "HIL_STATE_QUATERNION": 5000}
    assert counts == {k: stats["messages"][k] for k in counts}
    time_usec = np.array([r.msg.time_usec for r in imu])
    assert np.all(np.diff(time_usec) == 1000)
    assert all(r.msg.get_srcSystem() == 7 for r in rx.valid)
    assert "RAW_IMU 5000" in err  # the summary printed at exit


def test_wire_carries_exactly_the_simulated_samples():
    cfg = EmulatorConfig(profile="flight", rate_hz=1000.0, duration_s=3.0, seed=11, sysid=42,
                         fast=True)
    emu, rx = stream(cfg)
    rec = simulate(cfg)
    imu = rx.of_type("RAW_IMU")
    assert len(imu) == len(rec) == emu.stats.imu_samples
    got = np.array([[m.xacc, m.yacc, m.zacc, m.xgyro, m.ygyro, m.zgyro, m.xmag, m.ymag, m.zmag]
                    for m in imu])
    assert np.array_equal(got, np.hstack([rec.acc_counts, rec.gyr_counts, rec.mag_counts]))
    assert np.array_equal([m.time_usec for m in imu], rec.time_us)
    assert np.array_equal([m.temperature for m in imu], np.round(rec.temperature_c * 100))
    truth = rx.of_type("HIL_STATE_QUATERNION")
    assert np.array_equal([m.time_usec for m in truth], rec.truth_time_us[rec.truth_on_wire])
    q = np.array([m.attitude_quaternion for m in truth])
    assert np.allclose(q, rec.truth_q[rec.truth_on_wire], atol=1e-6)
    rates = np.array([[m.rollspeed, m.pitchspeed, m.yawspeed] for m in truth])
    assert np.allclose(rates, rec.truth_rates[rec.truth_on_wire], atol=1e-5)
    baro = rx.of_type("SCALED_PRESSURE")
    assert np.allclose([m.press_abs for m in baro], rec.pressure_pa / 100.0, atol=1e-3)
    assert np.array_equal([m.temperature for m in baro], rec.baro_temp_cdeg)
    assert np.array_equal([m.time_boot_ms for m in baro], rec.baro_time_us // 1000)
    beats = rx.of_type("HEARTBEAT")
    assert len(beats) == 3
    assert all(b.type == 2 and b.autopilot == 0 and b.get_srcSystem() == 42
               and b.get_srcComponent() == 1 for b in beats)
    seqs = unwrap_seq([r.seq for r in rx.valid])
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # nothing lost or reordered


@pytest.mark.parametrize("kind", ["SCALED_IMU", "HIGHRES_IMU"])
def test_scaled_and_highres_imu_in_frd(kind):
    cfg = EmulatorConfig(profile="tilt", duration_s=1.0, imu_message=kind, fast=True)
    _, rx = stream(cfg)
    rec = simulate(cfg)
    msgs = rx.of_type(kind)
    assert len(msgs) == len(rec) and not rx.of_type("RAW_IMU")
    acc = np.array([[m.xacc, m.yacc, m.zacc] for m in msgs], dtype=float)
    gyr = np.array([[m.xgyro, m.ygyro, m.zgyro] for m in msgs], dtype=float)
    mag = np.array([[m.xmag, m.ymag, m.zmag] for m in msgs], dtype=float)
    if kind == "SCALED_IMU":  # mG, mrad/s, mGauss
        acc, gyr, mag = acc * G / 1000.0, gyr / 1000.0, mag / 1000.0
        tol = (G / 1000.0, 1e-3, 1e-3)
    else:
        tol = (1e-5, 1e-6, 1e-6)
    assert np.allclose(acc, rec.acc, atol=tol[0])
    assert np.allclose(gyr, rec.gyr, atol=tol[1])
    assert np.allclose(mag, rec.mag, atol=tol[2])
    # FRD: level-ish tilt reads about -g on z, +g sin(pitch) on x
    assert np.mean(acc[:, 2]) < -9.0 and np.mean(acc[:, 0]) > 1.0
    if kind == "HIGHRES_IMU":
        updated = np.array([m.fields_updated for m in msgs])
        assert np.sum((updated & 0x1C0) != 0) == rec.mag_updated.sum()
        assert np.sum((updated & 0x200) != 0) == len(rec.baro_t_s)


def test_link_and_clock_faults_are_seen_on_the_wire_as_counted():
    faults = FaultConfig(loss=0.02, duplicate=0.02, reorder=0.02, corrupt=0.02, truncate=0.02,
                         time_jump_rate_hz=0.5, time_backwards_rate_hz=0.5)
    cfg = EmulatorConfig(profile="flight", duration_s=8.0, seed=5, fast=True, faults=faults)
    emu, rx = stream(cfg)
    f = emu.stats.faults
    for name in ("lost", "duplicated", "reordered", "corrupted", "truncated", "time_jumps",
                 "time_backwards"):
        assert getattr(f, name) > 0, name
    assert rx.corrupt == f.corrupted
    assert rx.truncated == f.truncated
    seqs = unwrap_seq([r.seq for r in rx.valid])
    seen: set[int] = set()
    duplicates = reordered = 0
    highest = -1
    for s in seqs:
        if s in seen:
            duplicates += 1
            continue
        seen.add(s)
        if s < highest:
            reordered += 1
        highest = max(highest, s)
    assert duplicates == f.duplicated
    assert reordered == f.reordered
    packed = sum(emu.stats.messages.values())
    assert packed - len(seen) - f.corrupted - f.truncated == f.lost
    assert emu.stats.datagrams_sent == rx.datagrams
    # time_usec in send order (by sequence number) jumps exactly where injected
    imu = dict(sorted(((key, r.msg) for key, r in zip(seqs, rx.valid, strict=True)
                       if r.msg.get_type() == "RAW_IMU"), key=lambda kv: kv[0]))  # dups collapse
    steps = np.diff([m.time_usec for m in imu.values()])
    assert np.sum(steps > 0.25e6) == f.time_jumps
    assert np.sum(steps < 0) == f.time_backwards


def test_sensor_faults_are_seen_on_the_wire_as_counted():
    faults = FaultConfig(saturation_rate_hz=1.0, stuck_rate_hz=0.5, vibration_g=0.3,
                         vibration_hz=70.0, mag_disturbance_rate_hz=0.3,
                         gyro_bias_step_rate_hz=0.5)
    cfg = EmulatorConfig(profile="static", duration_s=12.0, seed=4, fast=True, faults=faults)
    emu, rx = stream(cfg)
    f = emu.stats.faults
    imu = rx.of_type("RAW_IMU")
    assert len(imu) == 12000
    gyr = np.array([[m.xgyro, m.ygyro, m.zgyro] for m in imu])
    acc = np.array([[m.xacc, m.yacc, m.zacc] for m in imu])
    mag = np.array([[m.xmag, m.ymag, m.zmag] for m in imu])
    temp = np.array([m.temperature for m in imu])
    # the same board without faults: every random stream but the fault one is identical
    clean = simulate(replace(cfg, faults=FaultConfig()))

    limits = (gyr == 32767) | (gyr == -32768) | (acc == 32767) | (acc == -32768)
    saturated = np.any(limits, axis=1)
    assert f.saturation_events > 0 and saturated.sum() == f.saturated_samples
    assert _runs(saturated) == f.saturation_events

    reading = np.hstack([gyr, acc, temp[:, None]])
    same = np.all(reading[1:] == reading[:-1], axis=1)  # sample k+1 repeats sample k
    stuck_runs = _run_lengths(same)
    assert f.stuck_events > 0
    assert sum(1 for n in stuck_runs if n >= 50) == f.stuck_events
    assert sum(n for n in stuck_runs if n >= 50) == f.stuck_samples

    assert f.vibration_samples == len(imu)
    stuck = np.zeros(len(imu), dtype=bool)
    stuck[1:] = same
    good = ~saturated & ~stuck
    t = np.arange(len(imu))[good] / 1000.0
    basis = np.column_stack([np.cos(2 * np.pi * 70.0 * t), np.sin(2 * np.pi * 70.0 * t),
                             np.ones_like(t), t])  # sine + offset + slow drift, per axis
    coef, *_ = np.linalg.lstsq(basis, acc[good] / 4096.0, rcond=None)
    amplitude_g = np.linalg.norm(coef[:2])  # over both quadratures and the three axes
    expected = 0.3 / math.sqrt(1.0 + (70.0 / 184.0) ** 2)  # through the 184 Hz DLPF
    assert amplitude_g == pytest.approx(expected, rel=0.1)

    disturbed = np.any(np.abs(mag.astype(int) - clean.mag_counts) > 100, axis=1)
    assert f.mag_disturbances > 0 and _runs(disturbed) == f.mag_disturbances

    # a step shows as a new level of (wire - clean) between consecutive good samples
    level = np.round((gyr[good] - clean.gyr_counts[good]) / (5.0 * 16.4)).astype(int)
    changes = np.any(level[1:] != level[:-1], axis=1)
    assert f.gyro_bias_steps > 0 and changes.sum() == f.gyro_bias_steps


def _run_lengths(flags: np.ndarray) -> list[int]:
    out, n = [], 0
    for v in [*flags.tolist(), False]:
        if v:
            n += 1
        elif n:
            out.append(n)
            n = 0
    return out


def _runs(flags: np.ndarray) -> int:
    return len(_run_lengths(flags))


def test_several_targets_and_a_vanished_peer():
    a, b = Receiver.open(), Receiver.open()
    dead = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    dead.bind(("127.0.0.1", 0))
    dead_port = dead.getsockname()[1]
    dead.close()  # nobody listens there: ICMP port unreachable
    cfg = EmulatorConfig(profile="static", duration_s=1.0, fast=True)
    emu = asyncio.run(_run(cfg, [a, b], [("127.0.0.1", dead_port)]))
    assert [r.data for r in a.valid] == [r.data for r in b.valid]
    assert len(a.of_type("RAW_IMU")) == 1000
    # Linux does not report ICMP errors on an unconnected UDP socket: the dead target just
    # gets datagrams nobody reads, and the live ones are unaffected.
    assert emu.stats.datagrams_sent == 3 * len(a.valid)


def test_cancel_stops_an_endless_stream_cleanly():
    async def scenario() -> Emulator:
        rx = Receiver.open()
        loop = asyncio.get_running_loop()
        rx.attach(loop)
        emu = Emulator(EmulatorConfig(profile="flight", duration_s=None))
        task = asyncio.create_task(emu.run([("127.0.0.1", rx.port)]))
        await asyncio.sleep(0.5)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        rx.detach(loop)
        assert len(rx.of_type("RAW_IMU")) > 100
        return emu

    emu = asyncio.run(scenario())
    assert 100 < emu.stats.imu_samples < 1000


@pytest.mark.parametrize("argv", [
    ["hil", "--target", "udp:127.0.0.1"], ["hil", "--target", "udp:127.0.0.1:1", "--rate", "0"],
    ["hil", "--target", "udp:127.0.0.1:1", "--profile", "nope"],
    ["hil", "--target", "udp:127.0.0.1:1", "--loss", "2"]])
def test_cli_rejects_bad_arguments(argv, capsys):
    assert cli_main(argv) == 2
    assert "error" in capsys.readouterr().err


@pytest.mark.parametrize(("extra", "why"), [
    (["--autopilot", "px5"], "unknown autopilot"),
    (["--autopilot", "px4", "--imu-message", "RAW_IMU"], "does not send RAW_IMU"),
    (["--gps", "--gps-rate", "100"], "GPS rate"),
    (["--gps", "--gps-latency", "-1"], "GPS latency"),
    (["--home", "47.4"], "LAT,LON"), (["--home", "91,8"], "home"),
    (["--rotor-drag", "-1"], "drag"), (["--imu-message", "ATTITUDE"], "imu_message")])
def test_cli_new_options_fail_in_one_line_before_the_banner(extra, why, capsys):
    assert cli_main(["hil", "--target", "udp:127.0.0.1:1", "--duration", "1", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and why in err[0] and err[0].startswith("attitude-bridge hil: error")
