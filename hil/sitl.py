"""Real SITL autopilots for tests and recordings: start PX4 (SIH quadrotor) or ArduPilot
Copter from the packed runtimes in ``../shared/autopilots`` (read its README), each in a
private folder on its own ports, and talk to one as a ground station would.

Ports: an ArduPilot instance sends its two links to ports chosen here (free ones); a PX4
instance's ports follow from its instance number (onboard link: it sends to 14540+N,
listens on 14580+N; GCS link: listens on 18570+N), and PX4 allows one process per
instance number on a machine, so instance numbers are reserved with a lock file that
other test processes respect. PX4 answers a ground station on whichever local address
spoke to its GCS port first, so a test flies it from an ephemeral port (``udpout``).

A tlog record is the 8-byte big-endian arrival time in µs followed by the raw MAVLink frame,
written here by hand (pymavlink's ``mavudp`` does not log through ``setup_logfile``). Only
the message types a flight asks for are written, plus the COMMAND_LONGs this side sends.
"""

from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"  # before pymavlink is imported: PX4 and ArduPilot speak v2

import contextlib
import fcntl
import math
import select
import shutil
import signal
import socket
import struct
import subprocess
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from pymavlink import mavutil

mav = mavutil.mavlink
REPO = Path(__file__).resolve().parents[1]

ACCEPTED, IN_PROGRESS = 0, 5
ARMED_FLAG = 128  # HEARTBEAT base_mode MAV_MODE_FLAG_SAFETY_ARMED
LANDED = {0: "undefined", 1: "on_ground", 2: "in_air", 3: "takeoff", 4: "landing"}
# SET_POSITION_TARGET_LOCAL_NED: use vx, vy, vz and yaw rate; ignore position, accel, yaw
VELOCITY_YAWRATE_MASK = 0b0000_0101_1100_0111
GCS_SYSID, GCS_COMPID = 255, 190


# --------------------------------------------------------------------------- where and which ports
def shared_folder(name: str, env: str) -> Path:
    """``$env``, else ``shared/<name>`` beside this checkout or beside the checkout it
    was cloned from (CI tests a clone); the path beside this checkout when neither has
    it (the caller says what is missing)."""
    if env in os.environ:
        return Path(os.environ[env])
    beside = REPO.parent / "shared" / name
    if beside.is_dir():
        return beside
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        url = subprocess.run(["git", "-C", str(REPO), "config", "--get", "remote.origin.url"],
                             capture_output=True, text=True, timeout=5).stdout.strip()
        origin = Path(url.removeprefix("file://"))
        if url and origin.is_absolute() and (origin.parent / "shared" / name).is_dir():
            return origin.parent / "shared" / name
    return beside


def autopilots_dir() -> Path:
    """The packed SITL runtimes: SITL_AUTOPILOTS, else ``shared/autopilots``."""
    return shared_folder("autopilots", "SITL_AUTOPILOTS")


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that nothing is bound to now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _udp_port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


PX4_INSTANCES = range(1, 10)  # 0 is left to a user's own PX4 (onboard udp 14540)


@contextlib.contextmanager
def px4_instance() -> Iterator[int]:
    """Reserve a PX4 instance number whose ports are free, for the ``with`` block: a
    lock file per number, held with flock, so parallel test processes never share one."""
    lock_dir = Path(tempfile.gettempdir()) / "attitude_bridge_px4_instances"
    lock_dir.mkdir(exist_ok=True)
    for n in PX4_INSTANCES:
        f = (lock_dir / f"{n}.lock").open("w")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            continue
        if all(_udp_port_free(p) for p in (14540 + n, 14580 + n, 18570 + n)):
            try:
                yield n
            finally:
                f.close()
            return
        f.close()
    raise RuntimeError("no free PX4 instance number (1-9): every one is in use")


