"""MS5611-01BA03 barometer: factory PROM, raw conversions and the datasheet compensation.

The chip reports two 24-bit ADC words, D1 (pressure) and D2 (temperature), that only
mean something together with six factory coefficients C1..C6 read from its PROM. The
board (the STM32 firmware) applies the datasheet's first- and second-order
compensation to get TEMP [0.01 °C] and P [0.01 mbar = Pa]. The emulator works the other
way: from the true pressure and temperature it finds the D1/D2 words the chip would have
produced, so the board-side arithmetic is exercised exactly as on hardware.

Integer arithmetic follows the datasheet (64-bit intermediates, divisions by powers of
two done as arithmetic right shifts, i.e. rounding towards minus infinity).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: The datasheet's example coefficients C1..C6 (also the emulated chip's PROM).
DATASHEET_C = (40127, 36924, 23317, 23282, 33464, 28312)
#: 24-bit ADC limits.
ADC_MAX = (1 << 24) - 1
#: Datasheet RMS resolution at OSR 4096: pressure 0.012 mbar, temperature 0.002 °C.
PRESSURE_NOISE_PA = 1.2
TEMPERATURE_NOISE_C = 0.002
#: Conversion time at OSR 4096 (max 9.04 ms); the board interleaves D1 and D2, so a
#: compensated pressure is available about every 2 conversions (~50 Hz).
CONVERSION_TIME_S = 9.04e-3
DEFAULT_RATE_HZ = 50.0


def crc4(prom: tuple[int, ...] | list[int]) -> int:
    """CRC-4 of the 8 PROM words (AN520), with the CRC nibble itself taken as zero."""
    words = [int(w) & 0xFFFF for w in prom]
    if len(words) != 8:
        raise ValueError(f"MS5611 PROM has 8 words, got {len(words)}")
    words[7] &= 0xFF00
    rem = 0
    for i in range(16):
        byte = (words[i >> 1] & 0xFF) if i % 2 else (words[i >> 1] >> 8)
        rem ^= byte
        for _ in range(8):
            rem = ((rem << 1) ^ 0x3000) if rem & 0x8000 else (rem << 1)
            rem &= 0xFFFF
    return (rem >> 12) & 0xF


def make_prom(c: tuple[int, ...] = DATASHEET_C, factory: int = 0) -> tuple[int, ...]:
    """The 8 PROM words: factory word, C1..C6, and word 7 carrying the CRC nibble."""
    if len(c) != 6 or not all(0 <= v <= 0xFFFF for v in c):
        raise ValueError("C1..C6 must be six 16-bit unsigned integers")
    words = [factory, *c, 0]
    words[7] = crc4(words)
    return tuple(words)


def check_prom(prom: tuple[int, ...]) -> tuple[int, ...]:
    """C1..C6 from a PROM read; ValueError if its CRC does not match (bad I2C read)."""
    if crc4(prom) != (prom[7] & 0xF):
        raise ValueError("MS5611 PROM CRC mismatch")
    return tuple(prom[1:7])


@dataclass(frozen=True)
class Compensated:
    """Board-side result: TEMP [0.01 °C] and P [0.01 mbar]."""

    temp_cdeg: int
    pressure_pa: int


def compensate(c: tuple[int, ...], d1: int, d2: int, second_order: bool = True) -> Compensated:
    """Datasheet compensation (figure "pressure and temperature calculation")."""
    temp, off, sens = _terms(c, int(d2), second_order)
    return Compensated(temp_cdeg=temp, pressure_pa=_pressure(int(d1), off, sens))


def _pressure(d1: int, off: int, sens: int) -> int:
    """P [Pa] from the pressure word D1 and the temperature's OFF and SENS."""
    return (((d1 * sens) >> 21) - off) >> 15


def _terms(c: tuple[int, ...], d2: int, second_order: bool = True) -> tuple[int, int, int]:
    """TEMP, OFF and SENS for the temperature word D2 (the part of the compensation that
    does not depend on D1)."""
    c1, c2, c3, c4, c5, c6 = (int(v) for v in c)
    dt = d2 - (c5 << 8)
    temp = 2000 + ((dt * c6) >> 23)
    off = (c2 << 16) + ((c4 * dt) >> 7)
    sens = (c1 << 15) + ((c3 * dt) >> 8)
    if second_order and temp < 2000:
        t2 = (dt * dt) >> 31
        off2 = 5 * (temp - 2000) ** 2 >> 1
        sens2 = 5 * (temp - 2000) ** 2 >> 2
        if temp < -1500:
            off2 += 7 * (temp + 1500) ** 2
            sens2 += (11 * (temp + 1500) ** 2) >> 1
        temp -= t2
        off -= off2
        sens -= sens2
    return temp, off, sens


