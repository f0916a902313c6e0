"""Fixed-size time-stamped history (numpy ring buffer) for the live comparison."""

from __future__ import annotations

import numpy as np


class TimeRing:
    """The last ``capacity`` (time, vector) rows; O(1) push, ordered snapshot on demand."""

    def __init__(self, capacity: int, width: int) -> None:
        self.t = np.full(capacity, np.nan)
        self.v = np.full((capacity, width), np.nan)
        self._i = 0
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def push(self, t: float, row: np.ndarray) -> None:
        i = self._i
        self.t[i] = t
        self.v[i] = row
        self._i = (i + 1) % self.t.shape[0]
        if self._n < self.t.shape[0]:
            self._n += 1

    @property
    def last_t(self) -> float:
        return float(self.t[self._i - 1]) if self._n else float("nan")

    def last(self) -> tuple[float, np.ndarray] | None:
        """The newest (time, row), or None when empty."""
        if not self._n:
            return None
        i = self._i - 1
        return float(self.t[i]), self.v[i].copy()

    def snapshot(self, since: float = -np.inf) -> tuple[np.ndarray, np.ndarray]:
        """(times, rows) in push order, only rows with time >= since."""
        cap = self.t.shape[0]
        if self._n < cap:
            t, v = self.t[:self._n], self.v[:self._n]
        else:
            order = np.r_[self._i:cap, 0:self._i]
            t, v = self.t[order], self.v[order]
        keep = t >= since
        return t[keep].copy(), v[keep].copy()

    def clear(self) -> None:
        self._i = self._n = 0
