"""The emulated board's readings, straight from ``simulate`` (no sockets)."""

from __future__ import annotations

import math
from dataclasses import fields, replace

import numpy as np
import pytest
from scipy import signal

from estimators import quat
from hil import EmulatorConfig, FaultConfig, simulate
from hil.environment import G
from hil.gps import GpsConfig
from hil.motion import TILT_PITCH_DEG, TILT_ROLL_DEG
from hil.recording import Recording
from hil.sensors.hmc5883l import Hmc5883lConfig
from hil.sensors.mpu6050 import Mpu6050Config
from hil.source import TRUTH_AHEAD_S, SampleSource

#: A chip without fixed errors, to see one effect at a time.
IDEAL_MPU = Mpu6050Config(gyro_offset_dps=0.0, accel_offset_mg=0.0, gyro_bias_walk_dps_rts=0.0,
                          accel_bias_walk_mg_rts=0.0, scale_error=0.0, cross_axis=0.0)


def test_same_seed_same_samples_other_seed_other_samples():
    cfg = EmulatorConfig(profile="flight", rate_hz=500.0, duration_s=2.0, seed=7)
    a, b = simulate(cfg), simulate(cfg)
    c = simulate(replace(cfg, seed=8))
    for name in ("gyr_counts", "acc_counts", "mag_counts", "temp_raw", "time_us", "baro_d1"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.gyr_counts, c.gyr_counts)
    assert np.array_equal(a.truth_q, c.truth_q)  # the motion does not depend on the seed


@pytest.mark.parametrize("profile, rate_hz, duration_s", [
    ("handheld_flight", 250.0, 48.0),  # hand -> flight switch, take-offs, touchdown
    ("aggressive", 1000.0, 7.3),       # a run that ends inside a truth block
])
def test_truth_evaluated_ahead_gives_the_same_samples(profile, rate_hz, duration_s):
    """Evaluating the motion a second ahead (the default) instead of chunk by chunk
    changes no sample, no truth and no fault, to the bit (the sign of a zero included)."""
    faults = FaultConfig(vibration_g=0.2, vibration_dps=2.0, vibration_hz=90.0,
                         mag_disturbance_rate_hz=0.5, mag_disturbance_gauss=0.3,
                         mag_disturbance_duration_s=0.4, gyro_bias_step_rate_hz=0.3,
                         gyro_bias_step_dps=1.0, time_jump_rate_hz=0.2, time_jump_s=0.5)
    cfg = EmulatorConfig(profile=profile, rate_hz=rate_hz, duration_s=duration_s, seed=11,
                         faults=faults, gps=GpsConfig())

    def chunks(truth_ahead_s: float) -> list[Recording]:
        source = SampleSource(cfg, truth_ahead_s=truth_ahead_s)
        out = []
        while not source.finished:
            out.append(source.chunk())
        return out

    ahead, per_chunk = chunks(TRUTH_AHEAD_S), chunks(0.0)
    assert len(ahead) == len(per_chunk) > 100
    for a, b in zip(ahead, per_chunk, strict=True):
        for f in fields(Recording):
            x, y = getattr(a, f.name), getattr(b, f.name)
            if isinstance(x, np.ndarray):
                assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), f.name
                if x.dtype.kind == "f":
                    assert np.array_equal(np.signbit(x), np.signbit(y)), f.name
            else:
                assert x == y, f.name


def test_rates_of_each_chip_and_clock():
    rec = simulate(EmulatorConfig(profile="static", rate_hz=1000.0, duration_s=4.0,
                                  clock_drift_ppm=100.0))
    assert len(rec) == 4000
    assert rec.mag_updated.sum() == 60  # HMC5883L at 15 Hz
    assert len(rec.baro_t_s) == 200  # MS5611 at 50 Hz
    steps = np.diff(rec.time_us)
    assert np.all(steps > 0)
    # the crystal runs 100 ppm fast: 4 s of true time read 400 µs longer on the board
    assert rec.time_us[-1] - rec.time_us[0] == round(3.999 * 1e6 * (1 + 100e-6))
    assert rec.time_us[0] == 2_000_000  # first sample 2 s after boot


def test_8khz_uses_unfiltered_gyro_and_1khz_accelerometer():
    rec = simulate(EmulatorConfig(profile="flight", rate_hz=8000.0, duration_s=0.5))
    assert np.all(np.diff(rec.time_us) == 125)
    acc = rec.acc_counts
    # the accelerometer register only changes every 8th sample (1 kHz)
    changes = np.flatnonzero(np.any(acc[1:] != acc[:-1], axis=1)) + 1
    assert np.all(changes % 8 == 0) and len(changes) > 400
    assert np.any(rec.gyr_counts[1:] != rec.gyr_counts[:-1])


def test_static_level_board_reads_gravity_up_and_the_earth_field():
    rec = simulate(EmulatorConfig(profile="static", duration_s=2.0, mpu6050=IDEAL_MPU))
    # chip axes are RFU: z up reads +1 g = +4096 counts at AFS_SEL=2
    assert np.mean(rec.acc_counts[:, 2]) == pytest.approx(4096, abs=2)
    assert np.allclose(np.mean(rec.acc, axis=0), [0, 0, -G], atol=0.01)
    assert np.allclose(np.mean(rec.gyr, axis=0), 0.0, atol=math.radians(0.02))
    mag = np.mean(rec.mag, axis=0)
    angle = math.degrees(math.acos(np.dot(mag, rec.truth_mag[0])
                                   / np.linalg.norm(mag) / np.linalg.norm(rec.truth_mag[0])))
    assert angle < 1.5  # gain errors are 1 % per axis
    assert np.all(np.abs(rec.temperature_c - 25.0) < 0.5)


