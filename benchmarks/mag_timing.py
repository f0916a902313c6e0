"""How old is a recording's magnetometer reading? Measured against the truth, per dev
recording: how often the reading is refreshed while the vehicle moves, and how old a
reading is when it first appears, beside what eskf assumes (``mag_delay`` less the
IMU's filter delay).

    python benchmarks/mag_timing.py [--json out.json]      # about half a minute

Why: a reading that is ``τ`` older than the gyro sample it comes with points the field
``τ·ω`` away in a turn, and eskf reads that as a heading error. The age is found where
the field, turned into the world by the true attitude ``τ`` earlier, keeps the steadiest
heading over every freshly refreshed reading while moving (the spread falls to the
magnetometer's own noise at the right age, and grows either side of it). Only readings
that just changed count: a sender that repeats its last reading until the next one
(ArduPilot's RAW_IMU, PX4's HIGHRES_IMU) makes the held copies older still, which eskf
handles on its own (a repeated reading is dropped once the body has turned).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.accuracy import DATA, REPO, Trial, broad_trials, emulator_trials, sitl_trials
from estimators import quat as Q
from estimators.eskf import EskfParams

#: Ages tried [s]: 0 to 200 ms.
MAX_AGE_S = 0.2


def fresh_readings(mag: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """Indices of the samples whose magnetometer reading differs from the one before,
    while ``moving``."""
    changed = np.r_[False, np.any(np.diff(mag, axis=0) != 0.0, axis=1)]
    return np.flatnonzero(changed & moving & np.all(np.isfinite(mag), axis=1))


def heading_spread_deg(truth: np.ndarray, mag: np.ndarray, idx: np.ndarray, lag: int,
                       world: str) -> float:
    """RMS deviation [deg] from their circular mean of the headings of the readings at
    ``idx``, turned into the world by the truth ``lag`` samples earlier."""
    idx = idx[idx >= lag]
    field = Q.rotate(truth[idx - lag], mag[idx])
    north, east = (field[:, 0], field[:, 1]) if world.upper() == "NED" else \
        (field[:, 1], field[:, 0])
    heading = np.arctan2(east, north)
    heading = heading[np.isfinite(heading)]
    if heading.size == 0:
        return math.nan
    mean = math.atan2(np.sin(heading).mean(), np.cos(heading).mean())
    off = np.angle(np.exp(1j * (heading - mean)))
    return float(np.degrees(np.sqrt(np.mean(off ** 2))))


def reading_age(trial: Trial, moving: np.ndarray) -> dict[str, float]:
    """The refresh interval while moving and the age of a fresh reading, for one trial."""
    idx = fresh_readings(trial.mag, moving)
    step = 1.0 / trial.rate_hz
    lags = range(int(MAX_AGE_S / step) + 1)
    spread = [heading_spread_deg(trial.truth, trial.mag, idx, k, trial.world) for k in lags]
    best = int(np.nanargmin(spread))
    gaps = np.diff(idx) * step
    gaps = gaps[gaps < 1.0]  # within one moving stretch
    return {"fresh_readings": int(idx.size),
            "refresh_ms": float(np.median(gaps) * 1e3) if gaps.size else math.nan,
            "age_ms": best * step * 1e3,
            "spread_at_0_deg": spread[0], "spread_at_age_deg": spread[best],
            "eskf_assumes_ms": (EskfParams().mag_delay - trial.imu_delay) * 1e3}


def moving_samples(trial: Trial) -> np.ndarray:
    """Where the reading's age shows: in the air for a flight, the scored movements of a
    BROAD trial."""
    if trial.airborne is not None:
        return np.nan_to_num(trial.airborne) > 0.5
    return trial.scored


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, help="write the numbers as JSON")
    args = ap.parse_args(argv)
    trials = [*sitl_trials([DATA / "px4_sih", REPO / "tests" / "data" / "sitl"]),
              *emulator_trials((1,)), *broad_trials(DATA / "broad")]
    doc: dict[str, dict[str, float]] = {}
    print(f"{'recording':12s} {'fresh':>6s} {'refresh ms':>10s} {'age ms':>7s} "
          f"{'spread at 0 / at age [deg]':>27s} {'eskf assumes ms':>16s}")
    for t in trials:
        row = reading_age(t, moving_samples(t))
        doc[t.name] = row
        print(f"{t.name:12s} {row['fresh_readings']:6d} {row['refresh_ms']:10.1f} "
              f"{row['age_ms']:7.1f} {row['spread_at_0_deg']:13.2f} / "
              f"{row['spread_at_age_deg']:5.2f}       {row['eskf_assumes_ms']:10.1f}")
    if args.json:
        args.json.write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
