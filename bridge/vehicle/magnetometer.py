"""Which magnetometer of a PX4 the bridge uses, live (the policy: :mod:`imu.px4_mag`).

Beside HIGHRES_IMU, whose field has PX4's own bias estimate taken out, the bridge asks a
PX4 for SCALED_IMU (:mod:`bridge.vehicle.negotiate`) and for the parameters that say
whether PX4 calibrates that raw sensor at all (``imu.px4_mag.CALIBRATION_PARAMS``, read
with PARAM_REQUEST_READ as soon as the autopilot is known and again after a reboot: a
calibration is followed by one). Other autopilots: nothing asked, nothing replaced.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

from imu.px4_mag import CALIBRATION_PARAMS, RawMagnetometer

from ..wire.mav import mavlink
from .param_query import ParamQuery

log = logging.getLogger(__name__)


@dataclass
class Px4Magnetometer:
    """One vehicle's magnetometer choice and the parameters it waits for."""

    sysid: int
    chooser: RawMagnetometer = field(default_factory=RawMagnetometer)
    queries: dict[str, ParamQuery] = field(default_factory=dict)
    values: dict[str, float] = field(default_factory=dict)

    def plan(self, autopilot: int | None) -> None:
        """The autopilot is known, or rebooted: start over and ask for the parameters."""
        self.chooser.reset()
        self.values = {}
        self.queries = {}
        if autopilot == mavlink.MAV_AUTOPILOT_PX4:
            for name in CALIBRATION_PARAMS:
                query = self.queries[name] = ParamQuery()
                query.restart(name)

    def param_to_send(self, now: float) -> str | None:
        """The next parameter to ask for (a first try or a retry), if one is due."""
        for query in self.queries.values():
            name = query.to_send(now)
            if name is not None:
                return name
        return None

    def on_param(self, name: str, value: float) -> None:
        """A PARAM_VALUE from the autopilot."""
        query = self.queries.get(name)
        if query is None or not query.answer(name):
            return
        self.values[name] = value
        if len(self.values) == len(CALIBRATION_PARAMS):
            self.chooser.set_parameters(self.values)
            log.info("vehicle %d: %s", self.sysid, self.chooser.describe())

    def status(self) -> dict[str, Any]:
        return {**self.chooser.status(), "parameters": dict(self.values)}
