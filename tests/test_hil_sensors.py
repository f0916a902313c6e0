"""Register-level golden values of the emulated GY-86 chips (datasheet numbers)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil.sensors import hmc5883l, mpu6050, ms5611
from hil.sensors.dlpf import LowPass
from imu import boards

# ---- MPU6050 ------------------------------------------------------------------------


def test_mpu6050_sensitivities_and_ranges_match_the_datasheet():
    assert mpu6050.WHO_AM_I == 0x68
    assert mpu6050.GYRO_LSB_PER_DPS == (131.0, 65.5, 32.8, 16.4)
    assert mpu6050.ACCEL_LSB_PER_G == (16384.0, 8192.0, 4096.0, 2048.0)
    # 1 °/s at FS_SEL=3 and 1 g at AFS_SEL=2 (the GY-86 defaults)
    assert mpu6050.to_counts(np.array([1.0]), 16.4)[0] == 16
    assert mpu6050.to_counts(np.array([1.0]), 4096.0)[0] == 4096
    assert mpu6050.to_counts(np.array([-250.0]), 131.0)[0] == -32750


def test_mpu6050_saturates_at_int16_limits():
    counts = mpu6050.to_counts(np.array([2100.0, -2100.0, 1990.0]), 16.4)
    assert counts.tolist() == [32767, -32768, 32636]
    assert counts.dtype == np.int16


def test_mpu6050_temperature_formula():
    # Temperature in °C = TEMP_OUT / 340 + 36.53
    assert mpu6050.temperature_c(np.array([0]))[0] == pytest.approx(36.53)
    assert mpu6050.temperature_c(np.array([-521]))[0] == pytest.approx(-521 / 340 + 36.53)
    raw = mpu6050.temperature_raw(np.array([25.0]))
    assert raw[0] == round((25.0 - 36.53) * 340) == -3920


def test_mpu6050_burst_is_big_endian_accel_temp_gyro():
    data = mpu6050.burst_bytes(np.array([1, -2, 4096]), -3920, np.array([16, 0, -32768]))
    assert data.hex() == "0001fffe1000f0b0001000008000"
    acc, temp, gyr = mpu6050.parse_burst(data)
    assert acc.tolist() == [1, -2, 4096] and temp == -3920 and gyr.tolist() == [16, 0, -32768]
    with pytest.raises(ValueError):
        mpu6050.parse_burst(data[:13])


@pytest.mark.parametrize(("rate", "cfg", "div", "actual"), [
    (8000.0, 0, 0, 8000.0), (4000.0, 0, 1, 4000.0), (1000.0, 1, 0, 1000.0),
    (500.0, 1, 1, 500.0), (200.0, 2, 4, 200.0), (100.0, 3, 9, 100.0), (50.0, 4, 19, 50.0)])
def test_mpu6050_rate_selects_dlpf_and_divider(rate, cfg, div, actual):
    assert mpu6050.configure_for_rate(rate) == (cfg, div)
    assert mpu6050.sample_rate(cfg, div) == actual
    # the DLPF bandwidth stays below Nyquist whenever the DLPF is on
    if cfg:
        assert mpu6050.DLPF_TABLE[cfg][2] < actual / 2


def test_mpu6050_rejects_impossible_rates():
    for bad in (0.0, -1.0, 9000.0, math.nan):
        with pytest.raises(ValueError):
            mpu6050.configure_for_rate(bad)


@pytest.mark.parametrize("cfg", range(1, 7))
@pytest.mark.parametrize("sensor", ["accel", "gyro"])
def test_dlpf_low_frequency_delay_matches_datasheet(cfg, sensor):
    """A slow ramp comes out late by the datasheet's delay (within a sample)."""
    acc_bw, acc_delay_ms, gyr_bw, gyr_delay_ms = mpu6050.DLPF_TABLE[cfg]
    bw, delay_ms = (acc_bw, acc_delay_ms) if sensor == "accel" else (gyr_bw, gyr_delay_ms)
    fs = 1000.0
    lpf = LowPass(bw, delay_ms * 1e-3, fs, axes=1)
    t = np.arange(4000) / fs
    y = lpf(t[:, None])[:, 0]
    lag = np.mean(t[2000:] - y[2000:])  # a ramp's steady-state lag is the group delay
    assert lag == pytest.approx(delay_ms * 1e-3, abs=0.6 / fs)