# --------------------------------------------------------------------------- autopilot process
@dataclass
class Sitl:
    """One autopilot process, run from a private copy of its shared folder.

    ``start`` may be called again after ``kill``: the same folder, the parameters it
    saved (a restart, not a fresh vehicle)."""

    kind: str  # "px4" or "ardupilot"
    env: dict[str, str] = field(default_factory=dict)
    tmp: Path | None = None

    @property
    def script(self) -> str:
        return "start_px4_sih.sh" if self.kind == "px4" else "start_ap_sitl.sh"

    @property
    def pidfile(self) -> Path:
        assert self.tmp is not None
        return self.tmp / "run" / ("px4.pid" if self.kind == "px4" else "ap.pid")

    def start(self, fresh: bool = True) -> str:
        """Start it (about a second); returns the start script's line. RuntimeError with
        the script's reason if it does not start."""
        if self.tmp is None:
            self.tmp = Path(tempfile.mkdtemp(prefix=f"sitl_{self.kind}_"))
            here = self.tmp / "dist"
            here.mkdir()
            source = autopilots_dir() / self.kind
            if not source.is_dir():
                raise RuntimeError(f"no {self.kind} runtime at {source} (set SITL_AUTOPILOTS "
                                   "to the shared/autopilots folder)")
            for f in source.iterdir():  # the folder itself is read-only
                shutil.copyfile(f, here / f.name)
            (here / self.script).chmod(0o755)
        env = {**os.environ, **self.env, "FRESH": "1" if fresh else "0"}
        out = subprocess.run(["bash", str(self.tmp / "dist" / self.script),
                              str(self.tmp / "run")],
                             env=env, capture_output=True, text=True, timeout=120)
        if out.returncode != 0:
            raise RuntimeError(f"{self.script} failed: {out.stderr.strip()}")
        return out.stdout.strip()

    def console(self) -> str:
        assert self.tmp is not None
        log = self.tmp / "run" / ("px4.log" if self.kind == "px4" else "ap.log")
        return log.read_text(errors="replace") if log.exists() else ""

    def kill(self) -> None:
        """Stop the process (SIGTERM, then SIGKILL after 10 s); keep its folder."""
        if self.tmp is None:
            return
        with contextlib.suppress(FileNotFoundError, ValueError, ProcessLookupError):
            pid = int(self.pidfile.read_text().strip())
            os.kill(pid, signal.SIGTERM)
            for _ in range(100):
                if not Path(f"/proc/{pid}").exists():
                    break
                time.sleep(0.1)
            else:
                os.kill(pid, signal.SIGKILL)

    def stop(self) -> None:
        """Stop the process and remove its folder."""
        if self.tmp is None:
            return
        self.kill()
        shutil.rmtree(self.tmp, ignore_errors=True)
        self.tmp = None


# --------------------------------------------------------------------------- MAVLink link
@dataclass
class Event:
    t: float  # arrival time, s since the epoch
    what: str


