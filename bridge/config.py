"""Bridge settings: one dataclass, filled from the command line or a TOML file.

TOML keys are the field names below (``estimators`` is a list of ``"name:k=v,..."``
strings, ``outs`` a list of URLs); command-line options override the file.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import estimators
from estimators.spec import EstimatorSpec
from imu.boards import PROFILES
from imu.calibration import SensorCalibration
from imu.rotations import rotation_matrix

from .mav import BRIDGE_COMPONENT_ID
from .negotiate import parse_forced

#: Personalities of the built-in emulator (hil.personality.AUTOPILOTS; not imported
#: here: a bridge on a real vehicle need not load the emulator).
EMULATOR_AUTOPILOTS = ("stm32", "px4", "ardupilot")

#: Preferred default primary estimator, first one available wins.
DEFAULT_ESTIMATORS = ("eskf", "mahony", "madgwick", "quaternion")


def default_estimator() -> str:
    available = estimators.names()
    for name in DEFAULT_ESTIMATORS:
        if name in available:
            return name
    return available[0]


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
        from .links import parse_url

        self._check_types()
        self._check_ranges()
        if self.connect:
            parse_url(self.connect)
        for url in self.outs:
            parse_url(url)
        for spec in self.estimator_specs:
            spec.validate()
        if self.board is not None and self.board not in PROFILES:
            raise ValueError(f"unknown board {self.board!r}; valid: {sorted(PROFILES)}")
        rotation_matrix(self.rotation)
        self.sensor_calibration()
        parse_forced(self.imu_message)
        if self.emulator_autopilot not in EMULATOR_AUTOPILOTS:
            raise ValueError(f"unknown emulator autopilot {self.emulator_autopilot!r}; "
                             f"valid: {', '.join(EMULATOR_AUTOPILOTS)}")
        if not 1 <= self.component_id <= 255 or not 1 <= self.system_id <= 255:
            raise ValueError("component_id and system_id must be in 1..255")
        if self.mqtt:
            from .mqtt import MqttSettings

            MqttSettings.from_url(self.mqtt)

    def _check_types(self) -> None:
        """Every setting of the type it is declared with (a TOML file can say anything)."""
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
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

    def _check_ranges(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(f"setting {f.name!r} must be a finite number, got {value!r}")
        positive = ("imu_rate", "window_s", "status_period_s", "jump_s", "peer_timeout_s",
                    "max_source_rate", "source_timeout_s", "evict_after_s", "clock_resync_s",
                    "reinit_gap_s", "idle_timeout_s", "gyro_range_dps", "accel_range_g",
                    "mag_range_gauss", "aid_max_age_s")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"setting {name!r} must be positive, got {getattr(self, name)!r}")
        for name in ("reorder_s", "reinit_settle_s", "mqtt_rate"):
            if getattr(self, name) < 0:
                raise ValueError(f"setting {name!r} must not be negative")
        if self.duration is not None and not self.duration > 0:
            raise ValueError(f"duration must be positive, got {self.duration!r}")
        if self.declination_deg is not None and abs(self.declination_deg) > 180.0:
            raise ValueError(f"declination must be within ±180°, got {self.declination_deg!r}")
        if not 1 <= self.max_peers <= 100_000:
            raise ValueError(f"max_peers must be in 1..100000, got {self.max_peers}")
        for sysid in self.vehicles:
            if not 1 <= sysid <= 255:
                raise ValueError(f"vehicle system id must be in 1..255, got {sysid}")
        if self.imu_id is not None and not 0 <= self.imu_id <= 255:
            raise ValueError(f"imu_id must be in 0..255, got {self.imu_id}")
        if self.truth_source is not None:
            parse_source(self.truth_source)

    @property
    def truth(self) -> tuple[int, int] | None:
        return parse_source(self.truth_source) if self.truth_source else None

    def sensor_calibration(self) -> SensorCalibration | None:
        """The calibration file's contents (ValueError naming the file if it is bad)."""
        return SensorCalibration.load(self.calibration) if self.calibration else None

    @classmethod
    def from_toml(cls, path: str | Path) -> BridgeConfig:
        """Settings from a TOML file; a relative ``calibration`` path is taken relative
        to the settings file (they usually live side by side)."""
        data = tomllib.loads(Path(path).read_text())
        cal = data.get("calibration")
        if isinstance(cal, str) and not Path(cal).is_absolute():
            data["calibration"] = str(Path(path).parent / cal)
        return cls.from_dict(data)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> BridgeConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"unknown setting(s) {unknown}; valid: {sorted(names)}")
        return cls(**data)

    def merged(self, **overrides: Any) -> BridgeConfig:
        """A copy with every override that is not None (or an empty list) applied."""
        changes = {k: v for k, v in overrides.items() if v is not None and v != []}
        return dataclasses.replace(self, **changes)


def parse_source(text: str) -> tuple[int, int]:
    """``"SYSID:COMPID"`` -> (sysid, compid); ValueError saying the form otherwise."""
    sysid, sep, compid = str(text).partition(":")
    if not (sep and sysid.strip().isdigit() and compid.strip().isdigit()
            and 1 <= int(sysid) <= 255 and 0 <= int(compid) <= 255):
        raise ValueError(f"bad source {text!r}; use SYSID:COMPID, e.g. 1:1")
    return int(sysid), int(compid)
