"""``attitude-bridge calibrate``: fit a sensor calibration from logs (or the emulator).

    attitude-bridge calibrate LOG... -o calib.toml [--board gy86] [--rotation NAME]
                              [--no-gyro|--no-gyro-matrix|--no-accel|--no-mag]
    attitude-bridge calibrate --emulator [--seed 1] -o calib.toml

The log should show the board held still in many orientations (each of the six faces
down, square on a level surface, and a few edges and corners, ~2 s each) and turned
about every axis through all orientations in between;
``hil``'s ``calibration`` motion profile does exactly that. The written file is used by
``attitude-bridge run --calibration calib.toml`` (or ``calibration = "..."`` in the
settings TOML).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from imu.calibration_fit import BLOCK_S, fit_calibration


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate", help="fit gyro/accelerometer/magnetometer calibration from logs",
        description="Fit a gyro offset (longest still stretch) and matrix (turns between "
                    "static poses), an accelerometer offset and matrix (static poses; the "
                    "full matrix when all six faces were held square on a level surface) "
                    "and a magnetometer hard/soft-iron correction (ellipsoid) from logs in "
                    "which the board is turned through many orientations and held still "
                    "in each. Refuses data that cannot determine the calibration.")
    p.add_argument("logs", nargs="*", type=Path, metavar="LOG",
                   help="tlog (RAW_IMU via --board), CSV or npz file(s); samples of all "
                        "files are pooled")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="CALIB.toml")
    p.add_argument("--board", default="gy86",
                   help="what RAW_IMU integers in a tlog mean (imu.boards; default gy86)")
    p.add_argument("--rotation", default="NONE", metavar="NAME",
                   help="board mounting rotation, as given to `run` (default NONE)")
    p.add_argument("--imu", default=None, help="tlog IMU message (default: first present)")
    p.add_argument("--emulator", action="store_true",
                   help="fit from the HIL emulator's `calibration` motion instead of logs "
                        "(same sensor errors as `run`/`demo` with the same --seed)")
    p.add_argument("--seed", type=int, default=1, help="emulator seed (default 1, the "
                                                       "built-in emulator's)")
    p.add_argument("--no-gyro", action="store_true",
                   help="leave the gyro as is (offset zero, identity matrix)")
    p.add_argument("--no-gyro-matrix", action="store_true",
                   help="fit the gyro offset only, not its scale and cross-axis matrix")
    p.add_argument("--no-accel", action="store_true", help="leave the accelerometer as is")
    p.add_argument("--no-mag", action="store_true", help="leave the magnetometer as is")
    p.set_defaults(func=main)


def emulator_samples(seed: int, rate_hz: float = 250.0
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(gyr, acc, mag, rate) of the emulated GY-86 going through the calibration poses."""
    from hil import EmulatorConfig, simulate
    from hil.motion import calibration_duration_s

    cfg = EmulatorConfig(profile="calibration", duration_s=calibration_duration_s() + 1.0,
                         seed=seed, rate_hz=rate_hz)
    rec = simulate(cfg)
    return rec.gyr, rec.acc, rec.mag, cfg.imu_rate_hz


def log_samples(paths: list[Path], board: str, imu: str | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, float]:
    """Samples of all logs, pooled, with a gap between files (never one still stretch)."""
    from replay.readers import load

    recs = [load(p, board=board, imu=imu) for p in paths]
    rate = float(np.median([r.rate_hz for r in recs]))
    gap = np.full((2 * max(2, round(BLOCK_S * rate)), 3), np.nan)
    parts: dict[str, list[np.ndarray]] = {"gyr": [], "acc": [], "mag": []}
    for r in recs:
        for name in parts:
            v = getattr(r, name)
            parts[name] += [np.full((r.n, 3), np.nan) if v is None else v, gap]
    mag = np.concatenate(parts["mag"])
    return (np.concatenate(parts["gyr"]), np.concatenate(parts["acc"]),
            mag if np.isfinite(mag).any() else None, rate)


def main(args: argparse.Namespace) -> int:
    from imu.rotations import rotation_matrix

    from .config import check_rotation

    try:
        check_rotation(args.rotation)
        rot = rotation_matrix(args.rotation)
        if args.emulator:
            if args.logs:
                raise ValueError("give either LOG files or --emulator, not both")
            gyr, acc, mag, rate = emulator_samples(args.seed)
            source = f"HIL emulator, profile calibration, seed {args.seed}"
        elif not args.logs:
            raise ValueError("no LOG files given (or use --emulator)")
        else:
            gyr, acc, mag, rate = log_samples(args.logs, args.board, args.imu)
            source = ", ".join(str(p) for p in args.logs) + f" (board {args.board})"
        gyr, acc = gyr @ rot.T, acc @ rot.T
        mag = None if mag is None else mag @ rot.T
        cal, report = fit_calibration(gyr, acc, mag, rate, gyro=not args.no_gyro,
                                      accel=not args.no_accel,
                                      magnetometer=not args.no_mag,
                                      gyro_matrix=not args.no_gyro_matrix)
    except ValueError as exc:  # includes unreadable logs (ReplayInputError)
        print(f"attitude-bridge calibrate: error: {exc}", file=sys.stderr)
        return 2
    lines = report.lines()
    for line in lines:
        print(line)
    comment = "\n".join([f"fitted from {source}, rotation {args.rotation}", *lines])
    try:
        cal.save(args.output, comment)
    except OSError as exc:
        print(f"attitude-bridge calibrate: error: cannot write {args.output}: {exc}",
              file=sys.stderr)
        return 2
    print(f"wrote {args.output}")
    return 0
