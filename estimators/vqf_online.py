"""VQF (Laidig & Seel, 2023) as a live reference estimator: ``-e vqf``.

Not one of ours: the published ``vqf`` package's online filter with its published
defaults, run sample by sample beside our estimators in the bridge (and in ``replay``
or ``tune`` if asked for by name), so that the live comparison against the autopilot
and the truth has a well-known filter in the same run, on the same samples. It is a
*reference*: :func:`estimators.names` leaves it out (no default run, no contract of
ours it was not built for, such as velocity aiding or a starting attitude), and it needs
the optional package (``pip install 'attitude-bridge[compare]'``, which ``install.sh``
does).

What it takes from the common interface, and why:

* *Samples* are checked as ours are (``estimators._core``'s rules, and its counters):
  a non-finite or impossible gyro or a bad time step skips the sample; an unusable
  accelerometer or magnetometer is handed to VQF in the form it ignores (no
  accelerometer correction; the update without a magnetometer).
* *Time steps.* VQF runs at one fixed sample time. Each gyro sample is scaled by
  ``dt / Ts`` so that VQF integrates exactly the rotation of that sample's own step;
  ``Ts`` follows the stream's mean step (a low-pass), and when that departs from it by
  more than :data:`TS_TOLERANCE` the filter is rebuilt at the new ``Ts`` with its state
  carried over (its low-pass time constants are counted in samples, so a stream at a
  quarter of the assumed rate would otherwise react four times slower).
* *Frames.* VQF's world is ENU with magnetic north, on the samples' own body frame; the
  result is expressed in the requested world and turned to true north by
  ``declination``, as ours are (``Estimator.output_rotation``). ``imu_delay`` carries
  it forward at the body rate.
* The flight state and velocity aiding are accepted and not used (VQF has neither).
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from . import _core
from . import quat as Q
from .base import (
    BatchResult,
    CommonParams,
    Estimator,
    EstimatorStatus,
    SampleCounters,
    param,
    turned_forward,
)
from .registry import register

#: The stream's mean step may drift this far (relative) from VQF's sample time before
#: the filter is rebuilt at the new one.
TS_TOLERANCE = 0.1
#: Time constant [s] of the low-pass of the stream's step.
_DT_TAU = 1.0
_NO_Q0 = "estimator 'vqf' starts from its first samples; it takes no q0"


@dataclass(frozen=True)
class VqfParams(CommonParams):
    """VQF's two main time constants (its other settings keep the published defaults)."""

    BOUNDS: ClassVar[dict[str, tuple[float, float]]] = {
        "tau_acc": (1e-3, 1e4), "tau_mag": (1e-3, 1e4)}

    tau_acc: float = param(3.0, "VQF's accelerometer low-pass time constant [s] "
                                "(tauAcc: the tilt correction's time scale)")
    tau_mag: float = param(9.0, "VQF's magnetometer correction time constant [s] (tauMag)")


def _vqf_module() -> Any:
    try:
        return importlib.import_module("vqf")
    except ModuleNotFoundError:
        raise ValueError("estimator 'vqf' needs the vqf package: "
                         "pip install 'attitude-bridge[compare]'") from None


