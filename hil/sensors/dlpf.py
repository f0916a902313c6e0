"""The MPU6050's digital low-pass filter, as a stateful first-order filter plus delay.

The datasheet (register 26, CONFIG) gives, for each DLPF_CFG, a bandwidth and a delay
but not the filter itself. We use a first-order low-pass at the stated bandwidth, run at
the chip's internal sample rate, followed by a whole-sample pure delay that brings the
total low-frequency group delay up to the stated figure (the first-order filter alone
already delays by about 1/(2*pi*bandwidth)); for DLPF_CFG 5 and 6, whose listed delay is
shorter than that, the delay wins and the filter is made wider (about 12 and 9 Hz
instead of 10 and 5 Hz). State carries over between calls, so feeding a
signal in chunks gives exactly the same output as feeding it at once (given a first
chunk longer than the delay).

The chip's filter has been running since power-up when the firmware reads its first
sample, so its delay line holds earlier, different readings, never copies of the first
one (a real MPU6050 does not start with several identical samples, and a listener
counting identical readings as a stuck sensor must not see one). Those earlier inputs
are not known; the first inputs mirrored in time stand in for them: the same signal and
noise statistics, and no extra random draws (every seed's stream stays as it was after
the first few samples).
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
        if not self._started:
            self._prime(x)
        y = _first_order(x, self.alpha, self._state)
        if self.delay_samples == 0:
            return y
        joined = np.concatenate([self._tail, y])
        self._tail = joined[len(y):]
        return joined[: len(y)]

    def _prime(self, x: np.ndarray) -> None:
        """Fill the filter and its delay line with a history: x[d], ..., x[1] (the first
        inputs mirrored about x[0]), filtered from a state settled on x[d]."""
        d = self.delay_samples
        k = min(d, len(x) - 1)
        self._state[:] = x[k]
        if d:
            history = _first_order(np.ascontiguousarray(x[k:0:-1]), self.alpha, self._state)
            self._tail[: d - k] = x[k]  # a first chunk shorter than the delay
            self._tail[d - k:] = history
        self._started = True
