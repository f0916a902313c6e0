"""The built-in source: the HIL emulator (``hil``) streaming to the bridge in-process.

Used when ``run`` has no ``--connect`` and by ``demo``, so that one command shows the
whole product working without hardware.
"""

from __future__ import annotations

from typing import Any

from .config import BridgeConfig


def emulator_config(cfg: BridgeConfig, duration_s: float | None) -> Any:
    """The ``hil.EmulatorConfig`` matching the bridge settings.

    ``emulator_autopilot`` (stm32, px4, ardupilot) and ``emulator_gps`` are read when the
    bridge configuration has them: the seeds' board streams the bridge's IMU message
    from the start, the others start with their own streams and are asked by the bridge.
    """
    from hil import EmulatorConfig, GpsConfig
    from hil.personality import personality

    who = personality(getattr(cfg, "emulator_autopilot", "stm32"))
    imu_message = cfg.imu_message if cfg.imu_message in who.imu_messages else None
    if who.name != "stm32":
        imu_message = None  # a real autopilot starts with its own defaults
    gps = GpsConfig() if getattr(cfg, "emulator_gps", False) else None
    return EmulatorConfig(profile=cfg.emulator_profile, seed=cfg.emulator_seed,
                          fast=cfg.emulator_fast, duration_s=duration_s,
                          autopilot=who.name, imu_message=imu_message, gps=gps)


def check_emulator(cfg: BridgeConfig) -> None:
    """ValueError for emulator settings it cannot run (an unknown profile, a missing
    profile file), before the service starts rather than in its background task."""
    from hil.motion import make_profile

    ecfg = emulator_config(cfg, cfg.duration)
    make_profile(ecfg.profile, ecfg.duration_s or 60.0, ecfg.rotor_drag_per_s)


def emulator_declination_deg() -> float:
    """Magnetic declination at the emulator's home position (World Magnetic Model):
    its truth is referenced to true north, its magnetometer to magnetic north."""
    from hil import EmulatorConfig

    return float(EmulatorConfig().environment.magnetic_declination_deg)


def builtin_emulator(cfg: BridgeConfig):
    """An emulator starter for :class:`bridge.app.service.BridgeService`."""
    from hil import Emulator

    # Streaming until the bridge stops, unless a duration bounds the demo.
    ecfg = emulator_config(cfg, cfg.duration)

    async def start(port: int) -> Any:
        return await Emulator(ecfg).run(targets=[("127.0.0.1", port)])

    return start