@register
class VqfOnline(Estimator):
    """VQF's online filter (the published vqf package, its defaults): a reference."""

    name: ClassVar[str] = "vqf"
    reference: ClassVar[bool] = True
    Params = VqfParams

    def __init__(self, rate_hz: float = 1000.0, world: str = "NED",
                 q0: np.ndarray | None = None, **params: float) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"rate_hz must be a positive number, got {rate_hz!r}")
        if q0 is not None:
            raise ValueError(_NO_Q0)
        self._module = _vqf_module()
        self.rate_hz = float(rate_hz)
        self.world = "ENU" if Q.world_is_enu(world) else "NED"
        self.params = self.make_params(**params)
        self.reset()

    @classmethod
    def check_available(cls) -> None:
        _vqf_module()

    # --- what the bridge tells every estimator ----------------------------------------
    def set_declination(self, declination: float) -> None:
        self.params = self._replaced(declination=float(declination))
        self._to_world = self._world_factor()

    def set_imu_delay(self, delay_s: float) -> None:
        self.params = self._replaced(imu_delay=float(delay_s))

    def set_flight_state(self, airborne: bool | None) -> None:
        """Accepted and not used: VQF has no flight-only model."""

    @property
    def air_model(self) -> bool:
        return False

    def _world_factor(self) -> tuple[float, float, float, float]:
        """``W ⊗ C``: VQF's body -> ENU (magnetic) to the requested world (true north),
        one quaternion to multiply by on the left per output."""
        w, x, y, z = Q.multiply(self.output_rotation, Q.Q_NED_ENU).tolist()
        return w, x, y, z

    def _replaced(self, **changes: float) -> VqfParams:
        return self.make_params(**{**dataclasses.asdict(self.params), **changes})

    # --- state ----------------------------------------------------------------------
    def reset(self, q0: np.ndarray | None = None) -> None:
        if q0 is not None:
            raise ValueError(_NO_Q0)
        self._to_world = self._world_factor()
        self._ts = 1.0 / self.rate_hz
        self._mean_dt = self._ts
        self._filter = self._new_filter(self._ts)
        self._counts = dict.fromkeys(_core.COUNTER_NAMES, 0)
        self._initialised = False
        self._mag_seen = False
        self._last_flags = 0
        self._last_gyr = np.zeros(3)

    def _new_filter(self, ts: float) -> Any:
        return self._module.VQF(ts, tauAcc=self.params.tau_acc, tauMag=self.params.tau_mag)

    def _follow_rate(self, dt: float) -> None:
        """Keep VQF's sample time at the stream's mean step (see the module doc)."""
        self._mean_dt += (1.0 - math.exp(-dt / _DT_TAU)) * (dt - self._mean_dt)
        if abs(self._mean_dt - self._ts) > TS_TOLERANCE * self._ts:
            state = self._filter.state
            self._ts = self._mean_dt
            self._filter = self._new_filter(self._ts)
            self._filter.state = state

    @property
    def sample_time(self) -> float:
        """The sample time [s] VQF runs at now (it follows the stream's mean step)."""
        return self._ts

    @property
    def q(self) -> np.ndarray:
        v = self._filter.getQuat9D() if self._mag_seen else self._filter.getQuat6D()
        a0, a1, a2, a3 = self._to_world
        b0, b1, b2, b3 = float(v[0]), float(v[1]), float(v[2]), float(v[3])
        q = np.array([a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
                      a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
                      a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
                      a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0])
        if self.params.imu_delay > 0.0:
            q = turned_forward(q, self._last_gyr, self.bias, self.params.imu_delay)
        return q

    @property
    def bias(self) -> np.ndarray:
        bias, _sigma = self._filter.getBiasEstimate()
        return np.asarray(bias, dtype=float) * (self._ts / self._mean_dt)

    @property
    def counters(self) -> SampleCounters:
        return SampleCounters(**self._counts)

    @property
    def status(self) -> EstimatorStatus:
        return EstimatorStatus(q=self.q, bias=self.bias, initialising=not self._initialised,
                               acc_rejected=False,
                               mag_rejected=bool(self._last_flags & _core.F_MAG_REJECTED),
                               counters=self.counters)

    # --- estimation -----------------------------------------------------------------
    def update(self, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None = None,
               dt: float | None = None, *, vel: np.ndarray | None = None,
               vel_age: float = 0.0) -> np.ndarray:
        self._last_flags = self._step(gyr, acc, mag, self._ts if dt is None else dt)
        return self.q

    def _step(self, gyr: object, acc: object, mag: object, dt: object) -> int:
        """One sample with our estimators' checks and counters; its F_* flags."""
        g, a = _vector("gyr", gyr), _vector("acc", acc)
        m = None if mag is None else _vector("mag", mag)
        try:
            step = float(dt)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise ValueError(f"dt must be a number of seconds, got {dt!r}") from None
        c, p = self._counts, self.params
        c["samples"] += 1
        initialised = _core.F_INITIALISED if self._initialised else 0
        grange = p.gyr_range
        gx, gy, gz = float(g[0]), float(g[1]), float(g[2])
        corrupt = _core.GYR_CORRUPT_FACTOR * grange
        if not (abs(gx) <= corrupt and abs(gy) <= corrupt and abs(gz) <= corrupt):
            c["skipped"] += 1  # (NaN fails every comparison: skipped too)
            return _core.F_SKIPPED | initialised
        if not (step > 0.0 and step <= p.max_dt):
            c["skipped"] += 1
            c["bad_dt"] += 1
            return _core.F_SKIPPED | initialised
        flags = 0
        saturated = 0.999 * grange
        if abs(gx) >= saturated or abs(gy) >= saturated or abs(gz) >= saturated:
            c["gyr_saturated"] += 1
            g = np.clip(g, -grange, grange)
        acc_ok = _core.acc_usable(float(a[0]), float(a[1]), float(a[2]), p.acc_range)
        if not acc_ok:
            c["acc_unusable"] += 1
            flags |= _core.F_ACC_UNUSABLE
            a = _ZERO  # VQF skips the tilt correction for a zero vector
        mag_ok = m is not None and _core.mag_usable(float(m[0]), float(m[1]), float(m[2]))
        if m is not None and not mag_ok:
            c["mag_unusable"] += 1
        if not self._initialised and not acc_ok:
            return flags  # nothing to anchor the attitude to yet, as ours
        if not self._initialised:
            self._ts = self._mean_dt = step  # the first step: the best guess of the rate
            self._filter = self._new_filter(step)
        else:
            self._follow_rate(step)
        scaled = g * (step / self._ts)  # VQF integrates gyr·Ts: this step's rotation
        if mag_ok:
            self._filter.update(scaled, a, m)
            self._mag_seen = True
            if self._filter.getMagDistDetected():
                c["mag_rejected"] += 1
                flags |= _core.F_MAG_REJECTED
        else:
            self._filter.update(scaled, a)
        self._initialised = True
        self._last_gyr = g
        return flags | _core.F_INITIALISED

    def run(self, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None = None,
            dt: float | np.ndarray | None = None, *, vel: np.ndarray | None = None,
            vel_age: float | np.ndarray | None = None,
            airborne: np.ndarray | None = None) -> BatchResult:
        """``update`` over (N, 3) arrays, continuing from the current state."""
        g = np.asarray(gyr, dtype=float)
        a = np.asarray(acc, dtype=float)
        if g.ndim != 2 or g.shape[1] != 3 or a.shape != g.shape:
            raise ValueError(f"gyr and acc must both be (N, 3), got {g.shape} and {a.shape}")
        n = len(g)
        if mag is not None and np.shape(mag) != g.shape:
            raise ValueError(f"mag must be (N, 3) like gyr, got {np.shape(mag)}")
        dts = self._per_sample("dt", self._ts if dt is None else dt, n)
        q, b = np.empty((n, 4)), np.empty((n, 3))
        flags = np.zeros(n, dtype=np.uint8)
        for i in range(n):
            flags[i] = self._step(g[i], a[i], None if mag is None else mag[i],
                                  dts[i if len(dts) > 1 else 0])
            q[i], b[i] = self.q, self.bias
        self._last_flags = int(flags[-1]) if n else self._last_flags
        return BatchResult(q=q, bias=b, flags=flags)


_ZERO = np.zeros(3)


def _vector(name: str, x: object) -> np.ndarray:
    """A contiguous float64 (3,) array (VQF's update takes nothing else)."""
    v = np.ascontiguousarray(x, dtype=np.float64)
    if v.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {v.shape}")
    return v