def raw_from_true(c: tuple[int, ...], pressure_pa: float, temp_c: float) -> tuple[int, int]:
    """D1, D2 that the chip would output for a true pressure [Pa] and temperature [°C].

    The board's compensation is monotonic in D2 (for TEMP) and in D1 (for P at fixed
    D2), so a search over the 24-bit range finds the words whose compensated values are
    nearest the truth, second-order terms included. It starts from the first-order
    inverse (the emulator converts every barometer reading this way), which is a few
    steps from the answer.
    """
    c6, c5 = int(c[5]), int(c[4])

    def temp_of(x: int) -> int:
        return _terms(c, x)[0]

    target_t = temp_c * 100.0
    guess = (c5 << 8) + (target_t - 2000.0) * (1 << 23) / c6
    for _ in range(2):  # the second-order term, below 20 °C, moves the answer
        guess += (target_t - temp_of(_clip(guess))) * (1 << 23) / c6
    d2 = _nearest(temp_of, target_t, _clip(guess))
    _, off, sens = _terms(c, d2)
    guess_1 = ((pressure_pa * (1 << 15)) + off) * (1 << 21) / max(sens, 1)
    d1 = _nearest(lambda x: _pressure(x, off, sens), pressure_pa, _clip(guess_1))
    return d1, d2


def _clip(x: float) -> int:
    """A starting word for the search: ``x`` in the ADC's range (mid-range if not finite:
    the search then ends where the whole-range bisection does)."""
    if not math.isfinite(x):
        return ADC_MAX // 2
    return min(max(int(x), 0), ADC_MAX)


def _nearest(f, target: float, guess: int) -> int:
    """Integer x in [0, ADC_MAX] whose monotonic non-decreasing f(x) is nearest target:
    the smallest x with f(x) >= target (bracketed by steps doubling away from ``guess``,
    then bisected), or the one before it if that is as near."""
    lo, hi, step = 0, ADC_MAX, 1
    if f(guess) >= target:
        hi = guess
        while guess - step > 0:
            if f(guess - step) < target:
                lo = guess - step + 1
                break
            hi, step = guess - step, 2 * step
    else:  # (none at all: ADC_MAX, as the plain bisection ends)
        lo = min(guess + 1, ADC_MAX)
        while guess + step < ADC_MAX:
            if f(guess + step) >= target:
                hi = guess + step
                break
            lo, step = guess + step + 1, 2 * step
    while lo < hi:
        mid = (lo + hi) // 2
        if f(mid) >= target:
            hi = mid
        else:
            lo = mid + 1
    if lo > 0 and abs(f(lo - 1) - target) <= abs(f(lo) - target):
        return lo - 1
    return lo


@dataclass
class Ms5611:
    """The emulated chip: PROM plus D1/D2 from the truth with datasheet-level noise."""

    c: tuple[int, ...] = DATASHEET_C
    pressure_noise_pa: float = PRESSURE_NOISE_PA
    temperature_noise_c: float = TEMPERATURE_NOISE_C

    @property
    def prom(self) -> tuple[int, ...]:
        return make_prom(self.c)

    def convert(self, pressure_pa: np.ndarray, temp_c: np.ndarray,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """D1, D2 arrays for true pressure/temperature arrays (noise drawn from rng)."""
        pressure_pa = np.asarray(pressure_pa, dtype=float)
        temp_c = np.asarray(temp_c, dtype=float)
        noisy_p = pressure_pa + rng.normal(0.0, self.pressure_noise_pa, pressure_pa.shape)
        noisy_t = temp_c + rng.normal(0.0, self.temperature_noise_c, temp_c.shape)
        raw = [raw_from_true(self.c, p, t) for p, t in zip(noisy_p, noisy_t, strict=True)]
        d = np.array(raw, dtype=np.int64).reshape(-1, 2)
        return d[:, 0], d[:, 1]
