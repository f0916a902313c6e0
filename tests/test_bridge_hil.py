"""End to end with the HIL emulator: emulator -> bridge -> pymavlink listener.

The emulator sends to the bridge and to the listener (for the truth); the listener also
receives the bridge's output. The emulator runs --fast (faster than real time) in the
same event loop, over real UDP sockets.
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import replace

import numpy as np
import pytest
from bridge_support import UdpListener, async_test, running_bridge, stream_emulator

import estimators
from bridge.app.emulator import emulator_declination_deg
from estimators import metrics
from estimators import quat as Q
from estimators.eskf import MULTIROTOR_DRAG_PER_S
from hil import EmulatorConfig, FaultConfig, simulate
from hil.sensors.hmc5883l import Hmc5883lConfig
from hil.sensors.mpu6050 import Mpu6050Config

PRIMARY = "eskf"
#: A calibrated board: the accelerometer's zero-g offset, sensitivity and cross-axis
#: errors and the magnetometer's gain errors removed, as an accelerometer/compass
#: calibration does. Uncalibrated, the emulator's 20 mg (1σ) offsets alone tilt any
#: estimator's attitude by ~1-3° and, through the 65° magnetic dip, its heading more.
CALIBRATED = {"mpu6050": Mpu6050Config(accel_offset_mg=0.0, scale_error=0.0, cross_axis=0.0),
              "hmc5883l": Hmc5883lConfig(scale_error=0.0)}


async def run_emulator_through_bridge(cfg: EmulatorConfig, **bridge_settings):
    """Stream ``cfg`` into a bridge; returns (listener, emulator stats, bridge status)."""
    listener = UdpListener()
    out_port = await listener.start()
    # --fast runs faster than real time: lift the per-sender budget meant for live links.
    settings = {"estimators": [PRIMARY], "out_rate": 50.0, "imu_rate": cfg.imu_rate_hz,
                "max_source_rate": 1e7,
                "declination_deg": emulator_declination_deg(),
                "outs": [f"udpout:127.0.0.1:{out_port}"]}
    settings.update(bridge_settings)
    async with running_bridge(**settings) as bridge:
        stats = await stream_emulator(bridge, cfg, out_port, share=0.95)
        bridge.publish_status()
        status = bridge.last_status[cfg.sysid]
    listener.close()
    return listener, stats, status


def truth_at_outputs(listener: UdpListener):
    """(bridge quaternions, truth at their time_boot_ms, time_boot_ms) for sysid 1."""
    aq, truth = listener.outputs_with_truth()
    est = np.array([[m.q1, m.q2, m.q3, m.q4] for m in aq])
    ref = np.array([truth[m.time_boot_ms] for m in aq])
    return est, ref, np.array([m.time_boot_ms for m in aq])


def offline_run(cfg: EmulatorConfig):
    """(recording, primary estimate) of the same samples without faults, offline, with
    the rotor-drag model the bridge picks for the emulator's quadrotor heartbeat."""
    fault_free = replace(cfg, faults=FaultConfig())
    key = repr(fault_free)  # (the config holds unhashable sensor models)
    if key not in _FAULT_FREE_RUNS:
        _FAULT_FREE_RUNS[key] = _fault_free_run(fault_free)
    return _FAULT_FREE_RUNS[key]


#: Fault tests of one length share the same flight without its faults.
_FAULT_FREE_RUNS: dict[str, tuple] = {}


def _fault_free_run(cfg: EmulatorConfig):
    rec = simulate(cfg)
    dt = np.diff(rec.time_us, prepend=rec.time_us[0] - round(1e6 / cfg.imu_rate_hz)) * 1e-6
    q = estimators.batch(PRIMARY, rec.gyr, rec.acc, rec.mag, rate_hz=cfg.imu_rate_hz, dt=dt,
                         declination=math.radians(emulator_declination_deg()),
                         drag=MULTIROTOR_DRAG_PER_S)
    return rec, q


