"""The MPU6050's digital low-pass filter, as a stateful first-order filter plus delay.

The datasheet (register 26, CONFIG) gives, for each DLPF_CFG, a bandwidth and a delay
but not the filter itself. We use a first-order low-pass at the stated bandwidth, run at
the chip's internal sample rate, followed by a whole-sample pure delay that brings the
total low-frequency group delay up to the stated figure (the first-order filter alone
already delays by about 1/(2*pi*bandwidth)); for DLPF_CFG 5 and 6, whose listed delay is
shorter than that, the delay wins and the filter is made wider (about 12 and 9 Hz
instead of 10 and 5 Hz). State carries over between calls, so feeding a
signal in chunks gives exactly the same output as feeding it at once.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def _first_order(x: np.ndarray, alpha: float, state: np.ndarray) -> np.ndarray:
    y = np.empty_like(x)
    for i in range(x.shape[0]):
        for j in range(x.shape[1]):
            state[j] += alpha * (x[i, j] - state[j])
            y[i, j] = state[j]
    return y


class LowPass:
    """First-order low-pass (bandwidth_hz at rate_hz) plus delay_s of pure delay (total)."""

    def __init__(self, bandwidth_hz: float, delay_s: float, rate_hz: float, axes: int = 3):
        alpha = 1.0 - math.exp(-2.0 * math.pi * bandwidth_hz / rate_hz)
        # The narrowest settings (DLPF_CFG 5, 6) list less delay than a first-order
        # filter of their bandwidth has; there we keep the delay and widen the filter.
        if (1.0 - alpha) / alpha > delay_s * rate_hz:
            alpha = 1.0 / (1.0 + delay_s * rate_hz)
        self.alpha = alpha
        filter_delay = (1.0 - alpha) / alpha / rate_hz  # DC group delay of y += a(x - y)
        self.delay_samples = max(0, round((delay_s - filter_delay) * rate_hz))
        self._state = np.zeros(axes)
        self._started = False
        self._tail = np.zeros((self.delay_samples, axes))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=float)
        if not self._started:  # start settled on the first input, as after power-up
            self._state[:] = x[0]
            self._tail[:] = x[0]
            self._started = True
        y = _first_order(x, self.alpha, self._state)
        if self.delay_samples == 0:
            return y
        joined = np.concatenate([self._tail, y])
        self._tail = joined[len(y):]
        return joined[: len(y)]
