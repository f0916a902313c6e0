"""MAVLink output: the primary estimate as ATTITUDE_QUATERNION + ATTITUDE, and HEARTBEAT.

Messages are sent as (vehicle sysid, bridge component id) — a companion computer
speaks for the vehicle it sits on — to the connection and every ``--out`` link.
``out_rate`` decimates per source on *board* time, so the rate is exact whatever the
packet timing; ``out_rate <= 0`` sends every sample.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from estimators import quat as Q

from ..estimate.pipeline import Estimate
from ..vehicle.ingest import SourceKey
from ..vehicle.ring import TimeRing
from ..wire.links import Link
from ..wire.mav import mavlink

_NO_OFFSET = [1.0, 0.0, 0.0, 0.0]  # repr_offset_q: no display rotation


def euler_zyx(q: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of one quaternion as floats, by :func:`estimators.quat.to_euler`.

    Every Euler angle the bridge publishes (ATTITUDE, MQTT, the table) comes from that
    one conversion: a second formula disagreed with it near ±90° pitch, where only
    yaw ∓ roll is defined and the two split it differently (or not at all).
    """
    roll, pitch, yaw = Q.to_euler(q).tolist()
    return roll, pitch, yaw


#: An attitude sent this long after its IMU sample arrived is late [s]: a consumer takes
#: ATTITUDE_QUATERNION as the attitude now, and a tenth of a second is several control
#: periods of a flight controller and a visible lag on a display.
LATE_S = 0.1


@dataclass
class LateWindow:
    """Estimates sent over a span of time, how many of them late, the worst latency."""

    sent: int = 0
    late: int = 0
    worst_s: float = 0.0


class AttitudeOutput:
    """Decimates and sends the primary estimate; measures in->out latency."""

    def __init__(self, links: Sequence[Link], component_id: int, out_rate: float,
                 latency_samples: int = 4096) -> None:
        self.links = list(links)
        self.component_id = component_id
        self.period = 1.0 / out_rate if out_rate > 0 else 0.0
        self._next_t: dict[SourceKey, float] = {}
        self.sent: dict[int, int] = {}  # per sysid: estimates sent
        self.held: dict[int, int] = {}  # per sysid: estimates not sent while initialising
        # seconds, IMU datagram arrived (its kernel time over UDP) -> output written
        self.latency = TimeRing(latency_samples, 1)
        self.sent_late: dict[int, int] = {}  # per sysid: sent LATE_S or more after arrival
        self._window = LateWindow()  # since the last take_lateness()

    def offer(self, est: Estimate) -> bool:
        """Send ``est`` if it is due under the output rate; True if sent."""
        if self.period:
            due = self._next_t.get(est.key)
            if due is not None and est.t < due - 1e-6:
                if est.t < due - 2.0 * self.period:  # time went back (resync): restart
                    self._next_t[est.key] = est.t
                return False
            # Step the schedule, not the sample time, so the average rate is exact.
            nxt = est.t + self.period if due is None or est.t > due + self.period else \
                due + self.period
            self._next_t[est.key] = nxt
        self.send_estimate(est)
        return True

    def hold(self, est: Estimate) -> None:
        """Count an estimate that is not sent: it is re-converging after a restart (an
        ATTITUDE_QUATERNION has no field to say so, and a stale or unsettled attitude
        must not reach a consumer as if it were current)."""
        sysid = est.key.sysid
        self.held[sysid] = self.held.get(sysid, 0) + 1
        self._next_t.pop(est.key, None)

    def forget(self, key: SourceKey) -> None:
        """Drop the decimation schedule of a source that is gone."""
        self._next_t.pop(key, None)

    def send_estimate(self, est: Estimate) -> None:
        q, r = est.q, est.rates
        rates = (float(r[0]), float(r[1]), float(r[2]))
        roll, pitch, yaw = euler_zyx(q)
        aq = mavlink.MAVLink_attitude_quaternion_message(
            est.time_boot_ms, float(q[0]), float(q[1]), float(q[2]), float(q[3]),
            *rates, _NO_OFFSET)
        att = mavlink.MAVLink_attitude_message(est.time_boot_ms, roll, pitch, yaw, *rates)
        sysid = est.key.sysid
        pair = (aq, att)
        for link in self.links:
            link.send_many(pair, sysid, self.component_id)
        self.sent[sysid] = self.sent.get(sysid, 0) + 1
        latency = time.perf_counter() - est.arrival
        self.latency.push(0.0, np.array([latency]))
        self._window.sent += 1
        if latency >= LATE_S:
            self.sent_late[sysid] = self.sent_late.get(sysid, 0) + 1
            self._window.late += 1
            self._window.worst_s = max(self._window.worst_s, latency)

    def take_lateness(self) -> LateWindow:
        """The estimates sent, and sent late, since the last call."""
        window, self._window = self._window, LateWindow()
        return window

    def send_heartbeat(self, sysids: Sequence[int]) -> None:
        """One HEARTBEAT per vehicle we speak for, as an onboard controller."""
        hb = mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
            mavlink.MAV_STATE_ACTIVE, 3)
        for sysid in sysids:
            for link in self.links:
                link.send(hb, sysid, self.component_id)

    def latency_percentiles_ms(self) -> dict[str, float]:
        _, v = self.latency.snapshot()
        if not len(v):
            return {}
        p50, p90, p99 = np.percentile(v[:, 0], [50, 90, 99]) * 1e3
        return {"p50": round(float(p50), 3), "p90": round(float(p90), 3),
                "p99": round(float(p99), 3), "max": round(float(v[:, 0].max() * 1e3), 3)}