@pytest.mark.parametrize("cfg", range(1, 5))
def test_dlpf_bandwidth_matches_datasheet(cfg):
    """A sine at the listed gyro bandwidth comes out at about -3 dB."""
    bw, delay_ms = mpu6050.DLPF_TABLE[cfg][2:]
    fs = 1000.0
    t = np.arange(8000) / fs
    y = LowPass(bw, delay_ms * 1e-3, fs, axes=1)(np.sin(2 * np.pi * bw * t)[:, None])[:, 0]
    gain = math.sqrt(2.0) * y[4000:].std()
    assert abs(gain - 1.0 / math.sqrt(2.0)) < 0.05


def test_dlpf_chunked_equals_whole():
    x = np.random.default_rng(1).normal(size=(1000, 3))
    whole = LowPass(44.0, 4.9e-3, 1000.0)(x)
    lpf = LowPass(44.0, 4.9e-3, 1000.0)
    parts = np.concatenate([lpf(x[:333]), lpf(x[333:700]), lpf(x[700:])])
    assert np.array_equal(whole, parts)


def test_constants_agree_with_the_bridge_board_profile():
    """hil must not import bridge, so the datasheet tables live twice; keep them equal."""
    assert boards.MPU6050_GYRO_LSB_PER_DPS == mpu6050.GYRO_LSB_PER_DPS
    assert boards.MPU6050_ACCEL_LSB_PER_G == mpu6050.ACCEL_LSB_PER_G
    assert boards.MPU6050_GYRO_RANGE_DPS == mpu6050.GYRO_RANGE_DPS
    assert boards.MPU6050_ACCEL_RANGE_G == mpu6050.ACCEL_RANGE_G
    assert boards.HMC5883L_LSB_PER_GAUSS == hmc5883l.LSB_PER_GAUSS
    assert boards.HMC5883L_OVERFLOW == hmc5883l.OVERFLOW
    defaults = mpu6050.Mpu6050Config()
    assert (defaults.fs_sel, defaults.afs_sel) == (boards.DEFAULT_FS_SEL, boards.DEFAULT_AFS_SEL)
    assert hmc5883l.Hmc5883lConfig().gain == boards.DEFAULT_HMC_GAIN


# ---- HMC5883L -----------------------------------------------------------------------


def test_hmc5883l_gains_and_overflow():
    assert hmc5883l.IDENTIFICATION == b"H43"
    assert hmc5883l.LSB_PER_GAUSS[1] == 1090.0
    counts = hmc5883l.to_counts(np.array([[0.5, -1.0, 1.9]]), 1090.0)
    assert counts.tolist() == [[545, -1090, -4096]]  # 1.9 G * 1090 > 2047: overflow
    # the output range is -2048..2047: both ends still valid, one count beyond overflows
    counts = hmc5883l.to_counts(np.array([[-2048, 2047, 2048]]) / 1090.0, 1090.0)
    assert counts.tolist() == [[-2048, 2047, -4096]]


def test_hmc5883l_registers_are_x_z_y():
    data = hmc5883l.data_bytes(np.array([1, 2, -3]))
    assert data.hex() == "0001fffd0002"
    assert hmc5883l.parse_data(data).tolist() == [1, 2, -3]


def test_hmc5883l_rates_and_gains_are_validated():
    assert hmc5883l.Hmc5883lConfig().rate_hz == 15.0
    with pytest.raises(ValueError):
        hmc5883l.Hmc5883lConfig(rate_hz=100.0)
    with pytest.raises(ValueError):
        hmc5883l.Hmc5883lConfig(gain=8)


def test_hmc5883l_hard_and_soft_iron():
    cfg = hmc5883l.Hmc5883lConfig(noise_mgauss=0.0, scale_error=0.0,
                                  hard_iron_gauss=(0.1, 0.0, -0.2),
                                  soft_iron=((1.1, 0.0, 0.0), (0.0, 0.9, 0.0), (0.0, 0.0, 1.0)))
    chip = hmc5883l.Hmc5883l(cfg, np.random.default_rng(0))
    counts = chip.measure(np.array([[0.5, 0.5, 0.5]]), np.random.default_rng(0))
    assert counts.tolist() == [[round(0.65 * 1090), round(0.45 * 1090), round(0.3 * 1090)]]


