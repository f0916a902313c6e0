"""``load(path)``: pick a reader by extension (or by the file's first bytes) -> Recording."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ..dataset import Recording, ReplayInputError
from . import csv, npz, tlog, ulog

FORMATS: dict[str, Callable[..., Recording]] = {
    "ulog": ulog.read,
    "tlog": tlog.read,
    "npz": npz.read,
    "csv": csv.read,
}
_SUFFIXES = {".ulg": "ulog", ".ulog": "ulog", ".tlog": "tlog", ".npz": "npz", ".csv": "csv"}
#: File name endings that name a log format: what a folder given to replay / tune yields.
LOG_SUFFIXES = frozenset(_SUFFIXES)
ULOG_MAGIC = b"ULog\x01\x12\x35"
ZIP_MAGIC = b"PK\x03\x04"
MAVLINK_STX = (0xFE, 0xFD)  # MAVLink 1 / 2 start bytes, after a tlog's 8-byte time stamp


def detect_format(path: Path) -> str:
    """Format name from the suffix, else from the first bytes; ReplayInputError if unknown."""
    by_suffix = _SUFFIXES.get(path.suffix.lower())
    if by_suffix:
        return by_suffix
    with path.open("rb") as f:
        head = f.read(16)
    if head.startswith(ULOG_MAGIC):
        return "ulog"
    if head.startswith(ZIP_MAGIC):
        return "npz"
    if len(head) > 8 and head[8] in MAVLINK_STX:
        return "tlog"
    raise ReplayInputError(
        f"{path}: unknown log format (suffix {path.suffix!r}); replay reads PX4 ULog (.ulg), "
        f"MAVLink telemetry logs (.tlog), BROAD-style .npz and CSV (see replay/readers/csv.py)")


def load(path: str | Path, fmt: str | None = None, board: str | None = None,
         imu: str | None = None, reference: str = "auto", raw_mag: bool = True
         ) -> Recording:
    """Read a log or dataset file into a :class:`Recording`.

    ``board`` names the RAW_IMU profile for tlogs (``imu.boards``; None: the one whose
    accelerometer scale gives 1 g at rest); ``imu`` picks the
    IMU stream when a file has several (a tlog message name, or a ULog multi-instance
    ``sensor_combined`` is the only one). ``reference``: "auto" (truth when the file has
    it, else the autopilot's attitude), "truth" or "autopilot" (None when the file lacks
    that kind; ``Recording.references`` lists those it has). ``raw_mag`` False: a PX4
    tlog's HIGHRES_IMU field is kept even where its raw one would replace it
    (:mod:`imu.px4_mag`). Errors are
    :class:`ReplayInputError` with the file name and what was expected.
    """
    p = Path(path)
    if not p.exists():
        raise ReplayInputError(f"{p}: no such file")
    if not p.is_file():
        raise ReplayInputError(f"{p}: not a regular file")
    kind = fmt or detect_format(p)
    if kind not in FORMATS:
        raise ReplayInputError(f"unknown format {kind!r}; valid: {sorted(FORMATS)}")
    if kind == "tlog":
        return tlog.read(p, board=board, imu=imu, reference=reference, raw_mag=raw_mag)
    return FORMATS[kind](p, reference=reference)
