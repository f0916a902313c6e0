"""The real autopilots in tests: a SITL process, a ground-station link to fly it, and the
bridge as a user starts it (the ``attitude-bridge run`` command, default flags), with
what it reports (status file, log, the recorded session).

Scoring a live session: the recorded tlog holds every frame with its arrival (or send)
time, so the bridge's own ATTITUDE_QUATERNION, the autopilot's ATTITUDE_QUATERNION and
the simulator's truth are compared on one clock, as they were on the wire (the truth
interpolated to each estimate's moment).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil

from estimators import metrics
from estimators import quat as Q
from hil.sitl import Link, Sitl

REPO = Path(__file__).resolve().parents[1]
BRIDGE_COMPID = 191
#: Live, the primary estimate's inclination error is at most this multiple of PX4's own
#: (measured 0.87-1.01x on PX4 SIH; ArduPilot's test asks for 1x, measured 0.49x).
INCLINATION_VS_AUTOPILOT = 1.2
#: ... and its total error at most this multiple of PX4's: over 14 PX4 SIH flights
#: 0.45-1.09x (median 0.55x). The total is mostly heading, and the heading error of both
#: drifts by 1-3° within a flight with what SIH's magnetometer says; in one flight of 14
#: the bridge's ended above PX4's. Against ArduPilot (0.51x) the tests hold <= 1.
TOTAL_VS_PX4 = 1.2
TRUTH_TYPES = ("SIMSTATE", "HIL_STATE_QUATERNION")


@dataclass
class BridgeProcess:
    """``attitude-bridge run`` in a subprocess, watched through its status file and
    stopped with SIGINT like a user would."""

    proc: subprocess.Popen
    status_file: Path
    record: Path | None
    log_file: Path

    @classmethod
    def start(cls, folder: Path, connect: str, *extra: str) -> BridgeProcess:
        """Listening on ``connect`` and recording the session (``record``)."""
        record = folder / "session.tlog"
        return cls.run(folder, "--connect", connect, "--record", str(record), *extra,
                       record=record)

    @classmethod
    def run(cls, folder: Path, *args: str, record: Path | None = None,
            env: dict[str, str] | None = None):
        """``run --status-file FOLDER/status.json ARGS``, its log in ``FOLDER/log``."""
        status, log = folder / "status.json", folder / "log"
        cmd = [sys.executable, "-m", "bridge.app.cli", "run", "--status-file", str(status),
               *args]
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL,
                                stderr=log.open("w"),
                                env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})})
        return cls(proc, status, record, log)

    def status(self) -> dict:
        try:
            return json.loads(self.status_file.read_text())
        except (OSError, ValueError):
            return {}

    def vehicle(self, sysid: int) -> dict:
        return self.status().get("vehicles", {}).get(str(sysid), {})

    def wait_for(self, pred, timeout: float, what: str) -> dict:
        """Poll the status file until ``pred(status)``; AssertionError with the log."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            st = self.status()
            if st and pred(st):
                return st
            if self.proc.poll() is not None:
                break
            time.sleep(0.2)
        raise AssertionError(f"bridge: {what} not seen in {timeout:g} s\n{self.log()[-3000:]}")

    def log(self) -> str:
        return self.log_file.read_text(errors="replace") if self.log_file.exists() else ""

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode


def stop_all(*things: Sitl | Link | BridgeProcess | None) -> None:
    for t in things:
        if isinstance(t, BridgeProcess):
            t.stop()
        elif t is not None:
            (t.close if isinstance(t, Link) else t.stop)()


