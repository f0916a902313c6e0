"""`attitude-bridge run` and `attitude-bridge demo`.

Settings come from, in increasing precedence: defaults, the ``--config`` TOML file (or
``ATTITUDE_BRIDGE_CONFIG``), ``ATTITUDE_BRIDGE_*`` environment variables, the command
line (see :mod:`bridge.app.config`). Errors are raised as ``ValueError`` / ``OSError`` and
reported as one line by the CLI's error boundary (:mod:`bridge.app.cli`).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import signal
import sys
from collections.abc import Mapping

import estimators

from .cli import seconds
from .config import BridgeConfig

log = logging.getLogger(__name__)

#: What `demo` compares side by side unless --estimator is given (first = primary).
DEMO_ESTIMATORS = ("eskf", "mahony", "madgwick", "kalman")


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--estimator", "-e", action="append", dest="estimators",
                   metavar="NAME[:k=v,...]",
                   help="estimator to run (repeatable); the first is primary and goes out "
                        "over MAVLink (default: eskf)")
    p.add_argument("--out", action="append", dest="outs", metavar="URL",
                   help="extra MAVLink output, e.g. udpout:127.0.0.1:14550 (repeatable)")
    p.add_argument("--mqtt", metavar="URL", help="publish to MQTT: mqtt://host:port or "
                                                 "mqtts://... (TLS); credentials from "
                                                 "ATTITUDE_BRIDGE_MQTT_USERNAME/_PASSWORD")
    p.add_argument("--mqtt-username")
    p.add_argument("--mqtt-password",
                   help="visible to every user of this machine (ps): prefer the "
                        "ATTITUDE_BRIDGE_MQTT_PASSWORD environment variable or the "
                        "settings file")
    p.add_argument("--mqtt-tls", action="store_true", default=None, help="use TLS")
    p.add_argument("--mqtt-ca", metavar="FILE", help="CA bundle for the broker's certificate")
    p.add_argument("--mqtt-cert", metavar="FILE", help="client certificate (mutual TLS)")
    p.add_argument("--mqtt-key", metavar="FILE", help="client key (mutual TLS)")
    p.add_argument("--mqtt-rate", type=float, metavar="HZ",
                   help="attitude messages per estimator per second (default 10)")
    p.add_argument("--board", choices=("gy86", "ardupilot"),
                   help="what RAW_IMU integers mean (default: from the vehicle's autopilot, "
                        "ArduPilot: ardupilot, others: gy86)")
    p.add_argument("--rotation", metavar="NAME",
                   help="board mounting rotation, a PX4/ArduPilot/MAVLink name, e.g. YAW_90, "
                        "ROLL_180_YAW_90")
    p.add_argument("--calibration", metavar="FILE.toml",
                   help="sensor calibration to apply to every IMU sample (written by "
                        "`attitude-bridge calibrate`)")
    p.add_argument("--declination-deg", "--declination", dest="declination_deg", type=float,
                   metavar="DEG",
                   help="magnetic declination, east positive, to report true north (default: "
                        "the vehicle's own parameter EKF2_MAG_DECL / COMPASS_DEC, else the "
                        "World Magnetic Model at its position, else 0)")
    p.add_argument("--imu-message", metavar="NAME[,NAME...]",
                   help="IMU stream to ask the vehicle for: RAW_IMU, SCALED_IMU, SCALED_IMU2, "
                        "SCALED_IMU3 or HIGHRES_IMU; several (comma-separated) are tried in "
                        "order (default: negotiated from its autopilot, e.g. PX4 HIGHRES_IMU)")
    p.add_argument("--imu-rate", type=float, metavar="HZ",
                   help="IMU rate to request (MAV_CMD_SET_MESSAGE_INTERVAL), default 250")
    p.add_argument("--out-rate", type=float, metavar="HZ",
                   help="ATTITUDE/ATTITUDE_QUATERNION rate per vehicle, <= 0: every sample "
                        "(default 50)")
    p.add_argument("--component-id", type=int, metavar="ID", help="own component id (191)")
    p.add_argument("--signing-key", metavar="env:VAR|file:PATH",
                   help="MAVLink 2 signing key: 64 hex digits or a passphrase (not all "
                        "hex digits); unsigned input is then rejected and counted")
    p.add_argument("--allow-unsigned", action="store_true", default=None,
                   help="with --signing-key: accept unsigned input too")
    g = p.add_argument_group("who is served, and bounds under attack")
    g.add_argument("--vehicle", action="append", dest="vehicles", type=int, metavar="SYSID",
                   help="system id to serve (repeatable); default: the first autopilot "
                        "heard. Other system ids get nothing but our output")
    g.add_argument("--imu-id", type=int, metavar="N",
                   help="primary IMU index (RAW_IMU/HIGHRES_IMU id); default: the first heard")
    g.add_argument("--truth-source", metavar="SYSID:COMPID",
                   help="sender of HIL_STATE_QUATERNION truth (default: the vehicle's "
                        "autopilot)")
    g.add_argument("--max-peers", type=int, metavar="N",
                   help="UDP peers answered at once (default 32)")
    g.add_argument("--peer-timeout", dest="peer_timeout_s", type=float, metavar="S",
                   help="a silent UDP peer stops getting output after S seconds (10)")
    g.add_argument("--max-source-rate", type=float, metavar="MSG/S",
                   help="messages per second per sender (sysid, compid) admitted to "
                        "parsing (10000)")
    g.add_argument("--source-timeout", dest="source_timeout_s", type=float, metavar="S",
                   help="a primary IMU silent this long may be replaced (3)")
    g.add_argument("--evict-after", dest="evict_after_s", type=float, metavar="S",
                   help="drop a silent vehicle's estimators and history after S seconds (30)")
    g.add_argument("--clock-resync", dest="clock_resync_s", type=float, metavar="S",
                   help="board time of consistent stamps needed to adopt a new timeline (1)")
    g.add_argument("--reinit-gap", dest="reinit_gap_s", type=float, metavar="S",
                   help="an outage this long restarts the estimate (1)")
    g.add_argument("--reinit-settle", dest="reinit_settle_s", type=float, metavar="S",
                   help="after a restart, MAVLink output waits S seconds of board time (1)")
    g.add_argument("--idle-timeout", dest="idle_timeout_s", type=float, metavar="S",
                   help="TCP/serial: reconnect after S seconds without a valid message (5)")
    g.add_argument("--gyro-range", dest="gyro_range_dps", type=float, metavar="DEG/S",
                   help="gyro full scale: readings beyond it are rejected (2000)")
    g.add_argument("--accel-range", dest="accel_range_g", type=float, metavar="G",
                   help="accelerometer full scale (16)")
    g.add_argument("--mag-range", dest="mag_range_gauss", type=float, metavar="GAUSS",
                   help="magnetometer full scale (8)")
    p.add_argument("--config", metavar="FILE.toml",
                   help="settings file, keys = these options' names, e.g. peer-timeout = 10 "
                        "(default: $ATTITUDE_BRIDGE_CONFIG; the environment and options "
                        "override it)")
    p.add_argument("--duration", type=seconds, metavar="S", help="stop after S seconds")
    p.add_argument("--record", metavar="FILE.tlog",
                   help="record every MAVLink frame of the connection, in and out, with "
                        "its time (replay it with `attitude-bridge replay FILE.tlog`)")
    p.add_argument("--status-file", metavar="PATH",
                   help="rewrite the status (JSON) here every second, for `attitude-bridge "
                        "health` and other local monitors")
    p.add_argument("--web", metavar="[HOST:]PORT",
                   help="serve a live view of every vehicle and estimator to browsers at "
                        "http://HOST:PORT/ (read-only; HOST defaults to 127.0.0.1: give "
                        "0.0.0.0 to let other machines look)")
    p.add_argument("--profile", dest="emulator_profile", metavar="NAME",
                   help="built-in emulator's motion profile (no --connect), default flight")
    p.add_argument("--seed", dest="emulator_seed", type=int, help="built-in emulator seed")
    p.add_argument("--fast", dest="emulator_fast", action="store_true", default=None,
                   help="run the built-in emulator faster than real time")
    p.add_argument("--emulator-autopilot", choices=("stm32", "px4", "ardupilot"),
                   help="built-in emulator's autopilot personality (default stm32)")
    p.add_argument("--emulator-gps", action="store_true", default=None,
                   help="fit the built-in emulator with a GPS (5 Hz, 0.1 s latency)")
    p.add_argument("--no-aiding", dest="aiding", action="store_false", default=None,
                   help="do not use the vehicle's velocity (LOCAL_POSITION_NED, "
                        "GLOBAL_POSITION_INT, GPS_RAW_INT) to aid the estimators")
    p.add_argument("--aid-max-age", dest="aid_max_age_s", type=float, metavar="S",
                   help="a velocity older than this when its IMU sample comes is dropped "
                        "(0.5)")
    talk = p.add_mutually_exclusive_group()
    talk.add_argument("-v", "--verbose", action="store_true",
                      help="log more (DEBUG; INFO with the live table)")
    talk.add_argument("-q", "--quiet", action="store_true", help="log warnings only")


def register(subparsers: argparse._SubParsersAction) -> None:
    run = subparsers.add_parser(
        "run", help="run the bridge: MAVLink IMU in, attitude out over MAVLink and MQTT",
        description="Estimate attitude from a vehicle's IMU stream. With no --connect, the "
                    "built-in GY-86 emulator is started as the source.")
    run.add_argument("--connect", metavar="URL",
                     help="udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or a serial "
                          "device (/dev/ttyUSB0:921600)")
    run.add_argument("--table", action="store_true", default=None, help="show the live table")
    _add_common(run)
    run.set_defaults(func=lambda a: main(a, demo=False))
    demo = subparsers.add_parser(
        "demo", help="emulator + bridge in one process, with the live table and a summary",
        description="Runs the HIL emulator and the bridge together and shows the estimate "
                    "against the emulator's truth.")
    _add_common(demo)
    demo.set_defaults(func=lambda a: main(a, demo=True), connect=None, table=True)


#: Settings that only the command line gives (not files nor the environment).
_ARG_ONLY = ("config", "verbose", "quiet", "func", "command")


def config_from_args(args: argparse.Namespace, demo: bool,
                     environ: Mapping[str, str] | None = None) -> BridgeConfig:
    """Defaults < settings file < environment < command line."""
    environ = os.environ if environ is None else environ
    path = args.config or environ.get("ATTITUDE_BRIDGE_CONFIG")
    given = BridgeConfig.fields_from_toml(path) if path else {}
    given.update(BridgeConfig.fields_from_env(environ))
    overrides = {k: getattr(args, k) for k in (
        "connect", "estimators", "outs", "mqtt", "mqtt_username", "mqtt_password", "mqtt_tls",
        "mqtt_ca", "mqtt_cert", "mqtt_key", "mqtt_rate", "board", "rotation", "calibration",
        "declination_deg",
        "imu_message",
        "imu_rate", "out_rate", "component_id", "signing_key", "allow_unsigned", "duration",
        "table", "emulator_profile", "emulator_seed", "emulator_fast", "vehicles", "imu_id",
        "truth_source", "max_peers", "peer_timeout_s", "max_source_rate", "source_timeout_s",
        "evict_after_s", "clock_resync_s", "reinit_gap_s", "reinit_settle_s", "idle_timeout_s",
        "gyro_range_dps", "accel_range_g", "mag_range_gauss", "emulator_autopilot",
        "emulator_gps", "aiding", "aid_max_age_s", "record", "status_file", "web")}
    base = BridgeConfig(**given)
    if demo:
        overrides["connect"] = None
        if not args.estimators and "estimators" not in given:
            overrides["estimators"] = [n for n in DEMO_ESTIMATORS if n in estimators.names()]
        if base.duration is None and args.duration is None:
            overrides["duration"] = 30.0
    cfg = base.merged(**overrides)
    if demo:
        cfg.connect = None
    return cfg


async def serve(cfg: BridgeConfig) -> int:
    """Run until SIGINT/SIGTERM or the configured duration; print the summary."""
    from .emulator import builtin_emulator
    from .service import BridgeService
    from .table import LiveTable, summary
    from .warmup import LineProgress

    emulator = None
    if not cfg.connect:
        # (Its declination comes from its position like any vehicle's.)
        emulator = builtin_emulator(cfg)
    service = BridgeService(cfg, emulator)
    # numba compiles each filter on its very first use (up to a minute each, then cached
    # on disk; `attitude-bridge warmup` does it ahead): show which one, never a silent
    # terminal.
    progress = LineProgress("attitude-bridge: preparing estimators (compiled on first "
                            "use, then cached)", len(cfg.estimators) + 1)
    service.on_progress = progress
    if cfg.table:
        service.on_status = LiveTable()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, stop.set)
    try:
        await service.run(stop)
    finally:
        progress.done()
    print(summary(service), flush=True)
    return 0


def log_level(args: argparse.Namespace, table: bool) -> int:
    """A service talks (INFO); with the live table showing it all, warnings only."""
    if args.quiet:
        return logging.WARNING
    if args.verbose:
        return logging.INFO if table else logging.DEBUG
    return logging.WARNING if table else logging.INFO


def main(args: argparse.Namespace, demo: bool) -> int:
    cfg = config_from_args(args, demo)
    cfg.validate()
    logging.basicConfig(level=log_level(args, cfg.table), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(message)s")
    return asyncio.run(serve(cfg))
