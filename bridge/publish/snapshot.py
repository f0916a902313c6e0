"""A small picture of every served vehicle, taken off the sample path for the web view.

Taken by a timer (10 Hz), never by the per-sample path: the newest attitude of each
estimator (from its comparison history), of the autopilot and of the truth, each with
its own board time, and the slower facts from the last status report (stream, drops,
latency, flight state, aiding, declination, the rolling errors). A few hundred bytes per
vehicle, JSON-ready: the view keeps its own history of them.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from estimators import quat as Q

from ..estimate.pipeline import Pipeline
from ..vehicle.references import TRUTH, VEHICLE
from ..vehicle.vehicle import Vehicle

#: A reference older than this (board time) next to the estimate is not shown as current.
STALE_S = 2.0


def _attitude(row: tuple[float, np.ndarray] | None) -> list[float] | None:
    """[t, roll, pitch, yaw] in degrees (as MAVLink's ATTITUDE: yaw -180..180), None when
    absent or not finite."""
    if row is None:
        return None
    t, q = row
    if not (math.isfinite(t) and np.all(np.isfinite(q))):
        return None
    roll, pitch, yaw = np.degrees(Q.to_euler(Q.normalize(q)))
    return [round(t, 3), round(float(roll), 2), round(float(pitch), 2), round(float(yaw), 2)]


def _status_part(st: dict[str, Any]) -> dict[str, Any]:
    """What the view shows of a vehicle's last status report."""
    imu = st.get("imu_stream", {})
    fs = st.get("flight_state", {})
    aiding = st.get("aiding", {})
    compare = {ref: {label: {k: c.get(k) for k in ("total_deg", "inclination_deg",
                                                    "heading_deg")}
                     for label, c in by_label.items()}
               for ref, by_label in st.get("compare", {}).items()}
    own = st.get("vehicle_vs_truth")
    return {
        "report_time": st.get("time_unix"),  # which report (once a second)
        "online": st.get("online"), "initialising": st.get("initialising"),
        "vehicle": st.get("vehicle", {}).get("type"),
        "autopilot": st.get("vehicle", {}).get("autopilot"),
        "imu": {"message": imu.get("message"), "achieved_hz": imu.get("achieved_hz"),
                "asked_hz": imu.get("asked_hz"), "jitter_ms": imu.get("jitter_ms"),
                "state": imu.get("state")},
        "input_rate_hz": st.get("input_rate_hz"), "samples": st.get("samples"),
        "dropped": sum(st.get("drops", {}).values()),
        "lost": st.get("link", {}).get("lost"),
        "latency_ms": st.get("latency_ms", {}),
        "flight_state": {"state": fs.get("state"), "source": fs.get("source"),
                         "armed": fs.get("armed")},
        "aiding": {"enabled": aiding.get("enabled"), "source": aiding.get("source"),
                   "used": aiding.get("used")},
        "declination": st.get("declination", {}),
        "compare": compare,
        "vehicle_vs_truth": (None if own is None else
                             {k: own.get(k) for k in ("total_deg", "inclination_deg")}),
    }


def take(vehicles: dict[int, Vehicle], pipeline: Pipeline,
         last_status: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """The picture of every vehicle: {"vehicles": {sysid: {...}}}."""
    out: dict[str, Any] = {}
    for sysid, vehicle in sorted(vehicles.items()):
        src = pipeline.sources.get(vehicle.primary) if vehicle.primary else None
        series: dict[str, list[float] | None] = {}
        t_now = None
        if src is not None:
            for label in src.labels:
                series[label] = _attitude(src.history[label].last())
            t_now = src.last_sample.t if src.last_sample is not None else None
        if vehicle.refs is not None:
            for name in (VEHICLE, TRUTH):
                att = _attitude(vehicle.refs.series[name].last())
                fresh = att is not None and (t_now is None or abs(t_now - att[0]) < STALE_S)
                series[name] = att if fresh else None
        out[str(sysid)] = {"t": t_now, "primary": pipeline.primary_label,
                           "labels": src.labels if src is not None else [],
                           "series": series,
                           "status": _status_part(last_status.get(sysid, {}))}
    return {"vehicles": out}
