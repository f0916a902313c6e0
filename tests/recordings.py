"""The dev recordings the accuracy tests replay, read once per test process.

Several tests score the same tlogs (the PX4 SIH and ArduPilot SITL flights, 3-6 MB
each), and reading one is most of a replay's time. The copy handed out is shared, so
its arrays are made read-only: a test (or a change to the replay) that writes into a
recording fails at once instead of changing what the next test reads.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np

from replay.dataset import Recording
from replay.readers import load


@functools.lru_cache(maxsize=8)
def _read(path: Path, reference: str) -> Recording:
    rec = load(path, reference=reference)
    _freeze(rec)
    return rec


def _freeze(value: object) -> None:
    """Make every numpy array reachable through dataclass fields read-only."""
    if isinstance(value, np.ndarray):
        value.flags.writeable = False
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        for f in dataclasses.fields(value):
            _freeze(getattr(value, f.name))


def recording(path: Path | str, reference: str = "auto") -> Recording:
    """``replay.readers.load(path, reference=reference)``, read once per process."""
    return _read(Path(path).resolve(), reference)