# ---- MS5611 -------------------------------------------------------------------------


def test_ms5611_datasheet_example():
    c = (40127, 36924, 23317, 23282, 33464, 28312)
    out = ms5611.compensate(c, 9085466, 8569150)
    assert (out.temp_cdeg, out.pressure_pa) == (2007, 100009)


def test_ms5611_prom_crc():
    # AN520's example PROM has CRC 0xB
    assert ms5611.crc4([0x3132, 0x3334, 0x3536, 0x3738, 0x3940, 0x4142, 0x4344, 0x4500]) == 0xB
    prom = ms5611.make_prom(ms5611.DATASHEET_C, factory=0x1234)
    assert ms5611.check_prom(prom) == ms5611.DATASHEET_C
    damaged = (prom[0], prom[1] ^ 0x0100, *prom[2:])
    with pytest.raises(ValueError, match="CRC"):
        ms5611.check_prom(damaged)


@pytest.mark.parametrize(("pressure", "temp_c"), [
    (100009.0, 20.07), (101325.0, 25.3), (90000.0, 5.0), (70000.0, -30.0), (120000.0, 60.0)])
def test_ms5611_raw_words_invert_the_compensation(pressure, temp_c):
    """D1/D2 from truth, compensated on the board, give the truth back (to 1 count),
    including the second-order branch below 20 °C and -15 °C."""
    d1, d2 = ms5611.raw_from_true(ms5611.DATASHEET_C, pressure, temp_c)
    assert 0 <= d1 < 1 << 24 and 0 <= d2 < 1 << 24
    out = ms5611.compensate(ms5611.DATASHEET_C, d1, d2)
    assert abs(out.temp_cdeg - temp_c * 100) <= 1
    assert abs(out.pressure_pa - pressure) <= 1


def _nearest_by_bisection(f, target: float) -> int:
    """The plain search over the whole 24-bit range: the reference for the fast one."""
    lo, hi = 0, ms5611.ADC_MAX
    while lo < hi:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if f(mid) >= target else (mid + 1, hi)
    if lo > 0 and abs(f(lo - 1) - target) <= abs(f(lo) - target):
        return lo - 1
    return lo


@pytest.mark.parametrize("temp_c", [-60.0, -40.0, -16.0, 0.0, 19.99, 20.0, 45.0, 85.0, 150.0,
                                    math.nan])
@pytest.mark.parametrize("pressure", [0.0, 1000.0, 30000.0, 101325.0, 120000.0, 5e6, math.nan])
def test_ms5611_words_from_the_first_order_guess_are_the_whole_range_search(pressure,
                                                                             temp_c):
    """The emulator's search starts from the first-order inverse; it finds the words the
    whole-range bisection finds, to the range's ends (words 0 and 2^24 - 1), and for a
    value that is no number (where both end at the top of the range, without an error)."""
    c = ms5611.DATASHEET_C
    d2 = _nearest_by_bisection(lambda x: ms5611.compensate(c, 0, x).temp_cdeg, temp_c * 100)
    d1 = _nearest_by_bisection(lambda x: ms5611.compensate(c, x, d2).pressure_pa, pressure)
    assert ms5611.raw_from_true(c, pressure, temp_c) == (d1, d2)


def test_ms5611_second_order_matters_when_cold():
    d1, d2 = ms5611.raw_from_true(ms5611.DATASHEET_C, 90000.0, -20.0)
    first = ms5611.compensate(ms5611.DATASHEET_C, d1, d2, second_order=False)
    assert abs(first.temp_cdeg - (-2000)) > 100  # the first-order result is far off


@pytest.mark.parametrize("rate_hz", [250.0, 1000.0])
def test_mpu6050_never_repeats_a_reading_from_the_start(rate_hz):
    """A running chip's delay line holds earlier, different readings: the first samples
    are no copies of each other (a listener counting repeats as a stuck sensor must see
    none in a fault-free stream)."""
    from hil import EmulatorConfig, simulate

    rec = simulate(EmulatorConfig(profile="static", duration_s=1.0, seed=3, rate_hz=rate_hz))
    raw = np.hstack([rec.gyr_counts, rec.acc_counts])
    assert not np.any(np.all(raw[1:] == raw[:-1], axis=1))
