"""The world the emulated board lives in: where it is, gravity, Earth's field, the air.

NED world frame. The vehicle takes off from a home position (WGS-84 latitude,
longitude, altitude above mean sea level; by default PX4 SITL's home in Zurich) on a
date. The Earth's field there comes from the World Magnetic Model (``imu.geomag``), as
the field a real compass would see at that place, so the declination a listener must
apply follows from the position like on a real vehicle. For tests the field can be
given explicitly the way geomagnetic models report it: total intensity, inclination
(dip, positive downwards) and declination (east of true north) — all three or none.
"""

from __future__ import annotations

import datetime
import math
from dataclasses import dataclass

import numpy as np

from imu import geomag

G = 9.80665  # standard gravity [m/s^2]
GRAVITY_NED = np.array([0.0, 0.0, G])

WGS84_A = 6378137.0  # semi-major axis [m]
WGS84_E2 = 6.69437999014e-3  # first eccentricity squared

# International Standard Atmosphere, troposphere.
SEA_LEVEL_PA = 101325.0
LAPSE_K_PER_M = 0.0065
SEA_LEVEL_K = 288.15
ISA_EXPONENT = 5.25588


#: PX4 SITL's default home (Zurich), used unless another place is given.
HOME_LAT_DEG = 47.397742
HOME_LON_DEG = 8.545594
HOME_ALT_M = 488.0
#: Home altitudes [m AMSL]: the Dead Sea shore is at -430 m; the barometer follows the
#: ISA troposphere, valid up to 11 km (its formula has no real value above 44 km).
MIN_HOME_ALT_M = -500.0
MAX_HOME_ALT_M = 11_000.0
#: The emulator's calendar date (fixed, so a seed gives the same field every day).
DEFAULT_DATE = datetime.date(2026, 1, 1)


@dataclass(frozen=True)
class Environment:
    latitude_deg: float = HOME_LAT_DEG  # home (take-off point), WGS-84
    longitude_deg: float = HOME_LON_DEG
    ground_altitude_m: float = HOME_ALT_M  # AMSL of the take-off point
    date: datetime.date = DEFAULT_DATE
    # Explicit Earth field (all three, or None for the WMM field at home on `date`).
    field_ut: float | None = None
    inclination_deg: float | None = None
    declination_deg: float | None = None
    air_temperature_c: float = 20.0
    board_temperature_c: float = 25.0  # the GY-86 at power-up
    board_warmup_c: float = 8.0  # self-heating reached after a few minutes
    board_warmup_tau_s: float = 120.0

    def __post_init__(self) -> None:
        explicit = (self.field_ut, self.inclination_deg, self.declination_deg)
        if any(v is not None for v in explicit):
            if any(v is None for v in explicit):
                raise ValueError("give the field's intensity, inclination and declination "
                                 "together (or none, for the World Magnetic Model)")
            if not (self.field_ut > 0 and -90 <= self.inclination_deg <= 90):
                raise ValueError("field intensity must be > 0 and inclination within ±90°")
        if not (-90.0 <= self.latitude_deg <= 90.0 and -180.0 <= self.longitude_deg <= 180.0
                and MIN_HOME_ALT_M <= self.ground_altitude_m <= MAX_HOME_ALT_M):
            raise ValueError(f"no such home position: lat {self.latitude_deg}, "
                             f"lon {self.longitude_deg}, alt {self.ground_altitude_m} (latitude "
                             f"±90°, longitude ±180°, altitude {MIN_HOME_ALT_M:g}.."
                             f"{MAX_HOME_ALT_M:g} m AMSL)")

    def earth_field(self) -> tuple[float, float, float]:
        """(intensity µT, inclination °, declination °) of the field at home."""
        if self.field_ut is not None:
            return self.field_ut, self.inclination_deg, self.declination_deg
        f = geomag.field_at(self.latitude_deg, self.longitude_deg, self.ground_altitude_m,
                            self.date)
        return f.intensity_nt / 1000.0, f.inclination_deg, f.declination_deg

    @property
    def magnetic_declination_deg(self) -> float:
        """Declination at home [°, east positive]: what a listener adds to a magnetic
        heading to get a true one."""
        return self.earth_field()[2]

    def field_ned_gauss(self) -> np.ndarray:
        """Earth's field in NED [gauss] (1 gauss = 100 µT)."""
        intensity, inclination, declination = self.earth_field()
        inc = math.radians(inclination)
        dec = math.radians(declination)
        h = math.cos(inc)
        return intensity / 100.0 * np.array(
            [h * math.cos(dec), h * math.sin(dec), math.sin(inc)])

    def geodetic(self, position_ned: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(latitude °, longitude °, altitude AMSL m) of NED offsets from home.

        Local flat-Earth mapping with the WGS-84 meridian and prime-vertical radii at
        home: exact to millimetres over the few hundred metres a flight covers.
        """
        p = np.asarray(position_ned, dtype=float)
        lat0 = math.radians(self.latitude_deg)
        s2 = math.sin(lat0) ** 2
        meridian = WGS84_A * (1 - WGS84_E2) / (1 - WGS84_E2 * s2) ** 1.5
        normal = WGS84_A / math.sqrt(1 - WGS84_E2 * s2)
        h = self.ground_altitude_m
        lat = self.latitude_deg + np.degrees(p[..., 0] / (meridian + h))
        lon = self.longitude_deg + np.degrees(p[..., 1] / ((normal + h) * math.cos(lat0)))
        return lat, lon, h - p[..., 2]

    def pressure_pa(self, altitude_amsl_m: np.ndarray) -> np.ndarray:
        """ISA static pressure at an altitude above mean sea level."""
        h = np.asarray(altitude_amsl_m, dtype=float)
        return SEA_LEVEL_PA * (1.0 - LAPSE_K_PER_M * h / SEA_LEVEL_K) ** ISA_EXPONENT

    def board_temperature(self, t_s: np.ndarray) -> np.ndarray:
        """Die temperature [°C]: power-up value plus an exponential warm-up."""
        t = np.asarray(t_s, dtype=float)
        return self.board_temperature_c + self.board_warmup_c * (
            1.0 - np.exp(-t / self.board_warmup_tau_s))
