"""Says when a vehicle's IMU stream is settled, when it stops and when it comes back.

Run once per status period. What it knows (who is silent) also decides each vehicle's
``online`` in the status report and on MQTT.
"""

from __future__ import annotations

import logging

from ..vehicle.imu_sample import DROP_CAUSES
from ..vehicle.ingest import Ingest
from ..vehicle.vehicle import Vehicle

log = logging.getLogger(__name__)


class StreamWatch:
    """Per vehicle: the stream last announced, and since when its data stopped."""

    def __init__(self, ingest: Ingest, source_timeout_s: float) -> None:
        self.ingest = ingest
        self.timeout_s = source_timeout_s
        self.silent_since: dict[int, float] = {}  # sysid -> last_imu when it went quiet
        self._told: dict[int, str] = {}  # sysid -> IMU message last announced
        self._drops_seen: dict[int, dict[str, int]] = {}  # sysid -> primary's drops then

    def online(self, vehicle: Vehicle) -> bool:
        """Its attitude is being estimated now (data seen and not silent)."""
        return vehicle.last_imu > 0.0 and vehicle.sysid not in self.silent_since

    def check(self, vehicles: dict[int, Vehicle], now: float) -> None:
        """Log what changed since the last call (monotonic ``now``)."""
        for sysid, vehicle in vehicles.items():
            if vehicle.last_imu == 0.0:
                continue  # no data yet: nothing to lose
            self._announce_stream(vehicle)
            silent = now - vehicle.last_imu
            since = self.silent_since.get(sysid)
            refused = self._new_drops(vehicle)
            if silent >= self.timeout_s and since is None:
                self.silent_since[sysid] = vehicle.last_imu
                if refused:
                    log.warning("vehicle %d: IMU messages arrive but none was usable for "
                                "%.0f s (refused: %s): the sensor, its driver or the sender "
                                "is at fault, not the link", sysid, silent,
                                ", ".join(f"{c} {n}" for c, n in refused.items()))
                else:
                    log.warning("vehicle %d: no IMU data for %.0f s (link lost, or the "
                                "vehicle stopped sending)", sysid, silent)
            elif silent < self.timeout_s and since is not None:
                del self.silent_since[sysid]
                log.info("vehicle %d: IMU data again after %.1f s", sysid,
                         vehicle.last_imu - since)

    def _new_drops(self, vehicle: Vehicle) -> dict[str, int]:
        """Samples of the vehicle's IMU stream refused since the last check, by cause."""
        state = self.ingest.sources.get(vehicle.primary) if vehicle.primary else None
        if state is None:
            return {}
        now = {c: state.counts[c] for c in DROP_CAUSES}
        before = self._drops_seen.get(vehicle.sysid, now)
        self._drops_seen[vehicle.sysid] = now
        return {c: n - before.get(c, 0) for c, n in now.items() if n > before.get(c, 0)}

    def _announce_stream(self, vehicle: Vehicle) -> None:
        """Once per stream: which message the estimate comes from, at what rate."""
        stream = vehicle.negotiation.status()
        if stream["achieved_hz"] is None or self._told.get(vehicle.sysid) == stream["message"]:
            return
        self._told[vehicle.sysid] = stream["message"]
        board = (f", board {self.ingest.board_of(vehicle.sysid).name}"
                 if stream["message"] == "RAW_IMU" else "")  # SI units otherwise
        log.info("vehicle %d: estimating from %s at %.0f Hz, jitter %.2f ms (asked "
                 "%.4g Hz: %s)%s", vehicle.sysid, stream["message"], stream["achieved_hz"],
                 stream["jitter_ms"], stream["asked_hz"], stream["state"], board)
