"""The STM32's clock: microseconds since boot, as stamped on every message.

The firmware timestamps each sample from a timer driven by the board's crystal, so the
board clock differs from true time by the boot offset, the crystal error (drift, ppm),
the latency of the data-ready interrupt (jitter) and any injected clock fault.
"""

from __future__ import annotations

import numpy as np

#: The board clock is unsigned and also goes out as a uint32 millisecond time_boot_ms:
#: clock faults that step it below boot or past 2**32 ms hold it at the limit (a step
#: backwards cannot make time since boot negative), rather than packing garbage.
MAX_BOARD_US = (2**32 - 1) * 1000


class BoardClock:
    def __init__(self, boot_time_s: float, drift_ppm: float, jitter_us: float,
                 rng: np.random.Generator):
        self.boot_us = round(boot_time_s * 1e6)
        self.scale = 1.0 + drift_ppm * 1e-6
        self.jitter_us = jitter_us
        self.rng = rng

    def stamp(self, t_true: np.ndarray, fault_offset_us: np.ndarray | int = 0,
              jitter: bool = True) -> np.ndarray:
        """Board time [µs] of events at true times t (seconds since the first sample)."""
        t = np.asarray(t_true, dtype=float)
        us = self.boot_us + np.round(t * 1e6 * self.scale)
        if jitter and self.jitter_us > 0.0:
            us += np.round(self.rng.uniform(0.0, self.jitter_us, t.shape))
        return np.clip(us + fault_offset_us, 0, MAX_BOARD_US).astype(np.int64)
