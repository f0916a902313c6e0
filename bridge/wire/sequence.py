"""Packet loss per sender from MAVLink sequence numbers.

Every MAVLink sender numbers its packets 0..255. A forward gap means packets were lost
(or corrupted and discarded by CRC); a number from behind is either a late packet that
fills an earlier gap (reordered, so not lost after all) or a repeat (duplicate). Gaps
longer than half the counter cannot be told apart from reordering and count as lost.
"""

from __future__ import annotations

from collections import deque


class SequenceTracker:
    """Counts lost, late and duplicate packets of one (sysid, compid) sender."""

    def __init__(self, memory: int = 128) -> None:
        self.received = 0
        self.lost = 0
        self.late = 0
        self.duplicate = 0
        self._next: int | None = None
        self._missing: deque[int] = deque(maxlen=memory)

    def observe(self, seq: int) -> None:
        self.received += 1
        if self._next is None:
            self._next = (seq + 1) & 0xFF
            return
        gap = (seq - self._next) & 0xFF
        if gap == 0:
            self._next = (seq + 1) & 0xFF
        elif gap < 128:
            self._missing.extend((self._next + k) & 0xFF for k in range(gap))
            self.lost += gap
            self._next = (seq + 1) & 0xFF
        elif seq in self._missing:
            self._missing.remove(seq)
            self.lost -= 1
            self.late += 1
        else:
            self.duplicate += 1
