"""Checks of a whole BridgeConfig before anything starts: types (a TOML file can say
anything), ranges, and output files that can be written. Each raises ValueError naming
the setting, which the CLI prints as one line."""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any


def check_types(cfg: Any) -> None:
    """Every setting of the type it is declared with (a TOML file can say anything)."""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        kind = str(f.type)
        if value is None and "None" in kind:
            continue
        if kind.startswith("float"):
            ok = isinstance(value, int | float) and not isinstance(value, bool)
        elif kind.startswith("int"):
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif kind.startswith("bool"):
            ok = isinstance(value, bool)
        elif kind.startswith("str"):
            ok = isinstance(value, str)
        elif kind == "list[int]":
            ok = isinstance(value, list) and all(
                isinstance(v, int) and not isinstance(v, bool) for v in value)
        elif kind == "list[str]":
            ok = isinstance(value, list) and all(isinstance(v, str) for v in value)
        else:
            continue
        if not ok:
            raise ValueError(f"setting {f.name!r} must be {kind}, got {value!r}")


#: The fastest IMU stream the bridge takes (an ICM-42688 samples at 32 kHz, but no
#: autopilot streams MAVLink faster than a few kHz); the per-vehicle buffers scale with it.
MAX_IMU_RATE_HZ = 10_000.0
#: Longest ``duration`` [s]: a year; beyond it a number is a typo (and the built-in
#: emulator plans its motion for the whole run).
MAX_DURATION_S = 365 * 86400.0
#: setting -> the inclusive range of values that mean something. Wide: a user may set a
#: poor value, not an absurd one. Past them the service breaks without a word: a rate of
#: 1e-300 Hz overflows the MAVLink interval, a 1e9 s window allocates terabytes, a full
#: scale below what a sensor at rest reads (1 g) refuses every sample.
SETTING_RANGES: dict[str, tuple[float, float]] = {
    "imu_rate": (1.0, MAX_IMU_RATE_HZ),  # the ring buffers are sized by it
    "window_s": (0.1, 600.0),  # the comparison's ring buffers: window x rate samples
    "status_period_s": (0.01, 3600.0),
    "jump_s": (1e-3, 3600.0),
    "reorder_s": (0.0, 60.0),
    "peer_timeout_s": (0.01, 1e6),
    "max_source_rate": (1.0, 1e7),
    "source_timeout_s": (0.01, 1e6),
    "evict_after_s": (0.01, 1e6),
    "clock_resync_s": (1e-3, 3600.0),
    "reinit_gap_s": (1e-3, 1e6),
    "reinit_settle_s": (0.0, 3600.0),
    "idle_timeout_s": (0.01, 1e6),
    "gyro_range_dps": (100.0, 1e5),  # the smallest MEMS range is ±125 deg/s
    "accel_range_g": (2.0, 1e4),  # ±2 g is the smallest; at rest a sensor reads 1 g
    "mag_range_gauss": (0.7, 1e4),  # the Earth's field is up to 0.65 gauss
    "aid_max_age_s": (1e-3, 60.0),
    "mqtt_rate": (0.0, 1e4),
}


def check_ranges(cfg: Any) -> None:
    """Numbers finite, positive where a zero makes no sense, ids in range."""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"setting {f.name!r} must be a finite number, got {value!r}")
    for name, (lo, hi) in SETTING_RANGES.items():
        value = getattr(cfg, name)
        if not lo <= value <= hi:
            raise ValueError(f"setting {name!r} must be within {lo:g}..{hi:g}, got {value!r}")
    if cfg.emulator_seed < 0:
        raise ValueError(f"emulator seed must not be negative, got {cfg.emulator_seed}")
    if cfg.duration is not None and not 0 < cfg.duration <= MAX_DURATION_S:
        raise ValueError(f"duration must be more than 0 and at most {MAX_DURATION_S:g} s "
                         f"(a year), got {cfg.duration!r}")
    if cfg.declination_deg is not None and abs(cfg.declination_deg) > 180.0:
        raise ValueError(f"declination must be within ±180°, got {cfg.declination_deg!r}")
    if not 1 <= cfg.max_peers <= 100_000:
        raise ValueError(f"max_peers must be in 1..100000, got {cfg.max_peers}")
    for sysid in cfg.vehicles:
        if not 1 <= sysid <= 255:
            raise ValueError(f"vehicle system id must be in 1..255, got {sysid}")
    if cfg.imu_id is not None and not 0 <= cfg.imu_id <= 255:
        raise ValueError(f"imu_id must be in 0..255, got {cfg.imu_id}")
    if cfg.truth_source is not None:
        parse_source(cfg.truth_source)


def check_output_file(path: str | Path, option: str) -> None:
    """ValueError unless ``path`` can be written: a file name in an existing, writable
    folder (checked before the service starts, not when the first sample comes)."""
    p = Path(path)
    folder = p.parent
    if p.is_dir():
        raise ValueError(f"{option} {p}: is a folder, expected a file name")
    if not folder.is_dir():
        raise ValueError(f"{option} {p}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK):
        raise ValueError(f"{option} {p}: folder {folder} is not writable")
    if p.exists() and not p.is_file():  # a device or a pipe: opening a FIFO would block
        if not os.access(p, os.W_OK):
            raise ValueError(f"{option} {p}: cannot be written")
        return
    existed = p.exists()
    try:  # what access() cannot tell: /proc, a read-only mount, a full quota
        with p.open("a"):
            pass
    except OSError as exc:
        raise ValueError(f"{option} {p}: cannot be written ({exc.strerror})") from None
    if not existed:
        p.unlink(missing_ok=True)


def parse_source(text: str) -> tuple[int, int]:
    """``"SYSID:COMPID"`` -> (sysid, compid); ValueError saying the form otherwise."""
    sysid, sep, compid = str(text).partition(":")
    if not (sep and sysid.strip().isdigit() and compid.strip().isdigit()
            and 1 <= int(sysid) <= 255 and 0 <= int(compid) <= 255):
        raise ValueError(f"bad source {text!r}; use SYSID:COMPID, e.g. 1:1")
    return int(sysid), int(compid)


def same_file_key(path: str | Path) -> str:
    """One key per file, whatever the spelling (relative, symlinked, case on Windows)."""
    return os.path.normcase(os.path.realpath(path))


def check_outputs(outputs: Sequence[tuple[str | Path | None, str]],
                  inputs: Sequence[str | Path], inputs_are: str = "the logs read") -> None:
    """ValueError, before any work, for an output (path, option) that cannot be written,
    that two options share (the second would overwrite the first), or that is one of
    the ``inputs`` (it would be overwritten with the results)."""
    read = {same_file_key(p): p for p in inputs if Path(p).is_file()}
    taken: dict[str, str] = {}
    for path, option in outputs:
        if path is None:
            continue
        check_output_file(path, option)
        key = same_file_key(path)
        if key in taken:
            raise ValueError(f"{option} {path}: also given to {taken[key]}; each output "
                             f"needs a file of its own")
        if key in read:
            raise ValueError(f"{option} {path}: is one of {inputs_are} ({read[key]}); it "
                             f"would be overwritten")
        taken[key] = option
