"""A software GY-86 (MPU6050 + HMC5883L + MS5611) on an STM32, speaking MAVLink 2.

    from hil import EmulatorConfig, FaultConfig, Emulator, simulate
    rec = simulate(EmulatorConfig(profile="flight", rate_hz=1000.0, duration_s=10.0,
                                  gps=GpsConfig()))
    stats = await Emulator(cfg).run(targets=[("127.0.0.1", 14550)])

``simulate`` and the UDP stream produce the same samples for the same seed. On the
link the board behaves like a flight controller of its ``autopilot`` personality
(``stm32``, ``px4``, ``ardupilot``): it answers SET_MESSAGE_INTERVAL, REQUEST_MESSAGE
and parameter requests, sends its own onboard attitude and tells its flight state
(HEARTBEAT armed flag, EXTENDED_SYS_STATE on request; ``Recording.armed`` and
``landed_state`` hold the truth of it).
"""

from __future__ import annotations

from .config import EmulatorConfig
from .environment import Environment
from .faults import FaultConfig, FaultCounts
from .gps import GpsConfig
from .link import Emulator
from .motion import make_profile
from .recording import Recording
from .source import simulate
from .stats import EmulatorStats

__all__ = [
    "Emulator", "EmulatorConfig", "EmulatorStats", "Environment", "FaultConfig",
    "FaultCounts", "GpsConfig", "Recording", "make_profile", "simulate",
]
