"""What the emulated board is and does: one frozen dataclass for the whole emulator."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from .environment import Environment
from .faults import EVENT_RATES, FaultConfig, FaultSettingError
from .gps import GpsConfig
from .multirotor import DEFAULT_DRAG_PER_S
from .personality import personality
from .sensors.hmc5883l import Hmc5883lConfig
from .sensors.mpu6050 import Mpu6050Config, configure_for_rate, sample_rate
from .sensors.ms5611 import DEFAULT_RATE_HZ as BARO_RATE_HZ
from .sensors.ms5611 import Ms5611

IMU_MESSAGES = ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "HIGHRES_IMU")
#: Default ceiling for HIL_STATE_QUATERNION: every IMU sample up to this rate.
MAX_TRUTH_RATE_HZ = 1000.0
#: An STM32's internal RC oscillator is within 1 % (10 000 ppm); a "crystal" 10 % off
#: is a typo, and beyond it the board's timestamps no longer fit MAVLink's fields.
MAX_CLOCK_DRIFT_PPM = 100_000.0


@dataclass(frozen=True)
class EmulatorConfig:
    """Emulator settings. ``rate_hz`` sets the MPU6050's DLPF_CFG and SMPLRT_DIV, so the
    real rate is the nearest one the chip can produce (``imu_rate_hz``)."""

    profile: str = "static"
    rotor_drag_per_s: float = DEFAULT_DRAG_PER_S  # the `flight` quadrotor's rotor drag [1/s]
    gps: GpsConfig | None = None  # None: no GPS on the board
    rate_hz: float = 1000.0
    duration_s: float | None = 10.0  # None: until cancelled (streaming only)
    seed: int = 0
    sysid: int = 1
    compid: int = 1  # MAV_COMP_ID_AUTOPILOT1
    autopilot: str = "stm32"  # personality on the link: stm32, px4, ardupilot
    imu_message: str | None = None  # None: the personality's (RAW_IMU, HIGHRES_IMU, RAW_IMU)
    fast: bool = False
    #: The board tells its flight state (HEARTBEAT armed flag, EXTENDED_SYS_STATE on
    #: request); False: a bare board that tells neither.
    flight_state: bool = True
    faults: FaultConfig = field(default_factory=FaultConfig)
    truth_rate_hz: float | None = None  # None: IMU rate, divided down to <= 1 kHz
    baro_rate_hz: float = BARO_RATE_HZ
    heartbeat_hz: float = 1.0
    clock_drift_ppm: float = 0.0  # STM32 crystal error (board clock runs fast if > 0)
    clock_jitter_us: float = 0.0  # timestamp latency, uniform in [0, jitter]
    boot_time_s: float = 2.0  # board clock at the first sample (firmware start-up)
    environment: Environment = field(default_factory=Environment)
    mpu6050: Mpu6050Config = field(default_factory=Mpu6050Config)
    hmc5883l: Hmc5883lConfig = field(default_factory=Hmc5883lConfig)
    ms5611: Ms5611 = field(default_factory=Ms5611)

    def __post_init__(self) -> None:
        who = personality(self.autopilot)
        if self.imu_message is None:
            object.__setattr__(self, "imu_message", who.imu_messages[0])
        if self.imu_message not in IMU_MESSAGES:
            raise ValueError(f"imu_message must be one of {IMU_MESSAGES}, got {self.imu_message!r}")
        if self.imu_message not in who.imu_messages:
            raise ValueError(f"the {who.name} autopilot does not send {self.imu_message} "
                             f"(it has {', '.join(who.imu_messages)})")
        if not 1 <= self.sysid <= 255 or not 0 <= self.compid <= 255:
            raise ValueError("sysid must be 1..255 and compid 0..255")
        if self.duration_s is not None and not (math.isfinite(self.duration_s)
                                                and self.duration_s > 0):
            raise ValueError(f"duration must be > 0 seconds (or None), got {self.duration_s}")
        configure_for_rate(self.rate_hz)  # validates the rate
        if not 0.1 <= self.baro_rate_hz <= 100.0:
            raise ValueError("barometer rate must be 0.1..100 Hz (MS5611 at OSR 4096)")
        if not (math.isfinite(self.heartbeat_hz) and self.heartbeat_hz > 0.0):
            raise ValueError("heartbeat rate must be > 0")
        if not 0.0 <= self.clock_jitter_us * 2e-6 < 1.0 / self.imu_rate_hz:
            raise ValueError("clock jitter must be >= 0 and below half an IMU period")
        if not abs(self.clock_drift_ppm) <= MAX_CLOCK_DRIFT_PPM:
            raise ValueError(f"clock drift must be within ±{MAX_CLOCK_DRIFT_PPM:g} ppm, got "
                             f"{self.clock_drift_ppm}")
        for name in EVENT_RATES:  # a probability per IMU sample: at most one event each
            if getattr(self.faults, name) > self.imu_rate_hz:
                raise FaultSettingError(name, f"fault setting {name} must be at most the IMU "
                                              f"rate {self.imu_rate_hz:g} Hz, got "
                                              f"{getattr(self.faults, name):g}")
        # Vibration is drawn at the MPU6050's internal sample rate: above its Nyquist
        # frequency the sinusoid is sampled as garbage (at 1e308 Hz, NaN).
        nyquist = self.mpu.internal_rate_hz / 2.0
        if self.faults.vibration_hz > nyquist:
            raise FaultSettingError("vibration_hz", f"fault setting vibration_hz must be at most "
                                                    f"{nyquist:g} Hz (half the MPU6050's "
                                                    f"internal rate), got "
                                                    f"{self.faults.vibration_hz:g}")
        if self.truth_rate_hz is not None and not 0 < self.truth_rate_hz <= self.imu_rate_hz:
            raise ValueError("truth rate must be > 0 and not above the IMU rate")

    @property
    def mpu(self) -> Mpu6050Config:
        """The MPU6050 configuration with DLPF_CFG/SMPLRT_DIV chosen for rate_hz."""
        cfg, div = configure_for_rate(self.rate_hz)
        return replace(self.mpu6050, dlpf_cfg=cfg, smplrt_div=div)

    @property
    def imu_rate_hz(self) -> float:
        cfg, div = configure_for_rate(self.rate_hz)
        return sample_rate(cfg, div)

    @property
    def truth_divider(self) -> int:
        """HIL_STATE_QUATERNION goes out with every n-th IMU sample."""
        target = self.truth_rate_hz or min(self.imu_rate_hz, MAX_TRUTH_RATE_HZ)
        return max(1, round(self.imu_rate_hz / target))
