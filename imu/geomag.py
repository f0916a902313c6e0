"""The Earth's magnetic field at a place and date, from the World Magnetic Model.

A thin wrapper around ``pygeomag`` (a maintained pure-Python port of NOAA's WMM that
ships the WMM2025 coefficients, no compiled parts, no network): bridge, replay and the
emulator all ask it for the declination at the vehicle's position, so that headings are
reported relative to true north without the user typing a number.
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass
from functools import lru_cache

from pygeomag import GeoMag, decimal_year_from_date

MODEL_FILE = "wmm/WMM_2025.COF"
MODEL_NAME = "WMM2025"


@dataclass(frozen=True)
class FieldAtPlace:
    """The main field at one place and date (WMM: geodetic WGS-84 position)."""

    declination_deg: float  # east positive: magnetic north is this far east of true north
    inclination_deg: float  # dip, down positive
    intensity_nt: float  # total field [nT]
    north_nt: float
    east_nt: float
    down_nt: float
    model: str = MODEL_NAME

    @property
    def ned_unit(self) -> tuple[float, float, float]:
        """The field direction in true-north NED, unit length."""
        f = self.intensity_nt
        return (self.north_nt / f, self.east_nt / f, self.down_nt / f)


@lru_cache(maxsize=1)
def _model() -> GeoMag:
    return GeoMag(coefficients_file=MODEL_FILE)


def decimal_year(when: _dt.date | _dt.datetime | float | None = None) -> float:
    """A date as a decimal year (today when None; a float is taken as already one)."""
    if when is None:
        when = _dt.datetime.now(_dt.UTC).date()
    if isinstance(when, int | float):
        return float(when)
    if isinstance(when, _dt.datetime):
        when = when.date()
    return float(decimal_year_from_date(when))


def field_at(lat_deg: float, lon_deg: float, alt_m: float = 0.0,
             when: _dt.date | _dt.datetime | float | None = None) -> FieldAtPlace:
    """The WMM field at a WGS-84 position; ValueError for an impossible position.

    Dates outside the model's five-year life are still evaluated (the secular
    variation extrapolates; a declination a year off is still far better than none).
    """
    if not (math.isfinite(lat_deg) and math.isfinite(lon_deg) and math.isfinite(alt_m)):
        raise ValueError(f"position must be finite, got lat={lat_deg} lon={lon_deg} "
                         f"alt={alt_m}")
    if not -90.0 <= lat_deg <= 90.0 or not -180.0 <= lon_deg <= 360.0:
        raise ValueError(f"no such place: lat={lat_deg} lon={lon_deg}")
    r = _model().calculate(glat=float(lat_deg), glon=float(lon_deg), alt=float(alt_m) / 1000.0,
                           time=decimal_year(when), allow_date_outside_lifespan=True)
    return FieldAtPlace(declination_deg=float(r.d), inclination_deg=float(r.i),
                        intensity_nt=float(r.f), north_nt=float(r.x), east_nt=float(r.y),
                        down_nt=float(r.z))


def declination_deg(lat_deg: float, lon_deg: float, alt_m: float = 0.0,
                    when: _dt.date | _dt.datetime | float | None = None) -> float:
    """Magnetic declination [deg], east positive, at a WGS-84 position."""
    return field_at(lat_deg, lon_deg, alt_m, when).declination_deg
