"""How late a vehicle's IMU samples are, live: its autopilot's gyro low-pass filter.

The estimators carry their output forward by this delay (``imu_delay``, see
``imu.filter_delay`` for the filter and the numbers). For ArduPilot the bridge reads
``INS_GYRO_FILTER`` with PARAM_REQUEST_READ as soon as it knows the autopilot, and uses
ArduPilot's default for the vehicle type until (or unless) the answer comes; it is read
again when the vehicle disarms (a user may change it between flights). Other autopilots
send unfiltered samples: no delay, nothing asked.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

from imu import filter_delay
from imu.filter_delay import FilterDelay

from .param_query import ParamQuery

log = logging.getLogger(__name__)


@dataclass
class ImuDelay:
    """The IMU delay of one vehicle and where it came from."""

    sysid: int
    delay: FilterDelay = filter_delay.NONE
    autopilot: int | None = None
    mav_type: int | None = None
    query: ParamQuery = field(default_factory=ParamQuery)

    @property
    def seconds(self) -> float:
        return self.delay.seconds

    def plan(self, autopilot: int, mav_type: int | None) -> bool:
        """The autopilot is known (or the vehicle disarmed): ask for its parameter, and
        meanwhile use its default unless the parameter already answered. True if the
        delay changed."""
        self.autopilot, self.mav_type = autopilot, mav_type
        if autopilot != filter_delay.ARDUPILOT:
            self.query.restart(None)
            return self._set(filter_delay.NONE)
        self.query.restart(filter_delay.GYRO_FILTER_PARAM)
        if self.delay.from_parameter:
            return False  # the vehicle's own value, until it answers again
        return self._set(filter_delay.imu_filter_delay(autopilot, {}, mav_type))

    def param_to_send(self, now: float) -> str | None:
        return self.query.to_send(now)

    def on_param(self, name: str, value: float) -> bool:
        """A PARAM_VALUE from the autopilot; True if the delay changed."""
        if not self.query.answer(name):
            return False
        found = filter_delay.imu_filter_delay(self.autopilot, {name: value}, self.mav_type)
        if not found.from_parameter:
            log.warning("vehicle %d: %s", self.sysid, found.source)
        return self._set(found)

    def _set(self, delay: FilterDelay) -> bool:
        changed = delay != self.delay
        if changed:
            log.info("vehicle %d: IMU samples %.1f ms old (%s): estimates carried forward",
                     self.sysid, delay.ms, delay.source)
        self.delay = delay
        return changed

    def status(self) -> dict[str, Any]:
        return {"ms": round(self.delay.ms, 2), "source": self.delay.source}
