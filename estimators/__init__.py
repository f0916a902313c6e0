"""attitude-bridge estimators: attitude from gyro, accelerometer and magnetometer.

    import estimators
    estimators.names()
    est = estimators.create("mahony", rate_hz=1000.0, world="NED", q0=None, kp=1.0)
    q = est.update(gyr, acc, mag=None, dt=None)
    Q = estimators.batch("mahony", gyr, acc, mag, rate_hz=285.7, world="ENU")

Frames, units and conventions: see ``estimators.quat`` and the README.
"""

from __future__ import annotations

import numpy as np

from .base import BatchResult, Estimator, EstimatorStatus, SampleCounters
from .registry import estimator_class, names, register
from .smoother import SmoothResult, smooth

__all__ = [
    "BatchResult", "Estimator", "EstimatorStatus", "SampleCounters", "SmoothResult",
    "batch", "create", "estimator_class", "names", "register", "run", "smooth",
]


def create(name: str, rate_hz: float = 1000.0, world: str = "NED",
           q0: np.ndarray | None = None, **params: float) -> Estimator:
    """A new estimator by name; unknown names or parameters raise ValueError."""
    return estimator_class(name)(rate_hz=rate_hz, world=world, q0=q0, **params)


def run(name: str, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None = None,
        rate_hz: float = 1000.0, world: str = "NED", q0: np.ndarray | None = None,
        dt: float | np.ndarray | None = None, *, vel: np.ndarray | None = None,
        vel_age: float | np.ndarray | None = None, airborne: np.ndarray | None = None,
        **params: float) -> BatchResult:
    """Batch run returning quaternions, bias estimates and per-sample flags.

    ``vel``/``vel_age``: optional velocity aiding, see ``Estimator.update``;
    ``airborne``: the vehicle's flight state per sample, see ``Estimator.run``."""
    return create(name, rate_hz=rate_hz, world=world, q0=q0, **params).run(
        gyr, acc, mag, dt, vel=vel, vel_age=vel_age, airborne=airborne)


def batch(name: str, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None = None,
          rate_hz: float = 1000.0, world: str = "NED", q0: np.ndarray | None = None,
          dt: float | np.ndarray | None = None, *, vel: np.ndarray | None = None,
          vel_age: float | np.ndarray | None = None, airborne: np.ndarray | None = None,
          **params: float) -> np.ndarray:
    """(N, 4) quaternions, identical to calling ``update`` per sample, in a compiled loop."""
    return run(name, gyr, acc, mag, rate_hz=rate_hz, world=world, q0=q0, dt=dt, vel=vel,
               vel_age=vel_age, airborne=airborne, **params).q
