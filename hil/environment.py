"""The world the emulated board lives in: gravity, Earth's magnetic field, the air.

NED world frame. The field is given the way geomagnetic models report it: total
intensity, inclination (dip, positive downwards) and declination (east of true north).
The default is a mid-latitude site (about central Europe): 50 µT, 65° dip, 3° east.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

G = 9.80665  # standard gravity [m/s^2]
GRAVITY_NED = np.array([0.0, 0.0, G])

# International Standard Atmosphere, troposphere.
SEA_LEVEL_PA = 101325.0
LAPSE_K_PER_M = 0.0065
SEA_LEVEL_K = 288.15
ISA_EXPONENT = 5.25588


@dataclass(frozen=True)
class Environment:
    field_ut: float = 50.0
    inclination_deg: float = 65.0
    declination_deg: float = 3.0
    latitude_deg: float = 50.0  # only reported in HIL_STATE_QUATERNION
    longitude_deg: float = 8.0
    ground_altitude_m: float = 100.0  # AMSL of the take-off point
    air_temperature_c: float = 20.0
    board_temperature_c: float = 25.0  # the GY-86 at power-up
    board_warmup_c: float = 8.0  # self-heating reached after a few minutes
    board_warmup_tau_s: float = 120.0

    def __post_init__(self) -> None:
        if not (self.field_ut > 0 and -90 <= self.inclination_deg <= 90):
            raise ValueError("field intensity must be > 0 and inclination within ±90°")

    def field_ned_gauss(self) -> np.ndarray:
        """Earth's field in NED [gauss] (1 gauss = 100 µT)."""
        inc = math.radians(self.inclination_deg)
        dec = math.radians(self.declination_deg)
        h = math.cos(inc)
        return self.field_ut / 100.0 * np.array(
            [h * math.cos(dec), h * math.sin(dec), math.sin(inc)])

    def pressure_pa(self, altitude_amsl_m: np.ndarray) -> np.ndarray:
        """ISA static pressure at an altitude above mean sea level."""
        h = np.asarray(altitude_amsl_m, dtype=float)
        return SEA_LEVEL_PA * (1.0 - LAPSE_K_PER_M * h / SEA_LEVEL_K) ** ISA_EXPONENT

    def board_temperature(self, t_s: np.ndarray) -> np.ndarray:
        """Die temperature [°C]: power-up value plus an exponential warm-up."""
        t = np.asarray(t_s, dtype=float)
        return self.board_temperature_c + self.board_warmup_c * (
            1.0 - np.exp(-t / self.board_warmup_tau_s))
