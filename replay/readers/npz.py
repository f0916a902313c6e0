"""BROAD-style ``.npz`` (Laidig et al., Data 2021): see ../shared/data/README.md.

The IMU stays in its own sensor axes and the reference is sensor -> ENU, so estimators
run with ``world="ENU"`` and start from the first acc+mag sample, exactly as the
dataset's authors evaluate; only the ``movement`` samples are scored.
"""

from __future__ import annotations

import struct
import tokenize
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ..board import magnitude_warning
from ..dataset import Recording, ReplayInputError, TimeCleanup
from ._common import make_reference, pick_reference

REQUIRED = ("rate", "gyr", "acc")
ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")  # a zip's first bytes (\x05\x06: empty)
NPY_MAGIC = b"\x93NUMPY"
LAYOUT = "a BROAD-style .npz has rate, gyr, acc[, mag, quat_ref, movement]"
#: What reading a damaged archive raises: a bad CRC or directory (BadZipFile), a broken
#: deflate stream (zlib.error), a member cut short (EOFError, struct.error), a damaged
#: compression method (NotImplementedError), a garbled array header (TokenError) or one
#: claiming a huge shape (MemoryError).
DAMAGE = (zipfile.BadZipFile, zlib.error, EOFError, OSError, struct.error,
          NotImplementedError, tokenize.TokenError, MemoryError)


def read(path: Path, reference: str = "auto") -> Recording:
    with _open(path) as data:
        missing = [k for k in REQUIRED if k not in data.files]
        if missing:
            raise ReplayInputError(f"{path}: no IMU samples found (missing keys {missing}; "
                                   f"{LAYOUT})")
        try:
            rate = _scalar(_member(path, data, "rate"))
            gyr = np.asarray(_member(path, data, "gyr"), dtype=float)
            acc = np.asarray(_member(path, data, "acc"), dtype=float)
            mag = _optional(path, data, "mag", float)
            q_ref = _optional(path, data, "quat_ref", float)
            movement = _optional(path, data, "movement", bool)
        except ReplayInputError:
            raise
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


@contextmanager
def _open(path: Path) -> Iterator[np.lib.npyio.NpzFile]:
    """The archive, after checking it is one: numpy reads any other file as a pickle and
    its refusal invites the user to load it with ``allow_pickle``, unsafe for a file that
    is merely misnamed (a tlog or CSV called .npz). The file is opened here so that it is
    closed also when numpy fails half-way (it leaves its own handle open then)."""
    try:
        f = path.open("rb")
    except OSError as exc:
        raise ReplayInputError(f"{path}: cannot read ({exc.strerror})") from exc
    with f:
        head = f.read(len(NPY_MAGIC))
        if head.startswith(NPY_MAGIC):
            raise ReplayInputError(f"{path}: not a .npz archive (a single .npy array); "
                                   f"{LAYOUT}")
        if not head.startswith(ZIP_MAGIC):
            what = "an empty file" if not head else "not a .npz (zip) archive"
            raise ReplayInputError(f"{path}: {what}; {LAYOUT}")
        f.seek(0)
        try:
            data = np.load(f, allow_pickle=False)
        except (*DAMAGE, ValueError) as exc:
            raise ReplayInputError(f"{path}: not a readable .npz ({_reason(exc)})") from exc
        with data:
            yield data


def _member(path: Path, data: np.lib.npyio.NpzFile, key: str) -> np.ndarray:
    """One array, read and checked: members are decompressed only here, so this is where
    a damaged archive shows; a complex array would lose its imaginary part (and warn)
    when made float."""
    try:
        value = data[key]
    except DAMAGE as exc:
        raise ReplayInputError(f"{path}: not a readable .npz ({key}: {_reason(exc)})") from exc
    if np.iscomplexobj(value):
        raise ReplayInputError(f"{path}: {key} holds complex numbers ({value.dtype}); "
                               f"expected real numbers")
    return value


def _optional(path: Path, data: np.lib.npyio.NpzFile, key: str, dtype: type
              ) -> np.ndarray | None:
    """An optional member as ``dtype``, None when the archive lacks it."""
    if key not in data.files:
        return None
    return np.asarray(_member(path, data, key), dtype=dtype)


def _reason(exc: BaseException) -> str:
    """"BadZipFile: Bad CRC-32 ..." on one line: zlib's and zipfile's messages do not say
    which kind of damage on their own."""
    kind = type(exc)
    name = kind.__name__ if kind.__module__ == "builtins" else f"{kind.__module__}.{kind.__name__}"
    return f"{name}: {' '.join(str(exc).split())}"


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