def test_tilt_accelerometer_angles():
    rec = simulate(EmulatorConfig(profile="tilt", duration_s=2.0, mpu6050=IDEAL_MPU))
    f = np.mean(rec.acc, axis=0)
    assert math.degrees(math.atan2(-f[1], -f[2])) == pytest.approx(TILT_ROLL_DEG, abs=0.05)
    assert math.degrees(math.asin(f[0] / np.linalg.norm(f))) == pytest.approx(TILT_PITCH_DEG,
                                                                             abs=0.05)
    roll, pitch, _ = np.degrees(quat.to_euler(rec.truth_q[0]))
    assert (roll, pitch) == (pytest.approx(TILT_ROLL_DEG), pytest.approx(TILT_PITCH_DEG))


def test_gyro_follows_truth_in_aggressive_flips():
    rec = simulate(EmulatorConfig(profile="aggressive", duration_s=12.0, mpu6050=IDEAL_MPU))
    delay = 2  # samples: DLPF_CFG 1 is 1.9 ms at 1 kHz
    err = rec.gyr[delay:] - rec.truth_rates[:-delay]
    assert np.degrees(np.abs(rec.truth_rates).max()) > 600.0
    assert np.degrees(np.sqrt(np.mean(err**2))) < 3.0


def test_ranges_saturate_and_magnetometer_overflows():
    cfg = EmulatorConfig(profile="aggressive", duration_s=3.0,
                         mpu6050=replace(IDEAL_MPU, fs_sel=0),  # ±250 °/s
                         hmc5883l=Hmc5883lConfig(hard_iron_gauss=(1.9, 0.0, 0.0)))
    rec = simulate(cfg)
    assert np.any(rec.gyr_counts == 32767) or np.any(rec.gyr_counts == -32768)
    assert np.all(rec.gyr_counts.astype(int) <= 32767)
    over = np.any(rec.mag_counts == -4096, axis=1)
    assert over.any()
    assert np.all(np.isnan(rec.mag[over])) and np.all(np.isfinite(rec.mag[~over]))


def _band_psd(x: np.ndarray, fs: float, lo: float, hi: float) -> np.ndarray:
    f, p = signal.welch(x, fs=fs, nperseg=1024, axis=0)
    band = (f >= lo) & (f <= hi)
    return p[band].mean(axis=0)


def test_noise_density_matches_configuration():
    """Below the DLPF bandwidth the output PSD is the configured white-noise density."""
    mpu = replace(IDEAL_MPU, fs_sel=0, afs_sel=0, gyro_noise_dps_rthz=0.005,
                  accel_noise_ug_rthz=400.0)
    rec = simulate(EmulatorConfig(profile="static", rate_hz=1000.0, duration_s=30.0, seed=3,
                                  mpu6050=mpu))
    gyro_psd = _band_psd(rec.gyr, 1000.0, 2.0, 40.0)
    accel_psd = _band_psd(rec.acc, 1000.0, 2.0, 40.0)
    expected_gyro = math.radians(0.005) ** 2  # (rad/s)^2/Hz
    expected_accel = (400e-6 * G) ** 2  # (m/s^2)^2/Hz
    assert np.all(np.abs(gyro_psd / expected_gyro - 1.0) < 0.10)
    assert np.all(np.abs(accel_psd / expected_accel - 1.0) < 0.10)


def test_barometer_follows_altitude():
    # the flight profile stands 5 s on the ground, then climbs 10 m in 5 s
    rec = simulate(EmulatorConfig(profile="flight", duration_s=11.0))
    assert np.all(np.abs(rec.pressure_pa - rec.truth_pressure_pa) < 8.0)  # 1.2 Pa rms noise
    assert rec.pressure_pa[0] - rec.pressure_pa[-1] > 100.0  # climbed 10 m (~120 Pa)
    board_c = EmulatorConfig().environment.board_temperature(rec.baro_t_s)
    assert np.all(np.abs(rec.baro_temp_cdeg - board_c * 100.0) <= 2)  # 0.002 °C rms noise


def test_sensor_faults_are_counted_in_simulate():
    faults = FaultConfig(saturation_rate_hz=2.0, stuck_rate_hz=1.0, gyro_bias_step_rate_hz=1.0,
                         mag_disturbance_rate_hz=0.5, vibration_g=0.2, time_jump_rate_hz=0.5)
    rec = simulate(EmulatorConfig(profile="static", duration_s=10.0, seed=2, faults=faults))
    c = rec.faults
    assert c.saturation_events > 0 and c.stuck_events > 0 and c.gyro_bias_steps > 0
    assert c.mag_disturbances > 0 and c.time_jumps > 0
    assert c.vibration_samples == len(rec)
    assert c.lost == 0  # link faults only happen on a link


@pytest.mark.parametrize("kwargs", [
    {"rate_hz": 9000.0}, {"duration_s": -1.0}, {"imu_message": "ATTITUDE"}, {"sysid": 0},
    {"clock_jitter_us": 600.0}, {"truth_rate_hz": 2000.0}])
def test_bad_configuration_is_a_clear_error(kwargs):
    with pytest.raises(ValueError):
        EmulatorConfig(**kwargs)


def test_bad_fault_settings_are_rejected():
    with pytest.raises(ValueError):
        FaultConfig(loss=-0.1)
    with pytest.raises(ValueError):
        FaultConfig(loss=0.6, corrupt=0.6)
    with pytest.raises(ValueError):
        simulate(EmulatorConfig(duration_s=None))
