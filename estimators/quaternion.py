"""Gyro-only quaternion integration (seeds 000/003: q̇ = ½ q ⊗ [0, ω]).

No correction: the attitude drifts with gyro bias and noise. Useful as the baseline
against which the filters show what the accelerometer and magnetometer buy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import _core
from .base import CommonParams, Estimator, param
from .registry import register


@dataclass(frozen=True)
class QuaternionParams(CommonParams):
    exact: bool = param(True, "True: exact axis-angle step q ⊗ exp(ω·dt/2); False: the "
                              "seeds' first-order step q + ½ q ⊗ ω · dt (both renormalised)")


@_core.kernel
def _step(state, params, gx, gy, gz, ax, ay, az, mx, my, mz, acc_ok, mag_ok, dt) -> None:
    if params[0] > 0.0:
        _core.integrate_exact(state, gx, gy, gz, dt)
    else:
        _core.integrate_first_order(state, gx, gy, gz, dt)


@register
class QuaternionIntegrator(Estimator):
    """Integrates the gyro only; initial attitude from q0 or the first acc(+mag) sample."""

    name = "quaternion"
    Params = QuaternionParams
    _update_one, _run_batch = (staticmethod(k) for k in _core.make_kernels(_step))

    def _pack_params(self, p: QuaternionParams) -> np.ndarray:
        return np.array([1.0 if p.exact else 0.0])
