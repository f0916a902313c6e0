"""The bridge's local status file, and ``attitude-bridge health`` that reads it.

``run --status-file PATH`` (or ``ATTITUDE_BRIDGE_STATUS_FILE``) makes the service write
its status — the same JSON as the MQTT status topic, for every vehicle, plus the time —
to PATH with every status update (1 Hz), atomically (written beside it, then renamed),
so a reader never sees half a file. ``attitude-bridge health`` is the container
HEALTHCHECK: healthy (exit 0) while the file is fresh, i.e. the service's loop is alive;
``--need-input`` also requires IMU data from a vehicle. It needs no network, no broker
and no port: a health check must not depend on what it is checking.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

from .cli import seconds

STATUS_FILE_ENV = "ATTITUDE_BRIDGE_STATUS_FILE"
#: How far in the future a status file's time may be (the writer's and the reader's
#: clocks are the same machine's; this covers a step of the clock between the two).
CLOCK_SLACK_S = 2.0
EXIT_HEALTHY, EXIT_UNHEALTHY = 0, 1


def check_status_path(path: str | Path) -> None:
    """ValueError for a status file path that is not a regular file: the file is
    replaced by a rename, which would put a regular file where a device (/dev/null) or
    a pipe was — as root, for every other program on the machine."""
    p = Path(path)
    if p.exists() and not p.is_file():
        raise ValueError(f"--status-file {p}: not a regular file (it is replaced by a "
                         f"rename at every update); give a file name")


def write_status_file(path: str | Path, status: dict[str, Any]) -> None:
    """Replace ``path`` with ``status`` as JSON in one step (rename is atomic)."""
    from ..publish.mqtt import _encode

    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(_encode(status), encoding="utf-8")
    os.replace(tmp, path)


def check(path: Path, max_age_s: float, need_input: bool,
          now: float | None = None) -> tuple[bool, str]:
    """(healthy, one line saying why) for a status file."""
    try:
        status = json.loads(path.read_text(encoding="utf-8"))
        written = float(status["time_unix"])
    except FileNotFoundError:
        return False, f"no status file {path} (is the bridge running with --status-file?)"
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return False, f"unreadable status file {path}: {exc}"
    age = (time.time() if now is None else now) - written
    if not math.isfinite(age):
        return False, f"unreadable status file {path}: time_unix {written!r} is not a time"
    if age < -CLOCK_SLACK_S:  # a file from the future: not this clock's, or forged
        return False, (f"status file {path} written {-age:.0f} s in the future (another "
                       f"machine's clock, or not the bridge's file)")
    if age > max_age_s:
        return False, f"status {age:.0f} s old (the bridge is stuck or stopped)"
    vehicles = status.get("vehicles", {})
    rates = {s: v.get("input_rate_hz", 0.0) for s, v in vehicles.items()}
    if need_input and not any(r > 0 for r in rates.values()):
        return False, "alive, but no IMU data from any vehicle"
    mqtt = status.get("mqtt")
    parts = [f"updated {age:.1f} s ago"]
    parts += [f"vehicle {s} {r:.0f} Hz" for s, r in sorted(rates.items())] or ["no vehicle yet"]
    if mqtt is not None:
        parts.append("mqtt up" if mqtt.get("connected") else "mqtt down")
    return True, ", ".join(parts)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "health", help="check a running bridge through its status file (container "
                       "HEALTHCHECK)",
        description="Exit 0 if the bridge wrote its status file recently, 1 otherwise, "
                    "with one line saying why.")
    p.add_argument("--status-file", type=Path, default=os.environ.get(STATUS_FILE_ENV),
                   metavar="PATH", help=f"the bridge's --status-file (default: "
                                        f"${STATUS_FILE_ENV})")
    p.add_argument("--max-age", type=seconds, default=5.0, metavar="S",
                   help="older than this is unhealthy (default 5)")
    p.add_argument("--need-input", action="store_true",
                   help="unhealthy unless a vehicle's IMU data is coming in")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    if args.status_file is None:
        raise ValueError(f"no status file given (--status-file or {STATUS_FILE_ENV})")
    ok, why = check(args.status_file, args.max_age, args.need_input)
    print(f"{'healthy' if ok else 'unhealthy'}: {why}", file=sys.stdout if ok else sys.stderr)
    return EXIT_HEALTHY if ok else EXIT_UNHEALTHY
