"""Bridge settings: one dataclass, filled from a TOML file, the environment and the
command line (each overriding the one before).

A setting has one name everywhere: its command-line option. In a TOML file the key is
the option name, with dashes or underscores (``peer-timeout = 10``, ``estimator =
["eskf", "mahony:kp=0.5"]``, ``no-aiding = true``); in the environment it is
``ATTITUDE_BRIDGE_`` + the name in capitals (``ATTITUDE_BRIDGE_MQTT_PASSWORD``; lists
separated by spaces). The field names below are accepted too (files written before the
option names were). Unknown keys are refused with the list of valid ones: a typo must
not silently fall back to a default.
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import estimators
from estimators.spec import EstimatorSpec
from imu.boards import PROFILES
from imu.calibration import SensorCalibration
from imu.rotations import rotation_matrix

from ..vehicle.negotiate import parse_forced
from ..wire.mav import BRIDGE_COMPONENT_ID, mavlink
from .config_checks import check_outputs, check_ranges, check_types, parse_source

#: Personalities of the built-in emulator (hil.personality.AUTOPILOTS; not imported
#: here: a bridge on a real vehicle need not load the emulator).
EMULATOR_AUTOPILOTS = ("stm32", "px4", "ardupilot")

#: Preferred default primary estimator, first one available wins.
DEFAULT_ESTIMATORS = ("eskf", "mahony", "madgwick", "quaternion")


#: Command-line option (underscored) -> the field it sets, where the names differ.
OPTION_FIELDS = {
    "estimator": "estimators", "out": "outs", "vehicle": "vehicles",
    "declination": "declination_deg", "profile": "emulator_profile",
    "seed": "emulator_seed", "fast": "emulator_fast", "peer_timeout": "peer_timeout_s",
    "source_timeout": "source_timeout_s", "evict_after": "evict_after_s",
    "clock_resync": "clock_resync_s", "reinit_gap": "reinit_gap_s",
    "reinit_settle": "reinit_settle_s", "idle_timeout": "idle_timeout_s",
    "gyro_range": "gyro_range_dps", "accel_range": "accel_range_g",
    "mag_range": "mag_range_gauss", "aid_max_age": "aid_max_age_s",
}
#: Options that switch a setting off (``no-aiding = true`` is ``aiding = false``).
NEGATED_OPTIONS = {"no_aiding": "aiding"}
#: Settings without a command-line option (file and environment only).
FILE_ONLY = ("mqtt_prefix", "system_id", "jump_s", "reorder_s", "window_s",
             "status_period_s")
ENV_PREFIX = "ATTITUDE_BRIDGE_"
#: ATTITUDE_BRIDGE_* variables that are not settings.
ENV_NOT_SETTINGS = frozenset({"DATA", "DEBUG", "CONFIG"})

#: Mounting rotations by name: MAVLink's MAV_SENSOR_ORIENTATION (PX4's and ArduPilot's
#: tables, which agree) plus ArduPilot's later PITCH_7, ROLL_45 and ROLL_315.
STANDARD_ROTATIONS = tuple(
    [e.name.removeprefix("MAV_SENSOR_ROTATION_") for _, e in
     sorted(mavlink.enums["MAV_SENSOR_ORIENTATION"].items())
     if e.name.startswith("MAV_SENSOR_ROTATION_") and e.name != "MAV_SENSOR_ROTATION_CUSTOM"]
    + ["PITCH_7", "ROLL_45", "ROLL_315"])


def check_rotation(name: str) -> None:
    """ValueError unless ``name`` is a standard mounting rotation (``YAW_90``,
    ``ROTATION_YAW_90``): ``YAW_91`` is a typo, not a mounting an autopilot knows."""
    text = str(name).strip().upper().removeprefix("MAV_SENSOR_").removeprefix("ROTATION_")
    if text not in STANDARD_ROTATIONS:
        raise ValueError(
            f"unknown rotation {name!r}; use a PX4/ArduPilot name: "
            f"{', '.join(STANDARD_ROTATIONS)} (a board mounted at another angle: "
            f"`attitude-bridge calibrate` measures it)")


def normalise_key(key: str) -> str:
    """``--peer-timeout`` / ``peer-timeout`` / ``PEER_TIMEOUT`` -> ``peer_timeout``."""
    return str(key).strip().lstrip("-").lower().replace("-", "_")


def default_estimator() -> str:
    available = estimators.names()
    for name in DEFAULT_ESTIMATORS:
        if name in available:
            return name
    return available[0]


#: MAV_COMP_ID_AUTOPILOT1: where a vehicle's IMU streams come from.
AUTOPILOT_COMPONENT_ID = 1


#: Settings that name a file: relative ones in a settings file are relative to it.
PATH_SETTINGS = ("calibration", "record", "status_file", "mqtt_ca", "mqtt_cert", "mqtt_key",
                 "signing_key")


def _beside(settings: Path, value: str) -> str:
    """``value`` (a path, or a signing key's ``file:PATH``) relative to the settings
    file's folder; absolute paths, ``env:NAME`` and empty values as given."""
    prefix = ""
    if value.startswith("env:") or not value.strip():
        return value
    if value.startswith("file:"):
        prefix, value = "file:", value[5:]
    if value.startswith("~"):
        return prefix + str(Path(value).expanduser())
    if not value.strip() or Path(value).is_absolute():
        return prefix + value
    return prefix + str(settings.parent / value)


@dataclass
class BridgeConfig:
    """Everything the bridge service needs to run."""

    connect: str | None = None  # None: start the built-in emulator as the source
    estimators: list[str] = field(default_factory=list)  # "name[:k=v,...]"; first = primary
    outs: list[str] = field(default_factory=list)
    mqtt: str | None = None  # mqtt://[user:pass@]host:port or mqtts://...
    mqtt_username: str | None = None
    mqtt_password: str | None = None
    mqtt_tls: bool = False
    mqtt_ca: str | None = None
    mqtt_cert: str | None = None
    mqtt_key: str | None = None
    mqtt_rate: float = 10.0  # per-estimator attitude messages per second per source
    mqtt_prefix: str = "attitude"
    # What RAW_IMU integers mean (imu.boards); None: from the vehicle's autopilot
    # (ArduPilot: "ardupilot", anything else: "gy86").
    board: str | None = None
    rotation: str = "NONE"
    # Sensor calibration TOML (``attitude-bridge calibrate`` writes one), applied to every
    # IMU sample after board scaling and rotation. None: uncalibrated.
    calibration: str | None = None
    # Magnetic declination [deg, east positive]: estimators find magnetic north, MAVLink
    # and the truth use true north. None: 0, or the emulator's when it is the source.
    declination_deg: float | None = None
    # Velocity aiding from the vehicle's LOCAL_POSITION_NED / GLOBAL_POSITION_INT /
    # GPS_RAW_INT (bridge.aiding); a velocity older than aid_max_age_s when its IMU
    # sample comes is dropped.
    aiding: bool = True
    aid_max_age_s: float = 0.5
    # IMU stream to ask the vehicle for; None: negotiated from its autopilot
    # (bridge.negotiate); "A,B": these, in this order.
    imu_message: str | None = None
    imu_rate: float = 250.0  # requested IMU rate [Hz]; also the estimators' nominal rate
    out_rate: float = 50.0  # ATTITUDE(_QUATERNION) per second per source; <= 0: every sample
    component_id: int = BRIDGE_COMPONENT_ID
    system_id: int = 1  # heartbeat sysid until a vehicle is heard
    signing_key: str | None = None  # env:NAME, file:PATH or a path; enables MAVLink 2 signing
    allow_unsigned: bool = False
    jump_s: float = 0.1  # shortest timestamp step treated as a clock jump / outage
    reorder_s: float = 0.5  # how far back a late sample is considered reordered
    # --- who is served, and bounds under attack (see bridge.vehicle, bridge.admission)
    vehicles: list[int] = field(default_factory=list)  # sysids served; []: first autopilot
    imu_id: int | None = None  # the primary IMU's index (RAW_IMU/HIGHRES_IMU id); None: first
    truth_source: str | None = None  # "SYSID:COMPID" of HIL_STATE_QUATERNION; None: autopilot
    max_peers: int = 32  # UDP peers answered at once
    peer_timeout_s: float = 10.0  # a silent peer stops getting output after this
    max_source_rate: float = 10000.0  # messages/s per (sysid, compid) admitted to parsing
    source_timeout_s: float = 3.0  # a primary IMU silent this long may be replaced
    evict_after_s: float = 30.0  # a vehicle's estimators/history are dropped after this silence
    clock_resync_s: float = 1.0  # board time of consistent stamps needed for a new timeline
    reinit_gap_s: float = 1.0  # an outage this long restarts the estimate
    reinit_settle_s: float = 1.0  # after a restart, MAVLink output waits this long
    idle_timeout_s: float = 5.0  # TCP/serial: reconnect after this long without a message
    gyro_range_dps: float = 2000.0  # sensor full scale: readings beyond it are rejected
    accel_range_g: float = 16.0
    mag_range_gauss: float = 8.0
    window_s: float = 10.0  # live comparison window
    status_period_s: float = 1.0
    duration: float | None = None  # stop after this many seconds
    table: bool = False  # live table on stdout
    record: str | None = None  # .tlog of the connection's traffic, in and out
    status_file: str | None = None  # status JSON rewritten every status period (health)
    web: str | None = None  # "[HOST:]PORT" of the live web view (bridge.publish.web)
    # Built-in emulator (no --connect): profile, seed, IMU message, faster than real time.
    emulator_profile: str = "flight"
    emulator_seed: int = 1
    emulator_fast: bool = False
    emulator_autopilot: str = "stm32"  # its personality: stm32, px4 or ardupilot
    emulator_gps: bool = False  # fit it with a GPS (velocity aiding, position)

    def __post_init__(self) -> None:
        if not self.estimators:
            self.estimators = [default_estimator()]

    @property
    def estimator_specs(self) -> list[EstimatorSpec]:
        return [EstimatorSpec.parse(text) for text in self.estimators]

    def validate(self) -> None:
        """Raise ValueError naming the bad setting, before anything is started."""
        from ..wire.codec import load_signing_key
        from ..wire.links import parse_url

        check_types(self)
        check_ranges(self)
        if self.signing_key is not None:  # "" (an unset variable) is no "signing off"
            try:
                load_signing_key(self.signing_key)
            except ValueError as exc:
                raise ValueError(f"--signing-key {self.signing_key}: {exc}") from None
        if self.connect is not None:  # "" (an unset shell variable) is no emulator request
            parse_url(self.connect)
        for url in self.outs:
            parse_url(url)
        for spec in self.estimator_specs:
            spec.validate()
        if self.board is not None and self.board not in PROFILES:
            raise ValueError(f"unknown board {self.board!r}; valid: {sorted(PROFILES)}")
        check_rotation(self.rotation)
        rotation_matrix(self.rotation)
        self.sensor_calibration()
        parse_forced(self.imu_message)
        if self.emulator_autopilot not in EMULATOR_AUTOPILOTS:
            raise ValueError(f"unknown emulator autopilot {self.emulator_autopilot!r}; "
                             f"valid: {', '.join(EMULATOR_AUTOPILOTS)}")
        if not self.connect:  # the built-in emulator is the source
            from .emulator import check_emulator

            check_emulator(self)
            if self.signing_key is not None and not self.allow_unsigned:
                raise ValueError("--signing-key with the built-in emulator: it does not "
                                 "sign, so every message would be refused (give "
                                 "--connect, or --allow-unsigned)")
        if self.allow_unsigned and self.signing_key is None:
            raise ValueError("--allow-unsigned without --signing-key: with no key nothing "
                             "is signed or checked (give --signing-key, or drop "
                             "--allow-unsigned)")
        if not 1 <= self.component_id <= 255 or not 1 <= self.system_id <= 255:
            raise ValueError("component_id and system_id must be in 1..255")
        if self.component_id == AUTOPILOT_COMPONENT_ID:
            raise ValueError(f"component_id {AUTOPILOT_COMPONENT_ID} is the autopilot's "
                             f"(MAV_COMP_ID_AUTOPILOT1): the bridge would take the vehicle's "
                             f"messages for its own echo and serve nothing")
        from ..publish.mqtt import check_mqtt_settings

        check_mqtt_settings(self)
        if self.web is not None:
            from ..publish.web import parse_web

            parse_web(self.web)
        # each writable and neither the other's (the status would overwrite the recording)
        check_outputs(((self.record, "--record"), (self.status_file, "--status-file")), [])
        if self.status_file is not None:
            from .health import check_status_path

            check_status_path(self.status_file)

    @property
    def truth(self) -> tuple[int, int] | None:
        return parse_source(self.truth_source) if self.truth_source else None

    def sensor_calibration(self) -> SensorCalibration | None:
        """The calibration file's contents (ValueError naming the file if it is bad)."""
        return SensorCalibration.load(self.calibration) if self.calibration else None

    @classmethod
    def from_toml(cls, path: str | Path) -> BridgeConfig:
        """Settings from a TOML file (keys: option names)."""
        return cls(**cls.fields_from_toml(path))

    @classmethod
    def fields_from_toml(cls, path: str | Path) -> dict[str, Any]:
        """{field: value} of a TOML settings file; a relative path in it (calibration,
        recording, status, TLS and signing-key files) is taken relative to the settings
        file, whatever the folder the bridge is started from (a service's is often /).
        Every error names the file."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ValueError(f"settings file {path} does not exist") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"cannot read settings file {path}: "
                             f"{getattr(exc, 'strerror', None) or exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"settings file {path} is not valid TOML: {exc}") from None
        try:
            fields = cls.fields_from(data)
        except ValueError as exc:
            raise ValueError(f"settings file {path}: {exc}") from None
        for name in PATH_SETTINGS:
            value = fields.get(name)
            if isinstance(value, str):
                fields[name] = _beside(path, value)
        return fields

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> BridgeConfig:
        return cls(**cls.fields_from(data))

    @classmethod
    def fields_from(cls, data: Mapping[str, Any]) -> dict[str, Any]:
        """Settings by option name (or field name) -> {field: value}; ValueError for an
        unknown name, listing the valid ones. A list setting takes one value too."""
        out: dict[str, Any] = {}
        for key, value in data.items():
            name, negated = cls.field_of(key)
            if negated:
                if not isinstance(value, bool):
                    raise ValueError(f"setting {key!r} must be true or false, got {value!r}")
                value = not value
            if isinstance(value, str | int) and cls._is_list(name):
                value = [value]
            if name in out:
                raise ValueError(f"setting {key!r} given twice (as {name!r})")
            out[name] = value
        return out

    @classmethod
    def field_of(cls, key: str) -> tuple[str, bool]:
        """(field name, negated) for an option or field name; ValueError otherwise."""
        k = normalise_key(key)
        names = {f.name for f in dataclasses.fields(cls)}
        if k in NEGATED_OPTIONS:
            return NEGATED_OPTIONS[k], True
        name = OPTION_FIELDS.get(k, k)
        if name not in names:
            raise ValueError(f"unknown setting {key!r}; valid: {', '.join(cls.user_names())}")
        return name, False

    @classmethod
    def user_names(cls) -> list[str]:
        """Every setting's name at the user surface (its option name, dashed)."""
        by_field = {f: o for o, f in OPTION_FIELDS.items() if not o.endswith("declination")}
        by_field.update({f: o for o, f in NEGATED_OPTIONS.items()})
        return sorted(by_field.get(f.name, f.name).replace("_", "-")
                      for f in dataclasses.fields(cls))

    @classmethod
    def _is_list(cls, name: str) -> bool:
        kind = {f.name: str(f.type) for f in dataclasses.fields(cls)}[name]
        return kind.startswith("list")

    @classmethod
    def fields_from_env(cls, environ: Mapping[str, str] | None = None) -> dict[str, Any]:
        """Settings from ``ATTITUDE_BRIDGE_<OPTION>`` variables (strings, converted by
        the setting's type; lists separated by white space). Keeps secrets such as
        ``ATTITUDE_BRIDGE_MQTT_PASSWORD`` off the command line."""
        environ = os.environ if environ is None else environ
        out: dict[str, Any] = {}
        kinds = {f.name: str(f.type) for f in dataclasses.fields(cls)}
        for var, text in environ.items():
            if not var.startswith(ENV_PREFIX) or var[len(ENV_PREFIX):] in ENV_NOT_SETTINGS:
                continue
            try:
                name, negated = cls.field_of(var[len(ENV_PREFIX):])
                value = _from_text(kinds[name], text)
            except ValueError as exc:
                raise ValueError(f"environment variable {var}: {exc}") from None
            out[name] = (not value) if negated else value
        return out

    def merged(self, **overrides: Any) -> BridgeConfig:
        """A copy with every override that is not None (or an empty list) applied."""
        changes = {k: v for k, v in overrides.items() if v is not None and v != []}
        return dataclasses.replace(self, **changes)


_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off", "")


def _from_text(kind: str, text: str) -> Any:
    """An environment variable's text as a setting of the declared type."""
    base = kind.replace(" | None", "").strip()
    value = text.strip()
    if base == "bool":
        if value.lower() in _TRUE:
            return True
        if value.lower() in _FALSE:
            return False
        raise ValueError(f"expected true or false, got {text!r}")
    if base.startswith("list"):
        items = value.split()
        return [_from_text(base[5:-1], v) for v in items]
    if "None" in kind and value == "":
        return None
    try:
        if base == "float":
            return float(value)
        if base == "int":
            return int(value)
    except ValueError:
        raise ValueError(f"expected a number, got {text!r}") from None
    return value
