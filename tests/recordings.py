"""The dev recordings the accuracy tests replay, read once per test process.

Several tests score the same tlogs (the PX4 SIH and ArduPilot SITL flights, 3-6 MB
each), and reading one is most of a replay's time. Each caller gets its own deep copy
(a few MB of arrays, copied in milliseconds): nothing a test does to its recording
reaches the next test. (Read-only arrays would guard the shared one as well, but numba
compiles every kernel again for read-only arguments: tens of seconds on a fresh
machine.)
"""

from __future__ import annotations

import copy
import functools
from pathlib import Path

from replay.dataset import Recording
from replay.readers import load


@functools.lru_cache(maxsize=8)
def _read(path: Path, reference: str) -> Recording:
    return load(path, reference=reference)


def recording(path: Path | str, reference: str = "auto") -> Recording:
    """``replay.readers.load(path, reference=reference)``, read once per process."""
    return copy.deepcopy(_read(Path(path).resolve(), reference))
