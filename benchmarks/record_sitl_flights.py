"""Record real-autopilot SITL flights with touchdowns and time on the ground, as tlogs.

Flies PX4 (SITL, SIH quadrotor) and ArduPilot Copter (SITL) from /work/shared/autopilots,
one at a time on 127.0.0.1, and records each one's onboard MAVLink link: the IMU, the
simulator's true attitude, the autopilot's own estimate, position/velocity, landed state,
arming and command acknowledgements. Every flight has ground time before the first take-off,
a touchdown with the autopilot disarming, a second take-off and a final landing, so each
flight phase (ground, take-off, flight, touchdown, landing) can be scored.

    python benchmarks/record_sitl_flights.py [--out tests/data/sitl] [--which px4a,px4b,ap]
    python benchmarks/record_sitl_flights.py --check-only      # just re-check the files

Flights (see tests/data/sitl/README.md for the message lists and rates):
  px4a  PX4 "touchdown": ~5 m/s legs with reversals and yaw turns, land, ground, again
  px4b  PX4 "dashes": a ~6 m/s circle, 7-8 m/s diagonal dashes with reversals, land,
        ground, a circle the other way and dashes, land
  ap    ArduPilot Copter: GUIDED 5 m/s legs, LAND, ground, GUIDED again, LAND
  ap2   ArduPilot Copter: a 5 m/s circle, 6 m/s dashes with the nose turning, LAND,
        ground, a circle the other way, LAND
After recording, each file is read back with pymavlink and summarised: duration, message
counts and rates, landed-state and arm/disarm times, max tilt (truth), horizontal acceleration.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.sitl import LANDED, Leg, Link, Sitl, mav, mavutil
from hil.sitl_pilot import (
    FlightError,
    ap_guided,
    ap_land,
    ap_ready,
    ap_takeoff,
    log,
    px4_land,
    px4_offboard,
    px4_ready,
    px4_takeoff,
    set_rates,
)
from imu.px4_mag import CALIBRATION_PARAMS

REPO = Path(__file__).resolve().parents[1]

# Message -> requested rate (Hz). The keys are also the only messages written to the tlog,
# plus COMMAND_ACK, STATUSTEXT (as they come), the COMMAND_LONGs this script sends and
# the PARAM_VALUEs it asks for.
PX4_RATES = {
    "HIGHRES_IMU": 400.0, "HIL_STATE_QUATERNION": 200.0, "ATTITUDE_QUATERNION": 200.0,
    "ATTITUDE": 50.0, "LOCAL_POSITION_NED": 50.0, "GLOBAL_POSITION_INT": 50.0,
    "GPS_RAW_INT": 10.0, "EXTENDED_SYS_STATE": 10.0, "SYSTEM_TIME": 1.0, "HEARTBEAT": 1.0,
    "SCALED_IMU": 50.0,  # the raw magnetometer, without PX4's bias estimate (imu.px4_mag)
}
AP_RATES = {
    "RAW_IMU": 333.0, "SIMSTATE": 100.0, "ATTITUDE": 100.0, "LOCAL_POSITION_NED": 50.0,
    "GLOBAL_POSITION_INT": 10.0, "GPS_RAW_INT": 10.0, "EXTENDED_SYS_STATE": 10.0,
    "SYSTEM_TIME": 1.0, "HEARTBEAT": 1.0,
}
ALWAYS = {"COMMAND_ACK", "STATUSTEXT", "COMMAND_LONG", "PARAM_VALUE"}


@dataclass(frozen=True)
class Sortie:
    legs: list[Leg]
    ground_after: float  # seconds on the ground after landing (from landed_state on_ground)


@dataclass(frozen=True)
class Flight:
    name: str
    autopilot: str  # "px4" or "ardupilot"
    file: str
    takeoff_alt: float
    sorties: list[Sortie]
    ground_before: float = 10.0


FLIGHTS = {
    # Leg speeds are set-points: PX4's velocity loop (weak integrator against SIH's drag)
    # flies about 75 % of them, so 6.5 m/s set-points give legs of ~5 m/s.
    "px4a": Flight("px4a", "px4", "px4_sih_touchdown.tlog", 3.0, [
        Sortie([Leg(5, 6.5, 0), Leg(4, 6.5, 180), Leg(4, 6, 90, yaw=45),
                Leg(4, 6, 270, yaw=-45), Leg(3, 5.5, 45), Leg(2)], ground_after=10),
        Sortie([Leg(4, 5.5, 315, yaw=30), Leg(4, 5.5, 135, yaw=-30), Leg(4, 6.5, 0, yaw=90),
                Leg(3)], ground_after=5),
    ]),
    "px4b": Flight("px4b", "px4", "px4_sih_dashes.tlog", 3.0, [
        Sortie([Leg(3, 5, 0), Leg(8, 8, 0, turn=45, yaw=45), Leg(3, 9.5, 45),
                Leg(3, 9.5, 225), Leg(3, 10.5, 315), Leg(2)], ground_after=8),
        Sortie([Leg(6, 9, 180, turn=-60, yaw=-60), Leg(3, 10.5, 135), Leg(3, 10.5, 315),
                Leg(3)], ground_after=5),
    ]),
    "ap": Flight("ap", "ardupilot", "arducopter_touchdown.tlog", 4.0, [
        Sortie([Leg(5, 5, 0), Leg(4, 5, 180), Leg(4, 4, 90, yaw=45), Leg(4, 4, 270, yaw=-45),
                Leg(3)], ground_after=10),
        Sortie([Leg(4, 4, 45), Leg(4, 4, 225, yaw=60), Leg(3)], ground_after=5),
    ]),
    "ap2": Flight("ap2", "ardupilot", "arducopter_circles.tlog", 5.0, [
        Sortie([Leg(8, 5, 0, turn=45), Leg(4, 6, 90, yaw=-45), Leg(4, 6, 270), Leg(3)],
               ground_after=8),
        Sortie([Leg(8, 5, 180, turn=-45, yaw=30), Leg(3)], ground_after=5),
    ]),
}


# --------------------------------------------------------------------------- one flight
def record(flight: Flight, out: Path, px4_instance: int, ap_ports: tuple[int, int],
           px4_imu_hz: float = PX4_RATES["HIGHRES_IMU"]) -> Path:
    path = out / flight.file
    if flight.autopilot == "px4":
        rates = {**PX4_RATES, "HIGHRES_IMU": px4_imu_hz}
        sitl = Sitl("px4", {"FRESH": "1", "PX4_INSTANCE": str(px4_instance),
                            "PX4_PARAM_MIS_TAKEOFF_ALT": str(flight.takeoff_alt)})
        port = 14540 + px4_instance
        ready, takeoff, fly, land = px4_ready, px4_takeoff, px4_offboard, px4_land
    else:
        rates = AP_RATES
        sitl = Sitl("ardupilot", {"FRESH": "1", "AP_GCS_PORT": str(ap_ports[0]),
                                  "AP_API_PORT": str(ap_ports[1]),
                                  "AP_PARAM_WPNAV_ACCEL": "500"})
        port = ap_ports[1]
        ready, takeoff, fly, land = ap_ready, ap_takeoff, ap_guided, ap_land
    link = Link(port, keep=set(rates) | ALWAYS)  # listen before the autopilot starts
    try:
        log(f"[{flight.name}] {sitl.start()}")
        link.wait_heartbeat()
        set_rates(link, rates)
        ready(link)
        link.record(path)
        if flight.autopilot == "px4":  # whether PX4 calibrates its raw magnetometer
            for name in CALIBRATION_PARAMS:
                link.send(link.conn.mav.param_request_read_encode(
                    link.sysid, link.compid, name.encode(), -1))
        log(f"[{flight.name}] recording {path}; {flight.ground_before:g} s on the ground")
        time.sleep(flight.ground_before)
        for i, sortie in enumerate(flight.sorties, 1):
            log(f"[{flight.name}] take-off {i}")
            takeoff(link, flight.takeoff_alt)
            log(f"[{flight.name}] legs {i}: {sum(leg.seconds for leg in sortie.legs):g} s")
            fly(link, sortie.legs, flight.takeoff_alt)
            log(f"[{flight.name}] land {i}")
            land(link)
            time.sleep(sortie.ground_after)
        log(f"[{flight.name}] done")
    except Exception:
        for t, text in link.statustext[-8:]:
            log(f"  statustext {t:.1f}: {text}")
        raise
    finally:
        link.close()
        sitl.stop()
    return path


# --------------------------------------------------------------------------- read-back check
def read_tlog(path: Path) -> dict[str, list]:
    conn = mavutil.mavlink_connection(str(path))
    rows: dict[str, list] = {}
    while (m := conn.recv_match()) is not None:
        if m.get_type() != "BAD_DATA":
            rows.setdefault(m.get_type(), []).append(m)
    conn.close()
    return rows


def tilt_deg(rows: dict[str, list]) -> tuple[str, np.ndarray]:
    if rows.get("HIL_STATE_QUATERNION"):
        q = np.array([m.attitude_quaternion for m in rows["HIL_STATE_QUATERNION"]])
        return "HIL_STATE_QUATERNION", np.degrees(
            np.arccos(np.clip(1 - 2 * (q[:, 1] ** 2 + q[:, 2] ** 2), -1, 1)))
    if rows.get("SIMSTATE"):
        rp = np.array([(m.roll, m.pitch) for m in rows["SIMSTATE"]])
        return "SIMSTATE", np.degrees(np.arccos(np.cos(rp[:, 0]) * np.cos(rp[:, 1])))
    return "-", np.zeros(1)


def horizontal_accel(rows: dict[str, list], window_s: float = 0.1) -> np.ndarray:
    """|d(vN, vE)/dt| from LOCAL_POSITION_NED by differences over ``window_s``."""
    lp = rows.get("LOCAL_POSITION_NED", [])
    if len(lp) < 3:
        return np.zeros(1)
    t = np.array([m.time_boot_ms for m in lp]) * 1e-3
    v = np.array([(m.vx, m.vy) for m in lp])
    k = max(1, round(window_s / max(np.median(np.diff(t)), 1e-3) / 2))
    dt = t[2 * k:] - t[:-2 * k]
    ok = dt > 0
    return np.linalg.norm((v[2 * k:] - v[:-2 * k])[ok] / dt[ok, None], axis=1)


def summarise(path: Path) -> dict:
    rows = read_tlog(path)
    vehicle = Counter(m.get_srcSystem() for m in rows.get("HEARTBEAT", [])
                      if m.autopilot != mav.MAV_AUTOPILOT_INVALID).most_common(1)[0][0]
    stamps = [m._timestamp for ms in rows.values() for m in ms]
    t0, t1 = min(stamps), max(stamps)
    events = []
    armed = landed = None
    for m in rows.get("HEARTBEAT", []):
        if m.get_srcSystem() == vehicle and m.autopilot != mav.MAV_AUTOPILOT_INVALID:
            a = bool(m.base_mode & 128)
            if a != armed:
                events.append((m._timestamp - t0, "armed" if a else "disarmed"))
            armed = a
    for m in rows.get("EXTENDED_SYS_STATE", []):
        if m.landed_state != landed:
            events.append((m._timestamp - t0, LANDED.get(m.landed_state, "?")))
        landed = m.landed_state
    events.sort()
    imu = "HIGHRES_IMU" if "HIGHRES_IMU" in rows else "RAW_IMU"
    truth = "HIL_STATE_QUATERNION" if "HIL_STATE_QUATERNION" in rows else "SIMSTATE"
    t_imu = np.array([m.time_usec for m in rows[imu]]) * 1e-6
    a_imu = np.array([m._timestamp for m in rows[imu]]) - t0
    a_truth = np.array([m._timestamp for m in rows.get(truth, [])]) - t0
    overlap = (min(a_imu[-1], a_truth[-1]) - max(a_imu[0], a_truth[0])) if a_truth.size else 0.0
    tilt_src, tilt = tilt_deg(rows)
    acc = horizontal_accel(rows)
    return {
        "path": path, "size": path.stat().st_size, "duration": t1 - t0,
        "counts": {k: len(v) for k, v in sorted(rows.items(), key=lambda kv: -len(kv[1]))},
        "events": events, "imu": imu, "truth": truth,
        "imu_board_hz": (len(t_imu) - 1) / (t_imu[-1] - t_imu[0]),
        "imu_span": (a_imu[0], a_imu[-1]),
        "truth_span": (a_truth[0], a_truth[-1]) if a_truth.size else (math.nan, math.nan),
        "overlap": overlap, "tilt_src": tilt_src, "tilt_max": float(tilt.max()),
        "tilt_p95": float(np.percentile(tilt, 95)), "acc_max": float(acc.max()),
        "acc_p95": float(np.percentile(acc, 95)),
    }


def print_summary(s: dict) -> None:
    d = s["duration"]
    log(f"\n{s['path']}  {s['size'] / 1e6:.2f} MB  {d:.1f} s")
    log("  messages: " + ", ".join(f"{k} {n} ({n / d:.1f}/s)" for k, n in s["counts"].items()))
    log(f"  {s['imu']} board-clock rate {s['imu_board_hz']:.1f} Hz; arrival "
        f"{s['imu_span'][0]:.2f}-{s['imu_span'][1]:.2f} s; {s['truth']} "
        f"{s['truth_span'][0]:.2f}-{s['truth_span'][1]:.2f} s; overlap {s['overlap']:.1f} s")
    log("  events (s since file start): " + ", ".join(f"{t:.1f} {w}" for t, w in s["events"]))
    log(f"  max tilt ({s['tilt_src']}) {s['tilt_max']:.1f} deg (p95 {s['tilt_p95']:.1f}); "
        f"horizontal accel (LOCAL_POSITION_NED, 0.1 s differences) max {s['acc_max']:.1f} "
        f"m/s^2 (p95 {s['acc_p95']:.1f})")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=REPO / "tests" / "data" / "sitl")
    p.add_argument("--which", default="px4a,px4b,ap,ap2",
                   help=f"comma-separated flights: {','.join(FLIGHTS)}")
    p.add_argument("--px4-instance", type=int, default=6,
                   help="PX4 instance (system id N+1, onboard udp 14540+N); default 6")
    p.add_argument("--ap-ports", default="14660,14640",
                   help="ArduPilot GCS,onboard udp ports (default 14660,14640)")
    p.add_argument("--px4-imu-hz", type=float, default=PX4_RATES["HIGHRES_IMU"],
                   help="HIGHRES_IMU rate asked of PX4 (default 400: it gives ~380; 250 gives "
                        "200, every 2nd sample); the file shrinks by ~0.08 MB/s per 100 Hz")
    p.add_argument("--check-only", action="store_true",
                   help="do not fly: read back and summarise the existing files")
    args = p.parse_args()
    names = [n.strip() for n in args.which.split(",") if n.strip()]
    unknown = [n for n in names if n not in FLIGHTS]
    if unknown:
        p.error(f"unknown flight(s) {unknown}; choose from {list(FLIGHTS)}")
    gcs, api = (int(x) for x in args.ap_ports.split(","))
    failed = []
    for name in names:
        flight = FLIGHTS[name]
        try:
            path = (args.out / flight.file if args.check_only
                    else record(flight, args.out, args.px4_instance, (gcs, api),
                           args.px4_imu_hz))
            print_summary(summarise(path))
        except (FlightError, RuntimeError, OSError) as e:
            log(f"[{name}] FAILED: {e}")
            failed.append(name)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
