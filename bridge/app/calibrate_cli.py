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
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from imu.calibration import SensorCalibration
from imu.calibration_fit import BLOCK_S, FitReport, fit_calibration, repair_samples

from .config_checks import same_file_key

if TYPE_CHECKING:
    from replay.dataset import Recording

OUTPUT_OPTION = "-o/--output"


def _seed(text: str) -> int:
    """argparse type of ``--seed``: an integer >= 0 (argparse then names the option;
    the emulator's own check did not)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return value


def register(subparsers: argparse._SubParsersAction) -> None:
    from imu.boards import PROFILES

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
                        "files are pooled (a file given twice is used once)")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="CALIB.toml")
    p.add_argument("--board", default="gy86", choices=sorted(PROFILES),
                   help="what RAW_IMU integers in a tlog mean (imu.boards; default gy86)")
    p.add_argument("--rotation", default="NONE", metavar="NAME",
                   help="board mounting rotation, as given to `run` (default NONE)")
    p.add_argument("--imu", default=None, help="tlog IMU message (default: first present)")
    p.add_argument("--emulator", action="store_true",
                   help="fit from the HIL emulator's `calibration` motion instead of logs "
                        "(same sensor errors as `run`/`demo` with the same --seed)")
    p.add_argument("--seed", type=_seed, default=1, help="emulator seed (default 1, the "
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


@dataclass(frozen=True)
class LogSamples:
    """One log's samples as the fit takes them, and what the user must hear about it."""

    gyr: np.ndarray  # (N, 3), unusable samples NaN (short runs interpolated)
    acc: np.ndarray
    mag: np.ndarray | None  # None: no magnetometer (or not wanted)
    rate: float
    notes: tuple[str, ...]  # "note: ..." / "warning: ..." lines: the reader's, the repairs'
    left_out: int  # gyro/accelerometer samples unusable and not interpolated


def reader_lines(path: Path, rec: Recording) -> list[str]:
    """The reader's notes and warnings (dropped rows, a wrong unit), one line each, as
    ``replay`` shows them: damage the fit survives must still be seen."""
    notes = list(rec.notes)
    if rec.cleanup.dropped:
        notes.append(f"dropped IMU samples: {rec.cleanup}")
    return ([f"note: {path}: {n}" for n in notes]
            + [f"warning: {path}: {w}" for w in rec.warnings])


def load_log(path: Path, board: str, imu: str | None, mag: bool = True) -> LogSamples:
    """Read one log; unusable samples (non-finite, beyond any sensor) are interpolated
    or left out, and counted, so that damage shows on the output instead of as a
    refusal that blames the user's motion. ``mag``: False leaves the magnetometer out."""
    from replay.readers import load

    # The reader's |acc|-at-rest check squares the samples: absurd ones (1e200) overflow
    # to inf there, which it rightly reports as implausible, and repair_samples refuses.
    with np.errstate(over="ignore"):
        rec = load(path, board=board, imu=imu)
    try:
        gyr, g_fix = repair_samples(rec.gyr, "gyro", rec.rate_hz)
        acc, a_fix = repair_samples(rec.acc, "accelerometer", rec.rate_hz)
        m, m_fix = (None, None) if rec.mag is None or not mag else repair_samples(
            rec.mag, "magnetometer", rec.rate_hz, fill=False)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    if m is not None and not np.isfinite(m).any():  # a column without a single reading
        m, m_fix = None, None
    repairs = [f"note: {path}: {r.note()}" for r in (g_fix, a_fix, m_fix)
               if r is not None and r.note()]
    return LogSamples(gyr, acc, m, rec.rate_hz, (*reader_lines(path, rec), *repairs),
                      g_fix.left_out + a_fix.left_out)


def pool(logs: list[LogSamples]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, float]:
    """Samples of all logs, pooled, with a gap between files (never one still stretch)."""
    rate = float(np.median([log.rate for log in logs]))
    gap = np.full((2 * max(2, round(BLOCK_S * rate)), 3), np.nan)
    parts: dict[str, list[np.ndarray]] = {"gyr": [], "acc": [], "mag": []}
    for log in logs:
        for name in parts:
            v = getattr(log, name)
            parts[name] += [np.full((len(log.gyr), 3), np.nan) if v is None else v, gap]
    mag = np.concatenate(parts["mag"])
    return (np.concatenate(parts["gyr"]), np.concatenate(parts["acc"]),
            mag if np.isfinite(mag).any() else None, rate)


