"""The built-in source: the HIL emulator (``hil``) streaming to the bridge in-process.

Used when ``run`` has no ``--connect`` and by ``demo``, so that one command shows the
whole product working without hardware.
"""

from __future__ import annotations

from typing import Any

from .config import BridgeConfig


def emulator_config(cfg: BridgeConfig, duration_s: float | None) -> Any:
    """The ``hil.EmulatorConfig`` matching the bridge settings."""
    from hil import EmulatorConfig
    from hil.config import IMU_MESSAGES

    imu_message = cfg.imu_message if cfg.imu_message in IMU_MESSAGES else "RAW_IMU"
    return EmulatorConfig(profile=cfg.emulator_profile, seed=cfg.emulator_seed,
                          fast=cfg.emulator_fast, duration_s=duration_s,
                          imu_message=imu_message)


def emulator_declination_deg() -> float:
    """Magnetic declination at the emulator's home position (World Magnetic Model):
    its truth is referenced to true north, its magnetometer to magnetic north."""
    from hil import EmulatorConfig

    return float(EmulatorConfig().environment.magnetic_declination_deg)


def builtin_emulator(cfg: BridgeConfig):
    """An emulator starter for :class:`bridge.service.BridgeService`."""
    from hil import Emulator

    # Streaming until the bridge stops, unless a duration bounds the demo.
    ecfg = emulator_config(cfg, cfg.duration)

    async def start(port: int) -> Any:
        return await Emulator(ecfg).run(targets=[("127.0.0.1", port)])

    return start
