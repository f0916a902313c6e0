"""``attitude-bridge hil``: run the software GY-86 and stream MAVLink 2 over UDP."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import re
import signal
import sys
from dataclasses import fields
from pathlib import Path

from bridge.app.cli import seconds  # the command line's shared option types
from bridge.app.config_checks import check_output_file

from .config import IMU_MESSAGES, EmulatorConfig
from .environment import HOME_ALT_M, HOME_LAT_DEG, HOME_LON_DEG, Environment
from .faults import FaultConfig, FaultSettingError
from .gps import GpsConfig
from .link import Emulator
from .motion import PROFILE_NAMES
from .multirotor import DEFAULT_DRAG_PER_S
from .personality import AUTOPILOTS
from .source import SampleSource

PACING_SWITCH_INTERVAL_S = 1e-3
#: What argparse takes for a negative number (so not for an option) on the hil command
#: line: its own ``-5`` / ``-.5`` plus a comma list that starts with one, so that
#: ``--home -33.9,151.2`` works like ``--home=-33.9,151.2`` (no hil option looks like it).
NEGATIVE_VALUE = re.compile(r"^-\d+$|^-\d*\.\d+$|^-\.?\d[\d.eE+-]*(,[-+\d.eE]*)+$")


def non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return value

FAULT_HELP = {
    "loss": "probability a datagram is dropped",
    "duplicate": "probability a datagram is sent twice",
    "reorder": "probability a datagram is swapped with the next one",
    "corrupt": "probability 1-3 bytes of a datagram are changed (CRC catches it)",
    "truncate": "probability a datagram is cut short",
    "time_jump_rate_hz": "board clock jumps forward, events per second",
    "time_jump_s": "size of a forward clock jump [s]",
    "time_backwards_rate_hz": "board clock steps backwards, events per second",
    "time_backwards_s": "size of a backward clock step [s]",
    "saturation_rate_hz": "an IMU axis pinned at full scale, events per second",
    "saturation_duration_s": "length of a saturation event [s]",
    "stuck_rate_hz": "IMU readings frozen (re-sent unchanged), events per second",
    "stuck_duration_s": "length of a stuck event [s]",
    "vibration_g": "accelerometer vibration amplitude [g] (continuous)",
    "vibration_dps": "gyro vibration amplitude [deg/s] (continuous)",
    "vibration_hz": "vibration frequency [Hz]",
    "mag_disturbance_rate_hz": "a magnet nearby, events per second",
    "mag_disturbance_gauss": "extra field of a magnetic disturbance [gauss]",
    "mag_disturbance_duration_s": "length of a magnetic disturbance [s]",
    "gyro_bias_step_rate_hz": "gyro bias steps, events per second",
    "gyro_bias_step_dps": "size of a gyro bias step [deg/s]",
}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "hil", help="emulate a GY-86 on an STM32, streaming MAVLink 2 over UDP",
        description="Software GY-86 (MPU6050 + HMC5883L + MS5611) on an STM32: RAW_IMU, "
                    "SCALED_PRESSURE, HEARTBEAT and HIL_STATE_QUATERNION truth over UDP.")
    p.add_argument("--target", action="append", required=True, metavar="udp:HOST:PORT",
                   help="where to send (repeat for several targets)")
    p.add_argument("--profile", default="flight",
                   help=f"motion: {', '.join(PROFILE_NAMES)} or file:PATH (CSV time_s,qw,qx,qy,"
                        "qz); handheld_flight: carried by hand, then two flights (104 s)")
    p.add_argument("--rate", type=float, default=1000.0, help="IMU rate [Hz] (default 1000)")
    p.add_argument("--duration", type=seconds, default=0.0,
                   help="seconds of stream; 0 runs until interrupted (default)")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--fast", action="store_true", help="send as fast as possible (tests)")
    p.add_argument("--autopilot", default="stm32", metavar="NAME",
                   help=f"personality on the link: {', '.join(AUTOPILOTS)} (default stm32, the "
                        "seeds' board; px4 streams HIGHRES_IMU, ardupilot RAW_IMU in its units)")
    p.add_argument("--imu-message", default=None, metavar="NAME",
                   help=f"IMU stream at start-up ({', '.join(IMU_MESSAGES)}; default: the "
                        "autopilot's own)")
    p.add_argument("--no-flight-state", dest="flight_state", action="store_false",
                   help="a bare board that does not tell its flight state: no armed flag in "
                        "HEARTBEAT, EXTENDED_SYS_STATE refused (default: armed flag, "
                        "EXTENDED_SYS_STATE on request, as PX4 and ArduPilot)")
    p.add_argument("--sysid", type=int, default=1)
    p.add_argument("--truth-rate", type=float, default=None,
                   help="HIL_STATE_QUATERNION rate [Hz] (default: IMU rate, at most 1000)")
    p.add_argument("--clock-drift-ppm", type=float, default=0.0)
    p.add_argument("--clock-jitter-us", type=float, default=0.0)
    p.add_argument("--stats-json", type=Path, help="write the sent/fault counts here at exit")
    p.add_argument("--rotor-drag", type=float, default=DEFAULT_DRAG_PER_S, metavar="PER_S",
                   help="rotor drag of the `flight` and `handheld_flight` quadrotor [1/s] (default "
                        f"{DEFAULT_DRAG_PER_S}; real quads 0.3-0.6)")
    p.add_argument("--home", default=None, metavar="LAT,LON[,ALT]",
                   help="take-off point, WGS-84 degrees and metres AMSL (default PX4 SITL's "
                        f"{HOME_LAT_DEG},{HOME_LON_DEG},{HOME_ALT_M:g}); the Earth's field "
                        "comes from the World Magnetic Model there")
    gps = p.add_argument_group("GPS (u-blox-like: GPS_RAW_INT, GLOBAL_POSITION_INT, "
                               "LOCAL_POSITION_NED)")
    gps.add_argument("--gps", action="store_true", help="fit a GPS receiver")
    gps.add_argument("--gps-rate", type=float, default=GpsConfig.rate_hz, metavar="HZ",
                     help=f"fixes per second (default {GpsConfig.rate_hz:g})")
    gps.add_argument("--gps-latency", type=float, default=GpsConfig.latency_s, metavar="S",
                     help="from the instant a fix is valid to sending it (default "
                          f"{GpsConfig.latency_s:g})")
    faults = p.add_argument_group("faults")
    for f in fields(FaultConfig):
        faults.add_argument("--" + f.name.replace("_", "-"), dest=f"fault_{f.name}", type=float,
                            default=f.default, metavar="X",
                            help=f"{FAULT_HELP[f.name]} (default {f.default})")
    p.set_defaults(func=_run)
    # argparse (3.11) has no public switch for this; its own matcher is an attribute.
    p._negative_number_matcher = NEGATIVE_VALUE


def parse_target(text: str) -> tuple[str, int]:
    """``udp:HOST:PORT`` (or ``HOST:PORT``) -> (host, port); ValueError otherwise."""
    parts = text.split(":")
    if len(parts) == 3 and parts[0] in ("udp", "udpout"):
        parts = parts[1:]
    if len(parts) != 2 or not parts[1].isdigit():
        raise ValueError(f"target must look like udp:HOST:PORT, got {text!r}")
    return parts[0], int(parts[1])


def parse_home(text: str | None) -> Environment:
    """``LAT,LON[,ALT]`` -> the Environment at that place; ValueError otherwise."""
    if text is None:
        return Environment()
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
        raise ValueError(f"--home must look like LAT,LON[,ALT], got {text!r}")
    alt = values[2] if len(values) == 3 else HOME_ALT_M
    try:
        return Environment(latitude_deg=values[0], longitude_deg=values[1],
                           ground_altitude_m=alt)
    except ValueError as exc:
        raise ValueError(f"--home: {exc}") from exc


def config_from_args(args: argparse.Namespace) -> EmulatorConfig:
    try:
        return _config_from_args(args)
    except FaultSettingError as exc:  # name the option, as argparse does
        option = "--" + exc.setting.replace("_", "-")
        raise ValueError(f"argument {option}: {exc}") from exc


def _config_from_args(args: argparse.Namespace) -> EmulatorConfig:
    faults = FaultConfig(**{f.name: getattr(args, f"fault_{f.name}") for f in fields(FaultConfig)})
    gps = (GpsConfig(rate_hz=args.gps_rate, latency_s=args.gps_latency) if args.gps else None)
    return EmulatorConfig(
        profile=args.profile, rate_hz=args.rate,
        duration_s=args.duration if args.duration > 0 else None, seed=args.seed,
        sysid=args.sysid, autopilot=args.autopilot, imu_message=args.imu_message,
        fast=args.fast, faults=faults, flight_state=args.flight_state,
        truth_rate_hz=args.truth_rate, clock_drift_ppm=args.clock_drift_ppm,
        clock_jitter_us=args.clock_jitter_us, rotor_drag_per_s=args.rotor_drag, gps=gps,
        environment=parse_home(args.home))


def _run(args: argparse.Namespace) -> int:
    try:
        targets = [parse_target(t) for t in args.target]
        if args.stats_json:  # before streaming, not after it
            check_output_file(args.stats_json, "--stats-json")
        config = config_from_args(args)
        emulator = Emulator(config)
        SampleSource(config)  # builds the profile: a bad profile or drag fails here
    except ValueError as exc:
        print(f"attitude-bridge hil: error: {exc}", file=sys.stderr)
        return 2
    rate = config.imu_rate_hz
    if abs(rate - args.rate) > 1e-6:
        print(f"IMU rate {args.rate:g} Hz is not available on the MPU6050; using {rate:g} Hz",
              file=sys.stderr)
    until = f"for {config.duration_s:g} s" if config.duration_s else "until interrupted"
    gps = f", GPS at {config.gps.rate_hz:g} Hz" if config.gps else ""
    print(f"hil: {config.autopilot} board, {config.profile} at {rate:g} Hz{gps} to "
          f"{', '.join(args.target)} {until}{' (fast)' if config.fast else ''}", file=sys.stderr)
    # The chunk-making thread would otherwise hold the GIL for up to 5 ms at a time,
    # delaying the paced sends by as much.
    sys.setswitchinterval(PACING_SWITCH_INTERVAL_S)
    try:
        asyncio.run(_stream(emulator, targets))
    except ValueError as exc:
        print(f"attitude-bridge hil: error: {exc}", file=sys.stderr)
        return 2
    print(emulator.stats.summary(), file=sys.stderr)
    if args.stats_json:
        args.stats_json.write_text(json.dumps(emulator.stats.to_dict(), indent=2))
    return 0


async def _stream(emulator: Emulator, targets: list[tuple[str, int]]) -> None:
    """Run until the duration ends or SIGINT/SIGTERM arrives (then stop cleanly)."""
    task = asyncio.current_task()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, task.cancel)
    with contextlib.suppress(asyncio.CancelledError):
        await emulator.run(targets)