def log_samples(paths: list[Path], board: str, imu: str | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, float]:
    """Samples of all logs, pooled (see :func:`pool`); each path as often as given."""
    return pool([load_log(p, board, imu) for p in paths])


def unique_logs(paths: list[Path]) -> tuple[list[Path], list[str]]:
    """(each file once, in order, and a note line per repeated one): pooling a file twice
    would weight its poses double and add turns that are not new data."""
    seen: dict[str, Path] = {}
    count: dict[str, int] = {}
    for p in paths:
        key = same_file_key(p)
        seen.setdefault(key, p)
        count[key] = count.get(key, 0) + 1
    notes = [f"note: {seen[k]} given {n} times; used once"
             for k, n in count.items() if n > 1]
    return list(seen.values()), notes


def check_args(args: argparse.Namespace) -> None:
    """ValueError naming the option for anything wrong that needs no log read: before
    any work, so a typo does not cost the whole fit (or overwrite a log)."""
    from replay.readers.tlog import IMU_MESSAGES

    from .config import check_rotation
    from .config_checks import check_outputs

    check_rotation(args.rotation)
    if args.no_gyro and args.no_accel and args.no_mag:
        raise ValueError("nothing to fit: --no-gyro, --no-accel and --no-mag leave every "
                         "sensor as is")
    if args.imu is not None and args.imu.upper() not in IMU_MESSAGES:
        raise ValueError(f"--imu {args.imu!r}: unknown IMU message; valid: "
                         f"{list(IMU_MESSAGES)}")
    if args.emulator and args.logs:
        raise ValueError("give either LOG files or --emulator, not both")
    if not args.emulator and not args.logs:
        raise ValueError("no LOG files given (or use --emulator)")
    check_outputs([(args.output, OUTPUT_OPTION)], args.logs, "the LOG files")


@dataclass(frozen=True)
class Samples:
    """What the fit runs on: samples in board axes, where they came from, the note and
    warning lines the user must see (also written into the file) and the unusable
    samples left out."""

    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray | None
    rate: float
    source: str
    notes: tuple[str, ...] = ()
    left_out: int = 0


def read_samples(args: argparse.Namespace) -> Samples:
    """The samples of the logs (each file once) or of the emulator."""
    if args.emulator:
        return Samples(*emulator_samples(args.seed),
                       source=f"HIL emulator, profile calibration, seed {args.seed}")
    paths, notes = unique_logs(args.logs)
    logs = [load_log(p, args.board, args.imu, mag=not args.no_mag) for p in paths]
    return Samples(*pool(logs), source=", ".join(map(str, paths)) + f" (board {args.board})",
                   notes=(*notes, *(line for log in logs for line in log.notes)),
                   left_out=sum(log.left_out for log in logs))


def fit(args: argparse.Namespace, s: Samples) -> tuple[SensorCalibration, FitReport]:
    """The fit in body axes (after ``--rotation``); a refusal says when unusable samples
    left out are a likely cause, rather than only blaming the user's motion."""
    from imu.rotations import rotation_matrix

    rot = rotation_matrix(args.rotation)
    mag = None if s.mag is None else s.mag @ rot.T
    try:
        return fit_calibration(s.gyr @ rot.T, s.acc @ rot.T, mag, s.rate,
                               gyro=not args.no_gyro, accel=not args.no_accel,
                               magnetometer=not args.no_mag,
                               gyro_matrix=not args.no_gyro_matrix)
    except ValueError as exc:
        if not s.left_out:
            raise
        raise ValueError(f"{exc} ({s.left_out} gyro/accelerometer samples were unusable "
                         "and left out, which ends still stretches and turns: a likely "
                         "cause)") from None


def main(args: argparse.Namespace) -> int:
    try:
        check_args(args)
        samples = read_samples(args)
        for line in samples.notes:
            print(line)
        cal, report = fit(args, samples)
    except ValueError as exc:  # includes unreadable logs (ReplayInputError)
        print(f"attitude-bridge calibrate: error: {exc}", file=sys.stderr)
        return 2
    lines = report.lines()
    for line in lines:
        print(line)
    comment = "\n".join([f"fitted from {samples.source}, rotation {args.rotation}",
                         *samples.notes, *lines])
    try:
        cal.save(args.output, comment)
    except OSError as exc:
        print(f"attitude-bridge calibrate: error: cannot write {args.output}: {exc}",
              file=sys.stderr)
        return 2
    print(f"wrote {args.output}")
    return 0
