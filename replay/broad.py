"""The BROAD dataset as the benchmark and the regression test read it: its trials
(``*.npz``: gyr, acc, mag, quat_ref, movement, rate), the paper's published numbers
(``published_case_study.csv``), the example code's initial orientation, one estimator run
and the dataset's score (RMS over the ``movement`` samples).

The paper's numbers were made by the BROAD example code, whose initial orientation
(``broad_example_init``) is not the sensor's attitude but the inverse of its attitude
relative to south-east-up: Mahony's slow integrator remembers that start, so reproducing
the published Mahony numbers needs it.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import estimators
from estimators import quat as Q
from estimators.metrics import ErrorRms, rms_errors

PUBLISHED_MAHONY = {"kp": 0.74, "ki": 0.0012, "mag_mode": "full"}  # reference C code
PUBLISHED_MADGWICK = {"beta": 0.12, "original_mag_quirk": True}
_Q_Z90 = np.array([np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)])  # +90° about z: NWU x -> ENU y


@dataclass(frozen=True)
class Trial:
    """One BROAD recording."""

    name: str
    rate_hz: float
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    quat_ref: np.ndarray
    movement: np.ndarray


def load_trials(data_dir: Path) -> list[Trial]:
    """Every ``*.npz`` trial in ``data_dir``, sorted by name."""
    files = sorted(data_dir.glob("*.npz"))
    if not files:
        raise FileNotFoundError(f"no BROAD .npz trials in {data_dir}")
    trials = []
    for f in files:
        with np.load(f) as d:
            trials.append(Trial(f.stem, float(d["rate"]),
                                *(np.ascontiguousarray(d[k], dtype=float)
                                  for k in ("gyr", "acc", "mag", "quat_ref")),
                                d["movement"].astype(bool)))
    return trials


def load_published(data_dir: Path) -> dict[str, dict[str, ErrorRms]]:
    """published_case_study.csv as {"mahony"|"madgwick": {trial: ErrorRms}}."""
    path = data_dir / "published_case_study.csv"
    out: dict[str, dict[str, ErrorRms]] = {"madgwick": {}, "mahony": {}}
    if not path.exists():
        return out
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            out["madgwick"][r["trial"]] = ErrorRms(
                float(r["madgwick_b0.12_total"]), float(r["madgwick_heading"]),
                float(r["madgwick_incl"]), 0)
            out["mahony"][r["trial"]] = ErrorRms(
                float(r["mahony_kp0.74_ki0.0012_total"]), float(r["mahony_heading"]),
                float(r["mahony_incl"]), 0)
    return out


def broad_example_init(acc: np.ndarray, mag: np.ndarray) -> np.ndarray:
    """The initial orientation (sensor -> ENU) the BROAD example code gives the filters.

    That code stacks the unit vectors (-m_h, up × (-m_h), up), i.e. the south, east and up
    axes in sensor coordinates, as the *columns* of a matrix and converts it as if it were
    the sensor-to-world rotation; then rotates by +90° about z "to ENU". The result is the
    inverse of the sensor's attitude relative to south-east-up. Reproduced here only to
    match the published numbers; the estimators' own start (q0=None) is the correct one.
    """
    up = acc / np.linalg.norm(acc)
    south = -(mag - up * (up @ mag))
    south /= np.linalg.norm(south)
    east = np.cross(up, south)
    r = np.column_stack([south, east, up])
    return Q.multiply(_Q_Z90, Q.from_dcm(r))


def run_estimator(name: str, trial: Trial, use_mag: bool = True,
                  q0: np.ndarray | None = None, **params: float | bool | str) -> np.ndarray:
    """(N, 4) sensor -> ENU quaternions from one compiled batch run."""
    return estimators.batch(name, trial.gyr, trial.acc, trial.mag if use_mag else None,
                            rate_hz=trial.rate_hz, world="ENU", q0=q0, **params)


def score(trial: Trial, q: np.ndarray) -> ErrorRms:
    return rms_errors(q, trial.quat_ref, trial.movement)
