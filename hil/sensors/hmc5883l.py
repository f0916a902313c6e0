"""HMC5883L 3-axis magnetometer: from the true field to the data-output registers.

Datasheet (Honeywell HMC5883L, rev E) numbers: gain settings GN 0..7 with 1370, 1090,
820, 660, 440, 390, 330, 230 LSB/gauss; output range -2048..2047, and -4096 in a
channel whose ADC over- or underflowed; data output rates 0.75..75 Hz (15 Hz default);
noise floor 2 mG (standard deviation); gain tolerance ±5 %. The registers are read as
X, Z, Y (big-endian), an order the firmware must undo.

Hard iron (a constant field from magnetised parts of the board) and soft iron (a
linear distortion from nearby ferrous material) are optional.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

IDENTIFICATION = b"H43"  # registers 10..12
REG_DATA_X_MSB = 0x03
LSB_PER_GAUSS = (1370.0, 1090.0, 820.0, 660.0, 440.0, 390.0, 330.0, 230.0)
OUTPUT_RATES_HZ = (0.75, 1.5, 3.0, 7.5, 15.0, 30.0, 75.0)
DEFAULT_RATE_HZ = 15.0
OUTPUT_MIN, OUTPUT_MAX = -2048, 2047
OVERFLOW = -4096


@dataclass(frozen=True)
class Hmc5883lConfig:
    gain: int = 1  # GN: 1090 LSB/G, ±1.3 G
    rate_hz: float = DEFAULT_RATE_HZ
    noise_mgauss: float = 2.0
    scale_error: float = 0.01  # 1-sigma gain error per axis (datasheet ±5 %)
    hard_iron_gauss: tuple[float, float, float] = (0.0, 0.0, 0.0)
    soft_iron: tuple[tuple[float, ...], ...] = field(
        default=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)))

    def __post_init__(self) -> None:
        if self.gain not in range(8):
            raise ValueError("HMC5883L gain (GN) is 0..7")
        if self.rate_hz not in OUTPUT_RATES_HZ:
            raise ValueError(f"HMC5883L output rate must be one of {OUTPUT_RATES_HZ} Hz")

    @property
    def lsb_per_gauss(self) -> float:
        return LSB_PER_GAUSS[self.gain]


def to_counts(field_gauss: np.ndarray, lsb_per_gauss: float) -> np.ndarray:
    """Quantise; a channel outside the ADC range reads -4096 (datasheet overflow)."""
    counts = np.round(np.asarray(field_gauss, dtype=float) * lsb_per_gauss)
    overflow = (counts < OUTPUT_MIN) | (counts > OUTPUT_MAX)
    return np.where(overflow, OVERFLOW, counts).astype(np.int16)


def data_bytes(counts_xyz: np.ndarray) -> bytes:
    """Registers 3..8: X, Z, Y as big-endian int16."""
    x, y, z = (int(v) for v in counts_xyz)
    return np.array([x, z, y], dtype=">i2").tobytes()


def parse_data(data: bytes) -> np.ndarray:
    """X, Y, Z counts from the 6 data-register bytes (undoing the X, Z, Y order)."""
    if len(data) != 6:
        raise ValueError(f"HMC5883L data read is 6 bytes, got {len(data)}")
    x, z, y = np.frombuffer(data, dtype=">i2")
    return np.array([x, y, z], dtype=np.int16)


class Hmc5883l:
    """One emulated chip; its gain errors are drawn once from ``rng``."""

    def __init__(self, config: Hmc5883lConfig, rng: np.random.Generator):
        self.config = config
        gains = 1.0 + rng.normal(0.0, config.scale_error, 3)
        self.matrix = np.diag(gains) @ np.asarray(config.soft_iron, dtype=float)
        self.hard_iron = np.asarray(config.hard_iron_gauss, dtype=float)

    def measure(self, field_gauss: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Counts for true field samples [gauss] in chip axes, shape (N, 3)."""
        b = np.asarray(field_gauss, dtype=float).reshape(-1, 3)
        noise = rng.normal(0.0, self.config.noise_mgauss * 1e-3, b.shape)
        measured = b @ self.matrix.T + self.hard_iron + noise
        return to_counts(measured, self.config.lsb_per_gauss)
