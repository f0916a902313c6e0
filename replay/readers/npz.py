"""BROAD-style ``.npz`` (Laidig et al., Data 2021): see ../shared/data/README.md.

The IMU stays in its own sensor axes and the reference is sensor -> ENU, so estimators
run with ``world="ENU"`` and start from the first acc+mag sample, exactly as the
dataset's authors evaluate; only the ``movement`` samples are scored.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..board import magnitude_warning
from ..dataset import Recording, ReplayInputError, TimeCleanup
from ._common import make_reference, pick_reference

REQUIRED = ("rate", "gyr", "acc")


def read(path: Path, reference: str = "auto") -> Recording:
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as exc:
        raise ReplayInputError(f"{path}: not a readable .npz file ({exc})") from exc
    if not isinstance(data, np.lib.npyio.NpzFile):  # a lone .npy array renamed .npz
        raise ReplayInputError(f"{path}: not a .npz archive (a single .npy array); a "
                               f"BROAD-style .npz has rate, gyr, acc[, mag, quat_ref, "
                               f"movement]")
    with data:
        missing = [k for k in REQUIRED if k not in data.files]
        if missing:
            raise ReplayInputError(f"{path}: no IMU samples found (missing keys {missing}; "
                                   f"a BROAD-style .npz has rate, gyr, acc[, mag, quat_ref, "
                                   f"movement])")
        try:
            rate = _scalar(data["rate"])
            gyr = np.asarray(data["gyr"], dtype=float)
            acc = np.asarray(data["acc"], dtype=float)
            mag = np.asarray(data["mag"], dtype=float) if "mag" in data.files else None
            q_ref = (np.asarray(data["quat_ref"], dtype=float)
                     if "quat_ref" in data.files else None)
            movement = (np.asarray(data["movement"], dtype=bool)
                        if "movement" in data.files else None)
        except (TypeError, ValueError) as exc:  # text or object arrays, a vector rate
            raise ReplayInputError(f"{path}: not a BROAD-style .npz ({exc})") from exc
    if not (np.isfinite(rate) and rate > 0):
        raise ReplayInputError(f"{path}: rate must be a positive number, got {rate}")
    _check_shapes(path, gyr, {"acc": acc, "mag": mag, "quat_ref": q_ref,
                              "movement": movement})
    t = np.arange(gyr.shape[0]) / rate  # sample k is at k / rate
    found = None if q_ref is None else make_reference(t, q_ref, "truth", "quat_ref (optical)",
                                                    north="magnetic")
    ref, references = pick_reference({"truth": found}, reference)
    warning = magnitude_warning(acc, "npz acc")
    return Recording(path=path, format="npz", t=t, gyr=gyr, acc=acc, mag=mag, world="ENU",
                     body="sensor", source="npz gyr/acc/mag", reference=ref,
                     score_mask=movement, cleanup=TimeCleanup(kept=len(t)),
                     warnings=(warning,) if warning else (), references=references)


def _scalar(value: np.ndarray) -> float:
    """``rate`` as one number (a 0-d or one-element array); ValueError otherwise."""
    arr = np.asarray(value, dtype=float)
    if arr.size != 1:
        raise ValueError(f"rate must be one number, got an array of shape {arr.shape}")
    return float(arr.reshape(()))


def _check_shapes(path: Path, gyr: np.ndarray, others: dict[str, np.ndarray | None]) -> None:
    """One row per gyro sample in every array, before any arithmetic on them.

    Arrays of different lengths (a file cut or put together wrongly) cannot be paired
    row by row; caught later, they fail inside numpy (warnings, a message without the
    file's name) or pair different instants.
    """
    if gyr.ndim != 2 or gyr.shape[1] != 3 or gyr.shape[0] < 2:
        raise ReplayInputError(f"{path}: gyr must be (N>=2, 3), got {gyr.shape}")
    n = gyr.shape[0]
    columns = {"acc": (3,), "mag": (3,), "quat_ref": (4,), "movement": ()}
    for key, arr in others.items():
        expected = (n, *columns[key])
        if arr is not None and arr.shape != expected:
            raise ReplayInputError(f"{path}: {key} is {arr.shape}, expected {expected} "
                                   f"(one row per gyr sample; gyr has {n})")