def _series(rows: list[tuple[float, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    if not rows:
        return np.zeros(0), np.zeros((0, 4))
    t = np.array([r[0] for r in rows])
    return t, Q.normalize(np.array([r[1] for r in rows]))


@dataclass
class Session:
    """One recorded live session: attitudes on the wire's clock (s since the epoch)."""

    truth: tuple[np.ndarray, np.ndarray]
    bridge: tuple[np.ndarray, np.ndarray]  # what the bridge sent (its primary)
    autopilot: tuple[np.ndarray, np.ndarray]  # the autopilot's own ATTITUDE_QUATERNION
    landed: list[tuple[float, int]]  # EXTENDED_SYS_STATE landed_state changes
    armed: list[tuple[float, bool]]

    @classmethod
    def read(cls, path: Path, sysid: int) -> Session:
        conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
        truth, bridge, own = [], [], []
        landed: list[tuple[float, int]] = []
        armed: list[tuple[float, bool]] = []
        while (m := conn.recv_match()) is not None:
            kind = m.get_type()
            if m.get_srcSystem() != sysid:
                continue
            t, comp = m._timestamp, m.get_srcComponent()
            if kind == "SIMSTATE":
                truth.append((t, Q.from_euler(m.roll, m.pitch, m.yaw)))
            elif kind == "HIL_STATE_QUATERNION":
                truth.append((t, np.array(m.attitude_quaternion)))
            elif kind == "ATTITUDE_QUATERNION":
                (bridge if comp == BRIDGE_COMPID else own).append(
                    (t, np.array([m.q1, m.q2, m.q3, m.q4])))
            elif kind == "EXTENDED_SYS_STATE" and comp != BRIDGE_COMPID:
                if not landed or landed[-1][1] != m.landed_state:
                    landed.append((t, m.landed_state))
            elif kind == "HEARTBEAT" and comp == 1:
                a = bool(m.base_mode & 128)
                if not armed or armed[-1][1] != a:
                    armed.append((t, a))
        conn.close()
        return cls(_series(truth), _series(bridge), _series(own), landed, armed)

    def error(self, which: str, t0: float, t1: float) -> metrics.ErrorRms:
        """RMS error of ``which`` ("bridge" or "autopilot") over [t0, t1] against the
        truth at the moment each of its messages crossed the wire (interpolated between
        the truth messages around it): the attitude a consumer had, against the true one
        at that moment, its latency included."""
        t, q = getattr(self, which)
        tt, qt = self.truth
        keep = (t >= t0) & (t <= t1) & (t > tt[0]) & (t < tt[-1])
        i = np.searchsorted(tt, t[keep])
        frac = (t[keep] - tt[i - 1]) / (tt[i] - tt[i - 1])
        return metrics.rms_errors(q[keep], Q.slerp(qt[i - 1], qt[i], frac))

    def flight_span(self) -> tuple[float, float]:
        """From the first arming to the last disarming (take-off, flight, landing)."""
        on = [t for t, a in self.armed if a]
        off = [t for t, a in self.armed if not a and on and t > on[0]]
        assert on and off, f"no armed span in the session: {self.armed}"
        return on[0], off[-1]


def landed_and_disarmed(status: dict, sysid: int | str) -> bool:
    """The bridge has seen the vehicle on the ground and disarmed."""
    fs = status.get("vehicles", {}).get(str(sysid), {}).get("flight_state", {})
    return fs.get("state") == "on ground" and fs.get("armed") is False


def check_live_session_matches_replay(vehicle: dict, replayed: dict) -> None:
    """The bridge's whole-session inclination against the truth (``session_vs_truth`` of
    the status written at exit, ``vehicle``: that status's entry for the vehicle) equals
    the replay of its record: the truth (no time stamp) is placed by the IMU sample read
    before it, live as in the replay (before, by a learned clock offset, live read 2x the
    replay's error in a PX4 flight).

    The samples: live counts truth samples the estimate reaches, the replay the recorded
    IMU samples the truth reaches; one per IMU sample on a clean link. A failure shows
    the bridge's counters beside them (samples its clock dropped, messages lost on the
    link, restarts): a CI run once failed the count and left no record to tell why;
    a later one under load did (ArduPilot SITL stalled between an IMU sample and its
    truth, which the live clock placed 0.86 s ahead: ``bridge.vehicle.clock``).

    Inclination only: the heading follows the declination, which the live bridge learns
    from the autopilot during the session (the World Magnetic Model at the first
    position, then the autopilot's parameter, re-read on the ground and as it arms) and
    the replay takes, last reported, for all of it; its estimate lives in magnetic
    north, so that turns only the heading it reports (a constant 0.10° on an ArduPilot
    flight when the live bridge still flew with the WMM's 12.70° against 12.80°). PX4's
    replay is given the declination of the flight
    (``replayed_beside_vqf(declination_deg=...)``).
    Both estimate from the same first sample: the model the first heartbeat tells does
    not restart the live estimate but has the rebuilt estimators catch up on the samples
    so far (``bridge.estimate.pipeline.CATCH_UP_S``; a restart a second in, from another
    magnetometer reading, put the two headings 3° apart). The autopilot's own was 0.4-2.2 % apart,
    once 5.2 %, while the live scores paired its 50 Hz attitude with the nearest sample
    instead of interpolating it as the replay does (fixed in
    ``bridge.estimate.compare.pairs_at_shift``; the same flight's record re-scored: 0.516
    nearest, 0.489 interpolated, against the replay's 0.489)."""
    live = vehicle["session_vs_truth"]
    why = {"live": live["eskf"], "replayed": replayed["eskf"], "drops": vehicle["drops"],
           "link": vehicle["link"], "flags": vehicle["flags"], "restarts": vehicle["restarts"]}
    assert live["eskf"]["samples"] == pytest.approx(replayed["eskf"].samples, abs=5), why
    assert live["eskf"]["inclination_deg"] == pytest.approx(
        replayed["eskf"].inclination_deg, rel=0.015), (live, replayed)
    assert live["(vehicle own)"]["inclination_deg"] == pytest.approx(
        replayed["autopilot"].inclination_deg, rel=0.04), (live, replayed)


def check_flight_state_and_references(st: dict, truth_stream: str) -> None:
    """What every real-autopilot flight must show in the bridge's status: the take-off
    taken from the landed state, back on the ground at the end, both references asked
    for and compared live."""
    fs = st["flight_state"]
    took_off = [s for s in fs["recent_switches"] if s["state"] == "airborne"]
    assert took_off and took_off[-1]["source"] == "landed state", fs
    assert [s["state"] for s in fs["recent_switches"]][-2:] == ["airborne", "on ground"], fs
    assert st["imu_stream"]["reference_streams"] == {
        "ATTITUDE_QUATERNION": "MAV_RESULT_ACCEPTED", truth_stream: "MAV_RESULT_ACCEPTED"}
    assert {"truth", "vehicle"} <= set(st["compare"]), st["compare"]
    assert st["vehicle_vs_truth"] is not None


def armed_span_scores(record: Path, sysid: int, label: str
                      ) -> tuple[metrics.ErrorRms, metrics.ErrorRms]:
    """(bridge, autopilot) against the truth from arming to disarming, printed."""
    session = Session.read(record, sysid)
    t0, t1 = session.flight_span()
    ours, theirs = session.error("bridge", t0, t1), session.error("autopilot", t0, t1)
    print(f"{label} flight {t1 - t0:.0f} s: bridge {ours}, {label} {theirs}")
    assert ours.samples > 20 * (t1 - t0) and theirs.samples > 20 * (t1 - t0)
    return ours, theirs


def replayed_beside_vqf(record: Path, label: str, declination_deg: float | None = None
                        ) -> dict:
    """The recorded session replayed (``attitude-bridge replay --smooth --compare
    vqf,vqf-offline``: eskf with the defaults online and smoothed, the autopilot's own
    attitude, VQF online and offline, on the same samples against the same truth, every
    phase), scores by label, printed. ``declination_deg``: as ``--declination-deg``."""
    from replay.evaluate import evaluate
    from replay.readers import load

    ev = evaluate(load(record, reference="truth"), ["eskf"], smooth=True,
                  compare=("vqf", "vqf-offline"), declination_deg=declination_deg)
    d = ev.prepared.declination
    print(f"{label} session replayed (declination {d.deg:.3f}°, {d.source}): " + ", ".join(
        f"{name} {s.total_deg:.2f} / {s.inclination_deg:.2f}" for name, s in ev.scores.items()))
    return ev.scores


def read_param(link: Link, name: str, tries: int = 5) -> float | None:
    """The autopilot's current value of a parameter, asked on ``link`` (PARAM_REQUEST_READ,
    answered by PARAM_VALUE)."""
    values: dict[str, float] = {}

    def on_param(m) -> None:
        pid = m.param_id if isinstance(m.param_id, str) else m.param_id.decode()
        values[pid.rstrip("\x00")] = float(m.param_value)

    link.on_message["PARAM_VALUE"] = on_param
    for _ in range(tries):
        link.send(link.conn.mav.param_request_read_encode(link.sysid, link.compid,
                                                           name.encode(), -1))
        if link.wait_for(lambda: name in values, 1.0):
            return values[name]
    return None
