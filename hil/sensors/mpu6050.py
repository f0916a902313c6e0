"""MPU6050 6-axis IMU: from true rate and specific force to the register counts.

Numbers from the MPU-6000/6050 Product Specification rev 3.4 and Register Map rev 4.2:
sensitivities per FS_SEL / AFS_SEL, DLPF_CFG bandwidths and delays, the sample-rate
divider, rate noise spectral density 0.005 °/s/√Hz, accelerometer noise 400 µg/√Hz,
zero-rate offset (±20 °/s), zero-g offset (±50 mg X/Y, ±80 mg Z), sensitivity tolerance
(±3 %), cross-axis sensitivity (±2 %), and Temperature [°C] = raw / 340 + 36.53.

Inputs are in the chip's own axes (on the GY-86: X right, Y forward, Z up). Outputs are
the int16 values of ACCEL_XOUT..GYRO_ZOUT as the STM32 reads them: quantised, and
clipped at the int16 limits when the signal exceeds full scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .dlpf import LowPass

WHO_AM_I = 0x68
REG_ACCEL_XOUT_H = 0x3B  # 14-byte burst: accel XYZ, temperature, gyro XYZ (big-endian)
GYRO_LSB_PER_DPS = (131.0, 65.5, 32.8, 16.4)
GYRO_RANGE_DPS = (250.0, 500.0, 1000.0, 2000.0)
ACCEL_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)
ACCEL_RANGE_G = (2.0, 4.0, 8.0, 16.0)
#: DLPF_CFG 0..6: (accel bandwidth Hz, accel delay ms, gyro bandwidth Hz, gyro delay ms).
DLPF_TABLE = (
    (260.0, 0.0, 256.0, 0.98),
    (184.0, 2.0, 188.0, 1.9),
    (94.0, 3.0, 98.0, 2.8),
    (44.0, 4.9, 42.0, 4.8),
    (21.0, 8.5, 20.0, 8.3),
    (10.0, 13.8, 10.0, 13.4),
    (5.0, 19.0, 5.0, 18.6),
)
ACCEL_OUTPUT_RATE_HZ = 1000.0  # the accelerometer always updates at 1 kHz
INT16_MIN, INT16_MAX = -32768, 32767
TEMP_LSB_PER_C = 340.0
TEMP_OFFSET_C = 36.53
G = 9.80665


def gyro_output_rate(dlpf_cfg: int) -> float:
    """Gyroscope output rate: 8 kHz with the DLPF off (CFG 0 or 7), else 1 kHz."""
    return 8000.0 if dlpf_cfg in (0, 7) else 1000.0


def sample_rate(dlpf_cfg: int, smplrt_div: int) -> float:
    """Register 25: Sample Rate = Gyroscope Output Rate / (1 + SMPLRT_DIV)."""
    return gyro_output_rate(dlpf_cfg) / (1 + smplrt_div)


def configure_for_rate(rate_hz: float) -> tuple[int, int]:
    """(DLPF_CFG, SMPLRT_DIV) giving the achievable rate nearest to rate_hz.

    Above 1 kHz only the unfiltered 8 kHz path exists. At or below 1 kHz the firmware
    picks the widest DLPF whose gyro bandwidth stays below Nyquist (anti-aliasing).
    """
    if not (math.isfinite(rate_hz) and 3.9 <= rate_hz <= 8000.0):
        raise ValueError(f"IMU rate must be between 3.9 and 8000 Hz, got {rate_hz}")
    if rate_hz > 1000.0:
        return 0, max(0, round(8000.0 / rate_hz) - 1)
    div = min(255, max(0, round(1000.0 / rate_hz) - 1))
    nyquist = sample_rate(1, div) / 2.0
    cfg = next((c for c in range(1, 7) if DLPF_TABLE[c][2] < nyquist), 6)
    return cfg, div


def temperature_raw(temp_c: np.ndarray) -> np.ndarray:
    """TEMP_OUT register value for a die temperature."""
    raw = np.round((np.asarray(temp_c, dtype=float) - TEMP_OFFSET_C) * TEMP_LSB_PER_C)
    return np.clip(raw, INT16_MIN, INT16_MAX).astype(np.int16)


def temperature_c(raw: np.ndarray) -> np.ndarray:
    """Die temperature [°C] from TEMP_OUT (datasheet formula)."""
    return np.asarray(raw, dtype=float) / TEMP_LSB_PER_C + TEMP_OFFSET_C


def to_counts(value: np.ndarray, lsb_per_unit: float) -> np.ndarray:
    """Quantise to int16 register counts, clipping at the limits (saturation)."""
    return np.clip(np.round(value * lsb_per_unit), INT16_MIN, INT16_MAX).astype(np.int16)


def burst_bytes(acc: np.ndarray, temp: int, gyr: np.ndarray) -> bytes:
    """The 14 bytes read from ACCEL_XOUT_H: big-endian int16 accel XYZ, temp, gyro XYZ."""
    values = np.array([*acc, temp, *gyr], dtype=">i2")
    return values.tobytes()


def parse_burst(data: bytes) -> tuple[np.ndarray, int, np.ndarray]:
    """Inverse of burst_bytes, as the STM32 firmware decodes the I2C read."""
    if len(data) != 14:
        raise ValueError(f"MPU6050 burst is 14 bytes, got {len(data)}")
    v = np.frombuffer(data, dtype=">i2").astype(np.int16)
    return v[0:3], int(v[3]), v[4:7]


@dataclass(frozen=True)
class Mpu6050Config:
    """Register settings and error magnitudes (1-sigma unless said otherwise)."""

    fs_sel: int = 3  # ±2000 °/s
    afs_sel: int = 2  # ±8 g
    dlpf_cfg: int = 1
    smplrt_div: int = 0
    gyro_noise_dps_rthz: float = 0.005  # datasheet rate noise spectral density
    accel_noise_ug_rthz: float = 400.0  # datasheet power spectral density
    gyro_offset_dps: float = 1.0  # residual zero-rate offset (datasheet bound ±20 °/s)
    accel_offset_mg: float = 20.0  # zero-g offset (datasheet bound ±50 / ±80 mg)
    gyro_bias_walk_dps_rts: float = 0.002  # bias random walk [°/s/√s] (not in datasheet)
    accel_bias_walk_mg_rts: float = 0.02  # [mg/√s] (not in datasheet)
    scale_error: float = 0.01  # sensitivity error (datasheet ±3 %)
    cross_axis: float = 0.005  # cross-axis sensitivity (datasheet ±2 %)

    def __post_init__(self) -> None:
        if self.fs_sel not in range(4) or self.afs_sel not in range(4):
            raise ValueError("FS_SEL and AFS_SEL are 0..3")
        if self.dlpf_cfg not in range(7) or self.smplrt_div not in range(256):
            raise ValueError("DLPF_CFG is 0..6 and SMPLRT_DIV 0..255")

    @property
    def rate_hz(self) -> float:
        return sample_rate(self.dlpf_cfg, self.smplrt_div)

    @property
    def internal_rate_hz(self) -> float:
        return gyro_output_rate(self.dlpf_cfg)

    @property
    def decimation(self) -> int:
        return 1 + self.smplrt_div

    @property
    def gyro_lsb_per_dps(self) -> float:
        return GYRO_LSB_PER_DPS[self.fs_sel]

    @property
    def accel_lsb_per_g(self) -> float:
        return ACCEL_LSB_PER_G[self.afs_sel]


def _error_matrix(rng: np.random.Generator, scale: float, cross: float) -> np.ndarray:
    """Sensitivity (diagonal) and cross-axis (off-diagonal) errors of one triad."""
    m = np.eye(3) + np.diag(rng.normal(0.0, scale, 3))
    off = rng.normal(0.0, cross, (3, 3))
    np.fill_diagonal(off, 0.0)
    return m + off


class Mpu6050:
    """One emulated chip. Its fixed errors are drawn once from ``rng`` at power-up."""

    def __init__(self, config: Mpu6050Config, rng: np.random.Generator):
        self.config = config
        c = config
        self.gyro_matrix = _error_matrix(rng, c.scale_error, c.cross_axis)
        self.accel_matrix = _error_matrix(rng, c.scale_error, c.cross_axis)
        self.gyro_offset_dps = rng.normal(0.0, c.gyro_offset_dps, 3)
        self.accel_offset_g = rng.normal(0.0, c.accel_offset_mg * 1e-3, 3)
        self._gyro_walk = np.zeros(3)
        self._accel_walk = np.zeros(3)
        fs = c.internal_rate_hz
        acc_bw, acc_delay, gyr_bw, gyr_delay = DLPF_TABLE[c.dlpf_cfg]
        self._gyro_lpf = LowPass(gyr_bw, gyr_delay * 1e-3, fs)
        self._accel_lpf = LowPass(acc_bw, acc_delay * 1e-3, fs)
        self._accel_hold = max(1, round(fs / ACCEL_OUTPUT_RATE_HZ))
        self._internal_index = 0

    def measure(self, rate_dps: np.ndarray, accel_g: np.ndarray, temp_c: np.ndarray,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Counts (gyro, accel, temperature) at the output rate.

        ``rate_dps`` [°/s] and ``accel_g`` [g] are true values in chip axes at the
        internal rate; their length must be a multiple of the decimation, and only the
        last chunk may end between two 1 kHz accelerometer updates.
        """
        c = self.config
        n = len(rate_dps)
        dec = c.decimation
        if n % dec or self._internal_index % self._accel_hold:
            raise ValueError("chunks must hold whole output samples and start on a 1 kHz "
                             "accelerometer update")
        fs = c.internal_rate_hz
        dt = 1.0 / fs
        white_g = c.gyro_noise_dps_rthz * math.sqrt(fs / 2.0)
        white_a = c.accel_noise_ug_rthz * 1e-6 * math.sqrt(fs / 2.0)
        gyro_walk = self._walk(self._gyro_walk, c.gyro_bias_walk_dps_rts, dt, n, rng)
        accel_walk = self._walk(self._accel_walk, c.accel_bias_walk_mg_rts * 1e-3, dt, n, rng)
        gyro = (rate_dps @ self.gyro_matrix.T + self.gyro_offset_dps + gyro_walk
                + rng.normal(0.0, white_g, (n, 3)))
        accel = (accel_g @ self.accel_matrix.T + self.accel_offset_g + accel_walk
                 + rng.normal(0.0, white_a, (n, 3)))
        gyro = self._gyro_lpf(gyro)
        accel = self._accel_lpf(accel)
        if self._accel_hold > 1:  # the 1 kHz accelerometer register between updates
            accel = np.repeat(accel[:: self._accel_hold], self._accel_hold, axis=0)[:n]
        self._internal_index += n
        pick = slice(0, n, dec)
        gyro_counts = to_counts(gyro[pick], c.gyro_lsb_per_dps)
        accel_counts = to_counts(accel[pick], c.accel_lsb_per_g)
        return gyro_counts, accel_counts, temperature_raw(np.asarray(temp_c)[pick])

    @staticmethod
    def _walk(state: np.ndarray, density: float, dt: float, n: int,
              rng: np.random.Generator) -> np.ndarray:
        """Bias random walk continuing from ``state`` (updated in place)."""
        steps = rng.normal(0.0, density * math.sqrt(dt), (n, 3))
        walk = state + np.cumsum(steps, axis=0)
        state[:] = walk[-1]
        return walk