def offline_estimate(cfg: EmulatorConfig) -> dict[int, np.ndarray]:
    """The primary estimator run offline on the same (fault-free) samples, by board ms."""
    rec, q = offline_run(cfg)
    return dict(zip((rec.time_us // 1000).tolist(), q, strict=True))


def offline_by_sample_order(listener: UdpListener, q_offline: np.ndarray):
    """(bridge quaternions, offline ones) when the board clock was stepped: the k-th
    HIL_STATE_QUATERNION is IMU sample k, and an output belongs to the truth message
    with its time stamp that arrived closest to it (stamps repeat after a step back)."""
    by_stamp: dict[int, list[tuple[int, int]]] = {}
    k = 0
    for pos, (_, m) in enumerate(listener.messages):
        if m.get_type() == "HIL_STATE_QUATERNION":
            by_stamp.setdefault(m.time_usec // 1000, []).append((pos, k))
            k += 1
    est, ref = [], []
    for pos, (_, m) in enumerate(listener.messages):
        if m.get_type() == "ATTITUDE_QUATERNION" and m.get_srcComponent() == 191:
            cands = by_stamp.get(m.time_boot_ms)
            if cands:
                est.append([m.q1, m.q2, m.q3, m.q4])
                ref.append(q_offline[min(cands, key=lambda c: abs(c[0] - pos))[1]])
    return np.array(est), np.array(ref)


@pytest.fixture(scope="module")
def flight_run():
    """One 30 s `flight` stream through the bridge, shared by the checks below."""
    cfg = EmulatorConfig(profile="flight", duration_s=30.0, seed=3, fast=True, **CALIBRATED)
    listener, _, status = asyncio.run(run_emulator_through_bridge(cfg))
    return cfg, listener, status


@pytest.mark.xdist_group("bridge_hil_flight")  # one worker builds the fixture once
def test_flight_output_is_the_estimators_own_result(flight_run):
    cfg, listener, status = flight_run
    est, _, stamps = truth_at_outputs(listener)
    assert len(est) >= 0.95 * 30.0 * 50.0  # 50 Hz output over the 30 s stream
    # Over real UDP, the bridge outputs exactly what the estimator computes offline on
    # the same samples: scaling, axes, time steps and time stamps are all right.
    offline = offline_estimate(cfg)
    same = np.array([offline[t] for t in stamps])
    assert np.max(np.degrees(Q.angle_between(est, same))) < 0.05
    assert status["drops"] == dict.fromkeys(status["drops"], 0)
    assert status["link"]["lost"] == 0
    live = status["compare"]["truth"][PRIMARY]
    assert live["samples"] > 100 and np.isfinite(live["total_deg"])


@pytest.mark.xdist_group("bridge_hil_flight")  # one worker builds the fixture once
def test_flight_accuracy_against_truth(flight_run):
    """Primary estimate against the truth over the whole stream (ground, arming, take-off,
    flight) and after the first 10 s: measured 0.30° and 0.10° total (0.16° / 0.047°
    inclination); gates 1.5x that."""
    _, listener, _ = flight_run
    est, ref, stamps = truth_at_outputs(listener)
    whole = metrics.rms_errors(est, ref)
    assert whole.total_deg < 0.45 and whole.inclination_deg < 0.245, whole
    converged = stamps >= stamps[0] + 10_000
    err = metrics.rms_errors(est[converged], ref[converged])
    assert err.total_deg < 0.15 and err.inclination_deg < 0.07, err


FAULTS = {
    "loss": FaultConfig(loss=0.02),
    "duplicate": FaultConfig(duplicate=0.02),
    "reorder": FaultConfig(reorder=0.02),
    "corrupt": FaultConfig(corrupt=0.02),
    "truncate": FaultConfig(truncate=0.02),
    "time_jump": FaultConfig(time_jump_rate_hz=0.3),
    "time_backwards": FaultConfig(time_backwards_rate_hz=0.3),
    "saturation": FaultConfig(saturation_rate_hz=0.5),
    "stuck": FaultConfig(stuck_rate_hz=0.5),
    "mag_disturbance": FaultConfig(mag_disturbance_rate_hz=0.3),
    "vibration": FaultConfig(vibration_g=0.3, vibration_dps=2.0),
    "gyro_bias_step": FaultConfig(gyro_bias_step_rate_hz=0.5),
}
#: Stream length per fault [s]: vibration never ends, so it is judged after the same
#: 10 s of convergence as the fault-free flight; magnets come every ~3 s, and each
#: must be followed by 2 s without one to be judged.
FAULT_DURATION_S = {"vibration": 15.0, "mag_disturbance": 20.0}
#: Magnets from the first second on come before eskf has learned the field's reference:
#: the start-up rule for them (a provisional reference) is opt-in, since it costs 0.1° on
#: a real PX4 flight (docs/accuracy.md), so this board's user turns it on.
FAULT_ESTIMATOR = {"mag_disturbance": f"{PRIMARY}:mag_provisional_time=0.5"}


def check_counts(kind: str, injected: dict, status: dict) -> None:
    """The bridge's counters against what the emulator says it injected."""
    link, drops, flags = status["link"], status["drops"], status["flags"]
    conn = status["connection"]
    if kind == "loss":
        assert injected["lost"] > 0 and link["lost"] == injected["lost"]
    elif kind == "duplicate":
        assert injected["duplicated"] > 0 and link["repeated"] == injected["duplicated"]
        assert 0 < drops["duplicate"] <= injected["duplicated"]
    elif kind == "reorder":
        assert injected["reordered"] > 0 and link["late"] == injected["reordered"]
        # Most swaps are an IMU packet and the truth packet behind it, invisible to the
        # IMU clock; those that swap two IMU packets are dropped as reordered.
        assert drops["reordered"] <= injected["reordered"] and link["lost"] == 0
    elif kind == "corrupt":
        assert injected["corrupted"] > 0 and conn["bad_crc"] == injected["corrupted"]
        assert link["lost"] == injected["corrupted"]
    elif kind == "truncate":
        assert injected["truncated"] > 0 and conn["truncated"] == injected["truncated"]
        assert link["lost"] == injected["truncated"]
    elif kind == "time_jump":
        # Each step forward is adopted after a second of consistent stamps; the samples
        # held meanwhile are used then, so nothing is dropped.
        assert injected["time_jumps"] > 0 and flags["resync"] == injected["time_jumps"]
        assert drops == dict.fromkeys(drops, 0) and flags["reinit"] == 0
    elif kind == "time_backwards":
        # A 50 ms step back drops the samples stamped within the 50 ms already covered
        # (49 earlier stamps, one equal); then the stream overtakes the old timeline.
        per_step = round(FaultConfig().time_backwards_s * EmulatorConfig().imu_rate_hz)
        assert injected["time_backwards"] > 0 and flags["resync"] == 0
        assert drops["reordered"] + drops["backwards"] == per_step * injected["time_backwards"]
    elif kind == "saturation":
        assert injected["saturated_samples"] > 0
        assert flags["gyro_saturated"] + flags["acc_saturated"] == injected["saturated_samples"]
    elif kind == "stuck":
        assert injected["stuck_samples"] > 0
        assert flags["stuck"] == injected["stuck_samples"]
    elif kind == "mag_disturbance":
        assert injected["mag_disturbances"] > 0 and flags["mag_disturbed"] > 0
    elif kind == "vibration":
        assert injected["vibration_samples"] > 0
    elif kind == "gyro_bias_step":
        assert injected["gyro_bias_steps"] > 0


#: Faults that end and that the bridge itself handles (drops, holds, resyncs): the
#: output must be back on the fault-free estimate shortly after.
RECOVERY_CHECKED = {"loss", "duplicate", "reorder", "corrupt", "truncate", "time_jump",
                    "time_backwards", "saturation", "stuck"}


def mag_disturbed_until(rec) -> np.ndarray:
    """Per IMU sample: board time [s] at which the magnet seen so far went away (-inf
    before the first one). A calibrated board reads the Earth's field to a few mG, the
    injected magnet is 0.6 G: a reading 0.2 G off the true field is disturbed."""
    disturbed = np.linalg.norm(rec.mag - rec.truth_mag, axis=1) > 0.2
    t = rec.time_us * 1e-6
    ends = np.where(disturbed, t, -np.inf)
    return np.maximum.accumulate(ends)


def check_against_truth(kind: str, cfg: EmulatorConfig, listener: UdpListener,
                        status: dict) -> None:
    """Faults that change what the sensors measure, judged against the truth."""
    rec = simulate(cfg)  # the same seed: the same faults, with their timing
    est, ref, stamps = truth_at_outputs(listener)
    t = stamps * 1e-3
    t0 = rec.time_us[0] * 1e-6
    err = np.degrees(Q.angle_between(est, ref))
    if kind == "vibration":
        # Vibration never ends: after the same 10 s of convergence as the fault-free
        # flight, the attitude stays within 2°.
        late = t >= t0 + 10.0
        assert late.sum() > 150 and err[late].max() < 2.0, err[late].max()
    elif kind == "mag_disturbance":
        # Each magnet lasts 1 s: 2 s after it went away (and after 5 s on the ground,
        # where the filters start), the attitude is within 2°.
        assert rec.faults.mag_disturbances == status["injected"]["mag_disturbances"]
        rec_t = rec.time_us * 1e-6
        at = np.clip(np.searchsorted(rec_t, t, side="right") - 1, 0, len(rec_t) - 1)
        until = mag_disturbed_until(rec)[at]
        judged = (t >= until + 2.0) & (t >= t0 + 5.0)
        assert judged.sum() > 100
        assert err[judged].max() < 2.0, err[judged].max()
        # After the same 10 s of convergence as the fault-free flight: within 2° whether
        # a magnet is present or not (it is rejected).
        assert err[t >= t0 + 10.0].max() < 2.0
    elif kind == "gyro_bias_step":
        # NOT a recovery check: a 5 °/s step shows only through the slowly filtered
        # attitude errors and eskf does not yet learn it reliably in flight (see the
        # issue note); the bridge must keep running, finite, and count the steps.
        assert np.all(np.isfinite(est))


@pytest.mark.parametrize("kind", list(FAULTS))
@async_test
async def test_fault_is_counted_and_estimate_recovers(kind):
    duration = FAULT_DURATION_S.get(kind, 10.0)
    cfg = EmulatorConfig(profile="flight", duration_s=duration, seed=5, fast=True,
                         faults=FAULTS[kind], **CALIBRATED)
    listener, stats, status = await run_emulator_through_bridge(
        cfg, estimators=[FAULT_ESTIMATOR.get(kind, PRIMARY)])
    rec, q_offline = offline_run(cfg)
    status["injected"] = stats.faults.to_dict()
    check_counts(kind, status["injected"], status)
    if kind.startswith("time_"):
        est, ref = offline_by_sample_order(listener, q_offline)
    else:
        est, _, stamps = truth_at_outputs(listener)
        offline = dict(zip((rec.time_us // 1000).tolist(), q_offline, strict=True))
        keep = np.array([t in offline for t in stamps])
        est, ref = est[keep], np.array([offline[t] for t in stamps[keep]])
    assert len(est) > 0.5 * duration * 50
    assert np.all(np.isfinite(est))
    dev = np.degrees(Q.angle_between(est, ref))
    if kind in RECOVERY_CHECKED:
        # Faults here are short and sparse, so the last second of the run lies 2 s or
        # more after nearly all of them: by then the output is back on the estimate.
        assert np.max(dev[-50:]) < 2.0, (kind, dev[-50:].max())
    else:
        check_against_truth(kind, cfg, listener, status)


#: Hand-held profiles of a board that says quadrotor: emulator -> bridge, product
#: defaults (the primary estimator with the model the bridge picks), whole stream
#: scored against the truth. Measured total 0.355°, 0.475°, 0.454° (0.56°, 0.67°, 0.53°
#: before the start-up rest); gates 1.5x that (the product target for a hand-held board
#: is 1.0°).
HAND_HELD = [("tilt", 15.0, 0.53), ("gentle", 15.0, 0.71), ("calibration", 15.0, 0.68)]


@pytest.mark.parametrize("profile, seconds, gate", HAND_HELD)
def test_a_quadrotor_carried_by_hand_through_the_bridge(profile, seconds, gate):
    """The emulator says quadrotor but is disarmed on the ground: the bridge must not run
    the rotor-drag model (which read the hand's tilts as flight: 13.7° on `tilt`)."""
    cfg = EmulatorConfig(profile=profile, duration_s=seconds, seed=1, fast=True, **CALIBRATED)
    listener, _, _ = asyncio.run(run_emulator_through_bridge(cfg, estimators=[]))
    est, ref, _ = truth_at_outputs(listener)
    assert len(est) > 0.9 * seconds * 50.0
    err = metrics.rms_errors(est, ref)
    assert err.total_deg < gate, (profile, err)
