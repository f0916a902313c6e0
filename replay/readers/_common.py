"""Small helpers shared by the readers."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..dataset import (
    REFERENCE_KINDS,
    Reference,
    ReplayInputError,
    TimeCleanup,
    usable_quaternions,
)
from ..timebase import monotonic_mask


def clean_stream(t: np.ndarray, *columns: np.ndarray
                 ) -> tuple[np.ndarray, list[np.ndarray], TimeCleanup]:
    """Drop samples whose time does not increase (counted), applying it to every column."""
    keep, cleanup = monotonic_mask(t)
    return t[keep], [c[keep] for c in columns], cleanup


def trim_before_first_mag(t: np.ndarray, mag: np.ndarray, columns: list[np.ndarray]
                          ) -> tuple[int, np.ndarray, list[np.ndarray]]:
    """Start the IMU stream at the first held magnetometer sample.

    An estimator initialises its heading from its first usable sample; starting before
    any magnetometer reading would fix the heading arbitrarily (yaw 0) and score a
    spurious heading error for the whole convergence time.
    """
    have = np.all(np.isfinite(mag), axis=1)
    if not have.any():
        return 0, t, columns
    first = int(np.argmax(have))
    return first, t[first:], [c[first:] for c in columns]


def make_reference(t: np.ndarray, q: np.ndarray, kind: str, source: str,
                   north: str = "true", timing: str = "") -> Reference:
    """A Reference with its time cleaned and its quaternions normalised.

    Rows that are no attitude (zero, not finite) are left as they are: the Reference
    makes them NaN and counts them as damage, for the recording's notes.
    """
    t, (q,), cleanup = clean_stream(np.asarray(t, float), np.asarray(q, float))
    ok = usable_quaternions(q)
    q[ok] /= np.linalg.norm(q[ok], axis=1, keepdims=True)
    return Reference(t=t, q=q, kind=kind, source=source, cleanup=cleanup, north=north,
                     timing=timing)


def require_imu(n: int, path: object, what: str, damage: str = "") -> None:
    """At least two IMU samples; else an error that also says what damage cost them."""
    if n < 2:
        raise ReplayInputError(f"{path}: no IMU samples found (looked for {what})"
                               + (f"; {damage}" if damage else ""))


def other_autopilot(found: Mapping[str, Reference | None], chosen: Reference | None
                    ) -> Reference | None:
    """The autopilot's attitude when the chosen reference is another kind (else None)."""
    own = found.get("autopilot")
    return own if own is not None and own is not chosen else None


def pick_reference(found: Mapping[str, Reference | None], wanted: str
                   ) -> tuple[Reference | None, tuple[str, ...]]:
    """The reference asked for and the kinds the file has (in order of preference).

    ``auto`` is truth when the file has it, else the autopilot's attitude. A kind the
    file lacks gives None, never another kind: the replay command then says which
    kinds there are instead of scoring against something else.
    """
    has = tuple(kind for kind in REFERENCE_KINDS if found.get(kind) is not None)
    kind = (has[0] if has else None) if wanted == "auto" else wanted
    return (found.get(kind) if kind in has else None), has