class Link:
    """The companion end of an onboard link: receive thread + tlog writer + command helpers."""

    def __init__(self, port: int, keep: set[str], listen: bool = True):
        """``listen``: bind ``port`` (the autopilot sends there); else send to it from
        an ephemeral port (PX4's GCS link answers whoever spoke first)."""
        mode = "udpin" if listen else "udpout"
        self.conn = mavutil.mavlink_connection(f"{mode}:127.0.0.1:{port}",
                                               source_system=GCS_SYSID,
                                               source_component=GCS_COMPID)
        self.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
        self.keep = keep
        self.sysid: int | None = None
        self.compid = 1
        self.file = None
        self.written: Counter[str] = Counter()
        self.seen: Counter[str] = Counter()
        self.seen_from: Counter[tuple[str, int]] = Counter()  # (type, component id)
        #: message type -> callback(message), called in the receive thread
        self.on_message: dict[str, Callable] = {}
        self.events: list[Event] = []
        self.statustext: list[tuple[float, str]] = []
        self.armed: bool | None = None
        self.landed: int | None = None
        self.custom_mode: int | None = None
        self.pos: tuple[float, ...] | None = None  # LOCAL_POSITION_NED x, y, z, vx, vy, vz
        self.fix = 0
        self.lat = 0
        self.acks: dict[int, int] = {}
        self.cond = threading.Condition()
        self.send_lock = threading.Lock()
        self.file_lock = threading.Lock()
        self.stop_flag = threading.Event()
        self.rx = threading.Thread(target=self._receive, daemon=True)
        self.hb = threading.Thread(target=self._heartbeat, daemon=True)
        self.rx.start()
        self.hb.start()

    # ---- receive side
    def _receive(self) -> None:
        fd = self.conn.port.fileno()
        while not self.stop_flag.is_set():
            ready, _, _ = select.select([fd], [], [], 0.2)
            if not ready:
                continue
            while (m := self.conn.recv_msg()) is not None:
                self._handle(m, time.time())

    def _handle(self, m, now: float) -> None:
        kind = m.get_type()
        if kind == "BAD_DATA":
            return
        src = m.get_srcSystem()
        if self.sysid is None:
            if kind != "HEARTBEAT" or m.autopilot == mav.MAV_AUTOPILOT_INVALID:
                return
            self.sysid, self.compid = src, m.get_srcComponent()
        if src != self.sysid:
            return
        self.seen[kind] += 1
        self.seen_from[(kind, m.get_srcComponent())] += 1
        if self.file is not None and kind in self.keep:
            self._write(m, now)
        with self.cond:
            if kind == "HEARTBEAT" and m.get_srcComponent() == self.compid:
                armed = bool(m.base_mode & ARMED_FLAG)
                if armed != self.armed:
                    self.events.append(Event(now, "armed" if armed else "disarmed"))
                self.armed, self.custom_mode = armed, m.custom_mode
            elif kind == "EXTENDED_SYS_STATE":
                if m.landed_state != self.landed:
                    self.events.append(Event(now, LANDED.get(m.landed_state, "?")))
                self.landed = m.landed_state
            elif kind == "LOCAL_POSITION_NED":
                self.pos = (m.x, m.y, m.z, m.vx, m.vy, m.vz)
            elif kind == "GPS_RAW_INT":
                self.fix = m.fix_type
            elif kind == "GLOBAL_POSITION_INT":
                self.lat = m.lat
            elif kind == "COMMAND_ACK":
                self.acks[m.command] = m.result
            elif kind == "STATUSTEXT":
                self.statustext.append((now, m.text))
            if kind in self.on_message:
                self.on_message[kind](m)
            self.cond.notify_all()

    def _write(self, m, now: float) -> None:
        with self.file_lock:
            if self.file is not None:
                self.file.write(struct.pack(">Q", int(now * 1e6)) + m.get_msgbuf())
                self.written[m.get_type()] += 1

    def record(self, path: Path) -> None:
        """Start writing the kept messages to ``path`` (a tlog)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        with self.file_lock:
            self.file = path.open("wb")

    def close(self) -> None:
        self.stop_flag.set()
        self.rx.join(2)
        self.hb.join(2)
        with self.file_lock:
            if self.file is not None:
                self.file.close()
                self.file = None
        self.conn.close()

    # ---- send side
    def send(self, msg, log: bool = False) -> None:
        with self.send_lock:
            self.conn.mav.send(msg)
        if log:
            self._write(msg, time.time())

    def _heartbeat(self) -> None:
        while True:
            with contextlib.suppress(OSError):  # udpin: no peer to send to yet
                self.send(self.conn.mav.heartbeat_encode(
                    mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, mav.MAV_STATE_ACTIVE))
            if self.stop_flag.wait(1.0):
                return

    def wait_heartbeat(self, timeout: float = 30.0) -> None:
        if not self.wait_for(lambda: self.sysid is not None, timeout):
            raise RuntimeError("no HEARTBEAT from the autopilot")

    def wait_for(self, pred, timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(pred, timeout)

    def command(self, cmd: int, *params: float, retries: int = 5,
                timeout: float = 1.5) -> int | None:
        """COMMAND_LONG until acknowledged; returns the MAV_RESULT (None: no answer)."""
        p = [*params, *([0.0] * (7 - len(params)))]
        for attempt in range(retries):
            with self.cond:
                self.acks.pop(cmd, None)
            self.send(self.conn.mav.command_long_encode(self.sysid, self.compid, cmd,
                                                         attempt, *p), log=True)
            deadline = time.time() + timeout
            while time.time() < deadline:
                if self.wait_for(lambda: cmd in self.acks, deadline - time.time()):
                    with self.cond:
                        result = self.acks.pop(cmd)
                    if result != IN_PROGRESS:
                        return result
                    deadline = time.time() + timeout
        return None

    def set_rate(self, msg_id: int, hz: float) -> int | None:
        interval = -1 if hz <= 0 else round(1e6 / hz)
        return self.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval)

    def velocity(self, vn: float, ve: float, vd: float, yaw_rate: float) -> None:
        """One SET_POSITION_TARGET_LOCAL_NED: NED velocity (m/s) and yaw rate (rad/s)."""
        self.send(self.conn.mav.set_position_target_local_ned_encode(
            int(time.monotonic() * 1e3) & 0xFFFFFFFF, self.sysid, self.compid,
            mav.MAV_FRAME_LOCAL_NED, VELOCITY_YAWRATE_MASK, 0, 0, 0, vn, ve, vd,
            0, 0, 0, 0, yaw_rate))

    def hold_down_velocity(self, z_ref: float, gain: float = 1.0, limit: float = 1.5) -> float:
        """Down velocity that steers LOCAL_POSITION_NED z back to ``z_ref``."""
        if self.pos is None:
            return 0.0
        return max(-limit, min(limit, gain * (z_ref - self.pos[2])))


# --------------------------------------------------------------------------- flight legs
@dataclass(frozen=True)
class Leg:
    """Fly ``seconds`` at ``speed`` m/s, course starting at ``course`` deg (0 = north) and
    turning at ``turn`` deg/s (a circle when non-zero), nose turning at ``yaw`` deg/s."""

    seconds: float
    speed: float = 0.0
    course: float = 0.0
    turn: float = 0.0
    yaw: float = 0.0

    def at(self, t: float) -> tuple[float, float, float]:
        c = math.radians(self.course + self.turn * t)
        return self.speed * math.cos(c), self.speed * math.sin(c), math.radians(self.yaw)


def fly_legs(link: Link, legs: list[Leg], z_ref: float, rate_hz: float = 20.0) -> None:
    """Stream velocity set-points for each leg in turn (altitude held at ``z_ref``)."""
    for leg in legs:
        t0 = time.monotonic()
        while (t := time.monotonic() - t0) < leg.seconds:
            vn, ve, r = leg.at(t)
            link.velocity(vn, ve, link.hold_down_velocity(z_ref), r)
            time.sleep(1.0 / rate_hz)


def stream_hover(link: Link, seconds: float, z_ref: float | None = None) -> None:
    fly_legs(link, [Leg(seconds)], z_ref if z_ref is not None else
             (link.pos[2] if link.pos else 0.0))
