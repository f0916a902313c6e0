"""Real-socket helpers for the bridge tests: a pymavlink IMU sender and a UDP listener.

Not a test module: imported by tests/test_bridge_*.py. Everything here uses real UDP
sockets on 127.0.0.1 and real pymavlink encoding.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import math
import socket
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from bridge.app.config import BridgeConfig
from bridge.app.service import BridgeService
from bridge.wire.mav import mavlink
from estimators import quat as Q
from imu import boards

G = 9.80665
#: A magnetic field in NED [gauss]: north and down (inclination ~60°), no declination.
MAG_NED = np.array([0.25, 0.0, 0.43])
ZERO3 = np.zeros(3)
ZERO3.setflags(write=False)
#: The component id the bridge sends its attitude from.
BRIDGE_COMPID = 191


def _v2_frame_size(data: bytes, i: int) -> int:
    """Bytes of the MAVLink 2 frame starting at ``i``: 10-byte header, payload, checksum
    and, when flagged, the 13-byte signature."""
    return 12 + data[i + 1] + (13 if data[i + 2] & 1 else 0)


def frame_ids(data: bytes) -> set[int] | None:
    """The message ids of the MAVLink frames a datagram holds, read from their headers
    alone; None when the bytes are not a clean run of frames (then only decoding tells)."""
    ids: set[int] = set()
    i, n = 0, len(data)
    while i < n:
        if data[i] == 0xFD and i + 10 <= n:  # MAVLink 2
            size = _v2_frame_size(data, i)
            ids.add(data[i + 7] | data[i + 8] << 8 | data[i + 9] << 16)
        elif data[i] == 0xFE and i + 6 <= n:  # MAVLink 1: 6-byte header
            size = 8 + data[i + 1]
            ids.add(data[i + 5])
        else:
            return None
        i += size
    return ids if i == n else None


def lone_frame_stamp(data: bytes) -> int | None:
    """The first eight payload bytes of a datagram that is one whole MAVLink 2 frame, as
    an unsigned little-endian integer: a message's time_usec where that field leads it
    (HIL_STATE_QUATERNION); None for anything else (then only decoding tells)."""
    if len(data) < 12 or data[0] != 0xFD or _v2_frame_size(data, 0) != len(data):
        return None
    return int.from_bytes(data[10:10 + min(data[1], 8)], "little")  # (trailing zeros trimmed)


@dataclass
class UdpListener:
    """Collects every MAVLink message sent to its port (a stand-in GCS).

    Drains its socket completely on each wake-up (4 MB buffer), so a --fast emulator
    in the same event loop cannot overflow it. Datagrams are kept as they arrived and
    decoded when a test looks (``of_type`` decodes only those whose frame headers name
    the type): a listener that also receives an emulator's whole stream, for its truth,
    would otherwise spend more CPU decoding IMU messages nobody reads than the bridge
    spends on them. With a signing key everything is decoded in arrival order, as
    pymavlink's signature check refuses a timestamp older than one it has seen.
    """

    parser: mavlink.MAVLink = field(default_factory=lambda: mavlink.MAVLink(None, 255, 0))
    sock: socket.socket | None = None
    host: str = "127.0.0.1"  # any 127.x.y.z: another "machine" on the loopback network
    _datagrams: list = field(default_factory=list)  # (arrival time, bytes, frame ids)
    _decoded: dict = field(default_factory=dict)  # datagram index -> its messages

    async def start(self) -> int:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 * 1024 * 1024)
        self.sock.bind((self.host, 0))
        self.sock.setblocking(False)
        asyncio.get_running_loop().add_reader(self.sock.fileno(), self._readable)
        return self.port

    def _readable(self) -> None:
        while self.sock is not None:
            try:
                data = self.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                continue
            self._datagrams.append((time.perf_counter(), data, frame_ids(data)))

    def _decode(self, index: int) -> list:
        """The messages of one datagram (whole datagrams only: no half frame carries
        over; corrupted ones, from the fault tests, give none)."""
        if index not in self._decoded:
            try:
                msgs = self.parser.parse_buffer(self._datagrams[index][1]) or []
            except Exception:
                key = self.parser.signing.secret_key
                self.parser = mavlink.MAVLink(None, 255, 0)
                self.parser.signing.secret_key = key
                msgs = []
            self.parser.buf, self.parser.buf_index = bytearray(), 0
            self.parser.expected_length = mavlink.HEADER_LEN_V1 + 2
            self._decoded[index] = [m for m in msgs
                                    if not isinstance(m, mavlink.MAVLink_bad_data)]
        return self._decoded[index]

    @property
    def messages(self) -> list:
        """Every message so far, in arrival order, as (arrival time, message)."""
        return [(t, m) for k, (t, _, _) in enumerate(self._datagrams)
                for m in self._decode(k)]

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]

    def sendto(self, data: bytes, addr: tuple) -> None:
        self.sock.sendto(data, addr)

    @property
    def _decodes_all(self) -> bool:
        """With a signing key every datagram is decoded, in order (see the class doc)."""
        return self.parser.signing.secret_key is not None

    def _may_hold(self, msgid: int) -> Iterator[tuple[int, bytes, set[int] | None]]:
        """(index, bytes, frame ids) of the datagrams that may hold ``msgid``, in arrival
        order: all of them when ``_decodes_all``."""
        every = self._decodes_all
        for k, (_, data, ids) in enumerate(self._datagrams):
            if every or ids is None or msgid in ids:
                yield k, data, ids

    def of_type(self, name: str, sysid: int | None = None) -> list:
        out = []
        for k, _, _ in self._may_hold(getattr(mavlink, f"MAVLINK_MSG_ID_{name}")):
            out += [m for m in self._decode(k) if m.get_type() == name and
                    (sysid is None or m.get_srcSystem() == sysid)]
        return out

    def truth_by_ms(self, wanted: set[int]) -> dict[int, list[float]]:
        """The emulator's truth (HIL_STATE_QUATERNION attitude) at the wanted board ms,
        the last one of each ms as it arrived. An emulator sends one per IMU sample and
        a 50 Hz output needs a twentieth of them, so a datagram whose time_usec (read
        from its bytes) is not wanted is left undecoded."""
        name = "HIL_STATE_QUATERNION"
        msgid = mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION
        every = self._decodes_all
        out = {}
        for k, data, ids in self._may_hold(msgid):
            stamp = lone_frame_stamp(data) if ids == {msgid} and not every else None
            if stamp is not None and stamp // 1000 not in wanted:
                continue
            for m in self._decode(k):
                if m.get_type() == name and m.time_usec // 1000 in wanted:
                    out[m.time_usec // 1000] = m.attitude_quaternion
        return out

    def outputs_with_truth(self, compid: int = BRIDGE_COMPID
                           ) -> tuple[list, dict[int, list[float]]]:
        """The ATTITUDE_QUATERNION messages from ``compid`` (the bridge's) whose
        time_boot_ms has the emulator's truth, and that truth by ms (``truth_by_ms``)."""
        out = [m for m in self.of_type("ATTITUDE_QUATERNION") if m.get_srcComponent() == compid]
        truth = self.truth_by_ms({m.time_boot_ms for m in out})
        return [m for m in out if m.time_boot_ms in truth], truth

    def close(self) -> None:
        if self.sock is not None:
            with contextlib.suppress(Exception):
                asyncio.get_running_loop().remove_reader(self.sock.fileno())
            self.sock.close()
            self.sock = None


class MavSender:
    """Sends real MAVLink 2 packets from one (sysid, compid) over a UDP socket.

    It also listens on its socket: the bridge (udpin) replies to whoever sent to it, so
    the sender doubles as the vehicle side of the link.
    """

    def __init__(self, port: int, sysid: int = 1, compid: int = 1,
                 signing_key: bytes | None = None, host: str = "127.0.0.1") -> None:
        self.target = ("127.0.0.1", port)
        self.mav = mavlink.MAVLink(None, sysid, compid)
        if signing_key is not None:
            self.mav.signing.secret_key = signing_key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.timestamp = int((time.time() - 1420070400) * 1e5)
        self.listener = UdpListener(host=host)
        if signing_key is not None:  # verify what comes back: get_signed() is then True
            self.listener.parser.signing.secret_key = signing_key

    async def start(self) -> None:
        await self.listener.start()

    def pack(self, msg: mavlink.MAVLink_message) -> bytes:
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf

    def send_bytes(self, data: bytes) -> None:
        self.listener.sendto(data, self.target)

    def send(self, msg: mavlink.MAVLink_message) -> bytes:
        buf = self.pack(msg)
        self.send_bytes(buf)
        return buf

    def close(self) -> None:
        self.listener.close()


def gy86_counts(q: np.ndarray, omega_frd: np.ndarray = ZERO3,
                mag_ned: np.ndarray = MAG_NED) -> tuple[list[int], list[int], list[int]]:
    """RAW_IMU integers (acc, gyro, mag) a GY-86 would read at attitude q (FRD->NED)."""
    p = boards.gy86()
    back = p.to_frd.T  # FRD -> chip axes (the matrix is its own inverse)
    acc_frd = Q.rotate(Q.conjugate(q), np.array([0.0, 0.0, -G]))
    mag_frd = Q.rotate(Q.conjugate(q), mag_ned)
    acc = np.round(back @ acc_frd / p.accel_scale).astype(int).tolist()
    gyr = np.round(back @ omega_frd / p.gyro_scale).astype(int).tolist()
    mag = np.round(back @ mag_frd / p.mag_scale).astype(int).tolist()
    return acc, gyr, mag


def raw_imu(time_usec: int, q: np.ndarray, omega: np.ndarray = ZERO3,
            imu_id: int = 0) -> mavlink.MAVLink_raw_imu_message:
    acc, gyr, mag = gy86_counts(q, omega)
    return mavlink.MAVLink_raw_imu_message(time_usec, *acc, *gyr, *mag, imu_id, 2500)


def autopilot_heartbeat(mav_type: int = mavlink.MAV_TYPE_GENERIC
                        ) -> mavlink.MAVLink_heartbeat_message:
    """A PX4 autopilot's heartbeat. Generic vehicle type by default: the synthetic
    motions here (a board held tilted and turned in place) are nothing a multirotor
    can fly, so the bridge must not run its multirotor model on them."""
    return mavlink.MAVLink_heartbeat_message(mav_type, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 4, 3)


def attitude_of(msgs: list) -> np.ndarray:
    """Quaternions of ATTITUDE_QUATERNION messages, (N, 4)."""
    return np.array([[m.q1, m.q2, m.q3, m.q4] for m in msgs])


def angle_deg(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    return np.degrees(Q.angle_between(q1, q2))


@contextlib.asynccontextmanager
async def running_bridge(**settings):
    """A BridgeService on udpin:127.0.0.1:<free port>, stopped (and awaited) on exit."""
    settings.setdefault("connect", "udpin:127.0.0.1:0")
    cfg = BridgeConfig(**settings)
    service = BridgeService(cfg)
    stop = asyncio.Event()
    task = asyncio.create_task(service.run(stop))
    await service.ready.wait()
    try:
        yield service
    finally:
        stop.set()
        await asyncio.wait_for(task, 5.0)


async def send_static(sender: MavSender, q: np.ndarray, seconds: float, rate_hz: float = 500.0,
                      t0_us: int = 1_000_000, burst: int = 25) -> int:
    """Stream RAW_IMU of a vehicle at rest at attitude q; returns the next time_usec."""
    n = int(seconds * rate_hz)
    step = round(1e6 / rate_hz)
    t = t0_us
    for i in range(n):
        sender.send(raw_imu(t, q))
        t += step
        if i % burst == burst - 1:
            await asyncio.sleep(burst / rate_hz)
    return t


def euler_q(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    return Q.from_euler(math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg))


def rotating(q0: np.ndarray, omega_frd: np.ndarray, t: float) -> np.ndarray:
    """Attitude after t seconds at a constant body rate: q0 ⊗ exp(ω t / 2)."""
    return Q.normalize(Q.multiply(q0, Q.from_rotvec(np.asarray(omega_frd) * t)))


async def send_rotating(sender: MavSender, q0: np.ndarray, omega: np.ndarray, seconds: float,
                        rate_hz: float = 500.0, t0_us: int = 1_000_000,
                        burst: int = 25, sent: dict[int, float] | None = None) -> int:
    """Stream RAW_IMU of a constant-rate rotation; returns the next time_usec.
    ``sent``: filled with time_usec -> perf_counter() when that sample was sent."""
    step = round(1e6 / rate_hz)
    for i in range(int(seconds * rate_hz)):
        t_us = t0_us + i * step
        if sent is not None:
            sent[t_us] = time.perf_counter()
        sender.send(raw_imu(t_us, rotating(q0, omega, (t_us - t0_us) * 1e-6), omega))
        if i % burst == burst - 1:
            await asyncio.sleep(burst / rate_hz)
    return t0_us + int(seconds * rate_hz) * step


def async_test(fn):
    """Run an async test function in a fresh event loop (no pytest plugin needed)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        return asyncio.run(fn(*args, **kwargs))

    return wrapper


async def wait_until(condition, timeout: float = 5.0, period: float = 0.05) -> bool:
    """Poll ``condition()`` until true or timeout (for delivery under CPU load)."""
    deadline = asyncio.get_running_loop().time() + timeout
    while not condition():
        if asyncio.get_running_loop().time() > deadline:
            return False
        await asyncio.sleep(period)
    return True


def accepted(bridge, sysid: int = 1) -> int:
    """IMU samples the bridge accepted from a vehicle so far."""
    return sum(s.accepted for k, s in bridge.ingest.sources.items() if k.sysid == sysid)


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that nothing is bound to right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def stream_emulator(bridge, cfg, out_port: int, share: float = 1.0):
    """Run the emulator ``cfg`` into ``bridge`` and, for the truth, to ``out_port``; then
    wait until the bridge has handled ``share`` of its IMU messages (and 0.3 s more for
    the last outputs). Returns the emulator's stats."""
    from hil import Emulator

    stats = await Emulator(cfg).run(targets=[("127.0.0.1", bridge.port),
                                             ("127.0.0.1", out_port)])
    n_imu = stats.messages[cfg.imu_message]
    await wait_until(lambda: sum(s.accepted + s.dropped
                                 for s in bridge.ingest.sources.values()) >= share * n_imu,
                     timeout=10.0)
    await asyncio.sleep(0.3)
    return stats


def airborne_per_sample(status: dict, t_board: np.ndarray) -> np.ndarray:
    """The flight state the bridge gave its estimators at each board time (1 / 0 / NaN),
    from its status's ``flight_state.board_switches``: a switch applies from the sample
    after the board time it names (None: before the first sample)."""
    out = np.full(len(t_board), np.nan)
    for t_switch, state in status["flight_state"]["board_switches"]:
        value = {"airborne": 1.0, "on ground": 0.0}.get(state, np.nan)
        start = 0 if t_switch is None else int(np.searchsorted(t_board, t_switch, "right"))
        out[start:] = value
    return out
