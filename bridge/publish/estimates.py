"""Every estimator's attitude as JSON on MQTT, ``<prefix>/<sysid>/<estimator>``.

Published at ``mqtt_rate`` per IMU source (on board time, so a replayed or sped-up
stream is thinned the same way), each estimator on its own topic, with its parameters,
the frame and the declination that defines its north in the payload: a consumer must
never have to guess what a quaternion means.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from estimators.spec import EstimatorSpec

from ..estimate.pipeline import Estimate, Pipeline
from ..vehicle.ingest import SourceKey
from ..wire.mav import mavlink
from .mqtt import MqttPublisher
from .output import euler_zyx

#: What the JSON on MQTT and in the status file says about its quaternions.
FRAME = {"frame": "NED", "body_frame": "FRD", "q_order": "wxyz", "north": "true"}

#: Board time a sample may fall short of the period and still be due (stamps are µs).
PERIOD_SLACK_S = 1e-6


def estimator_topics(labels: list[str], names: list[str]) -> dict[str, str]:
    """Estimator label -> topic name: the estimator's name (``mahony``), with ``-2``,
    ``-3``... for further instances of the same estimator (their parameters are in the
    payload; topic names stay stable when a parameter is tuned)."""
    seen: dict[str, int] = {}
    out = {}
    for label, name in zip(labels, names, strict=True):
        seen[name] = seen.get(name, 0) + 1
        out[label] = name if seen[name] == 1 else f"{name}-{seen[name]}"
    return out


def topics_of(specs: list[EstimatorSpec]) -> dict[str, str]:
    """Estimator label -> topic name for the bridge's estimators."""
    return estimator_topics([s.label for s in specs], [s.name for s in specs])


def source_info(key: SourceKey) -> dict[str, Any]:
    """An IMU source as an object: who sent it, which message, which IMU."""
    entry = mavlink.mavlink_map.get(key.msg)
    return {"sysid": key.sysid, "compid": key.compid,
            "message": entry.msgname if entry is not None else str(key.msg), "imu": key.imu}


class EstimatePublisher:
    """Thins each source's estimates to ``rate_hz`` and publishes every estimator."""

    def __init__(self, mqtt: MqttPublisher, pipeline: Pipeline, rate_hz: float) -> None:
        self.mqtt = mqtt
        self.pipeline = pipeline
        self.period = 1.0 / rate_hz if rate_hz > 0 else 0.0
        self.topics = topics_of(pipeline.specs)
        self._user_params = {s.label: s.user_params() for s in pipeline.specs}

    def offer(self, est: Estimate, last_sent: dict[Any, float]) -> None:
        """Publish ``est``'s source if it is due.

        ``last_sent`` (the vehicle's, cleared when its state is dropped) keeps the board
        time each of its sources was last published at. Within one timeline board time
        only grows (ingest drops duplicates and reordered samples), so a sample before
        it means the timeline restarted (a reboot): published at once, the count starts
        over. Anything else waits the full period, however long (no guess of "too far
        ahead": at 0.25 Hz the period itself is 4 s). The comparison allows
        :data:`PERIOD_SLACK_S`: board times are whole µs, so ``0.204 - 0.104`` falls a
        hair short of 0.1 and would otherwise cost a sample every period.
        """
        last = last_sent.get(est.key)
        if last is not None and last <= est.t and est.t - last < self.period - PERIOD_SLACK_S:
            return
        last_sent[est.key] = est.t
        src = self.pipeline.sources[est.key]
        now = time.time()
        declination = math.degrees(src.declination_rad)
        for label, estimator in zip(src.labels, src.estimators, strict=True):
            st = estimator.status
            roll, pitch, yaw = euler_zyx(st.q)
            name = self.topics[label]
            self.mqtt.publish(self.mqtt.topic(est.key.sysid, name), {
                "sysid": est.key.sysid, "estimator": name, "label": label,
                "params": self._user_params[label],
                "primary": label == self.pipeline.primary_label,
                "source": source_info(est.key),
                "time_unix": round(now, 3), "time_s": est.t, "time_boot_ms": est.time_boot_ms,
                **FRAME, "declination_deg": round(declination, 3),
                "q": _finite_list(st.q),
                "euler_deg": {"roll": _finite(math.degrees(roll)),
                              "pitch": _finite(math.degrees(pitch)),
                              "yaw": _finite(math.degrees(yaw))},
                "gyro_bias_dps": [_finite(math.degrees(b)) for b in st.bias],
                "flags": {"initialising": st.initialising or est.initialising,
                          "acc_rejected": st.acc_rejected, "mag_rejected": st.mag_rejected},
            })


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _finite_list(v: np.ndarray) -> list[float | None]:
    return [_finite(float(x)) for x in v]
