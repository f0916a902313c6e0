"""The board's UDP link: paces the firmware's packets in real time (or as fast as
possible) to one or more targets, through the link faults, inside asyncio; and reads
its socket like an autopilot: commands and parameter requests from a listener (sent to
the address the stream comes from) are answered to their sender (``hil.commands``).

Every datagram, stream or reply, gets the link's next sequence number when it is sent
(``Sequencer``), so a reply slotted between pre-built stream packets does not look like
loss or reordering to a listener counting sequence gaps.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from fastcrc.crc16 import mcrf4xx

from .commands import CommandHandler
from .config import EmulatorConfig
from .faults import LinkFaults
from .messages import Firmware, Packet, mavlink
from .source import SampleSource
from .stats import EmulatorStats

log = logging.getLogger(__name__)

#: In --fast mode, let the event loop (and any in-process receiver) run this often.
FAST_YIELD_EVERY = 16


class Sequencer:
    """Stamps the link's running sequence number into finished MAVLink 2 frames."""

    def __init__(self) -> None:
        self.seq = 0

    def stamp(self, data: bytes) -> bytes:
        frame = bytearray(data)
        if len(frame) < 12 or frame[0] != 0xFD:
            return data
        msg_id = frame[7] | frame[8] << 8 | frame[9] << 16
        cls = mavlink.mavlink_map.get(msg_id)
        if cls is None:
            return data
        frame[4] = self.seq
        self.seq = (self.seq + 1) & 0xFF
        end = 10 + frame[1]
        crc = mcrf4xx(bytes(frame[1:end]) + bytes([cls.crc_extra]))
        frame[end], frame[end + 1] = crc & 0xFF, crc >> 8
        return bytes(frame)


class SendError(ValueError):
    """Every datagram to a target was refused by the OS: the target is unusable."""


class _Endpoint(asyncio.DatagramProtocol):
    def __init__(self, stats: EmulatorStats, on_datagram):
        self.stats = stats
        self.on_datagram = on_datagram

    def datagram_received(self, data: bytes, addr: tuple) -> None:
        self.on_datagram(data, addr)

    last_error: Exception | None = None

    def error_received(self, exc: Exception) -> None:
        # A target without a listener answers with ICMP port unreachable; keep going.
        self.last_error = exc
        self.stats.send_errors += 1
        log.debug("send error: %s", exc)


class Emulator:
    """A software GY-86 + STM32 streaming MAVLink 2 over UDP. ``stats`` counts everything."""

    def __init__(self, config: EmulatorConfig):
        self.config = config
        self.stats = EmulatorStats()

    async def run(self, targets: list[tuple[str, int]]) -> EmulatorStats:
        """Stream until ``duration_s`` of samples went out, or until cancelled."""
        if not targets:
            raise ValueError("at least one UDP target is needed")
        cfg = self.config
        loop = asyncio.get_running_loop()
        addresses = [await _resolve(loop, host, port) for host, port in targets]
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        source = SampleSource(cfg, counts=self.stats.faults)
        mpu = source.mpu.config
        firmware = Firmware(cfg, (mpu.gyro_lsb_per_dps, mpu.accel_lsb_per_g),
                            source.hmc.config.lsb_per_gauss)
        self.firmware = firmware
        now_s = [0.0]  # stream time of the last packet sent: the board's "now"

        def now_message(kind: str) -> mavlink.MAVLink_message | None:
            """A HEARTBEAT / EXTENDED_SYS_STATE for MAV_CMD_REQUEST_MESSAGE, with the
            flight state of the instant the stream has reached."""
            armed, landed = source.profile.flight_state(np.array([now_s[0]]))
            return firmware.message_now(kind, bool(armed[0]), int(landed[0]))

        handler = CommandHandler(firmware.personality, firmware.streams, cfg.sysid, cfg.compid,
                                 cfg.environment.magnetic_declination_deg,
                                 self.stats.requests, now_message)
        sequencer = Sequencer()

        def on_datagram(data: bytes, addr: tuple) -> None:
            parser = mavlink.MAVLink(None)  # one per datagram: no half frame carries over
            parser.robust_parsing = True
            try:
                msgs = parser.parse_buffer(data) or []
            except Exception:  # bad bytes from the link are counted, never raised
                msgs = []
            if not msgs:
                self.stats.requests.ignored += 1
            for msg in msgs:
                if msg.get_type() == "BAD_DATA":
                    self.stats.requests.ignored += 1
                    continue
                for reply in handler.handle(msg):
                    data_out = sequencer.stamp(firmware.pack_reply(reply))
                    self.stats.count_message(reply.get_type())
                    transport.sendto(data_out, addr)
                    self.stats.datagrams_sent += 1
                    self.stats.bytes_sent += len(data_out)

        transport, endpoint = await loop.create_datagram_endpoint(
            lambda: _Endpoint(self.stats, on_datagram), sock=sock)
        link = LinkFaults(cfg.faults, source.rng["link_faults"], self.stats.faults)
        start_wall = time.perf_counter()
        start: float | None = None  # stream time 0 = when the first packet is ready
        sent_since_yield = 0

        delivered = dict.fromkeys(addresses, 0)  # sends the kernel took, per target
        refused: dict[tuple[str, int], Exception] = {}  # last refusal, per target

        def send(datagrams: list[bytes]) -> None:
            for data in datagrams:
                for addr in addresses:
                    errors = self.stats.send_errors
                    transport.sendto(data, addr)  # a refusal calls error_received at once
                    if self.stats.send_errors > errors and endpoint.last_error is not None:
                        refused[addr] = endpoint.last_error
                    else:
                        delivered[addr] += 1
                    self.stats.datagrams_sent += 1
                    self.stats.bytes_sent += len(data)

        def check_targets() -> None:
            """A target that refused every datagram of a whole chunk never will take one
            (e.g. a broadcast address): stop instead of streaming into nothing."""
            for (host, port), exc in refused.items():
                if delivered[(host, port)] == 0:
                    raise SendError(f"cannot send to udp:{host}:{port}: {exc}")

        def produce() -> tuple[int, float, list[Packet]]:
            rec = source.chunk()
            t_end = source.time_s
            return len(rec), t_end, firmware.packets(rec, t_end)

        # Chunks are made in a worker thread one step ahead, so that generating the next
        # 50 ms of data does not stall the pacing of the current one.
        worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="hil-chunks")
        try:
            pending = loop.run_in_executor(worker, produce)
            while pending is not None:
                n_samples, t_end, packets = await pending
                pending = None if source.finished else loop.run_in_executor(worker, produce)
                if start is None:
                    start = loop.time()
                for packet in packets:
                    if cfg.fast:
                        sent_since_yield += 1
                        if sent_since_yield >= FAST_YIELD_EVERY:
                            sent_since_yield = 0
                            await asyncio.sleep(0)
                    else:
                        wait = start + packet.due_s - loop.time()
                        if wait > 0.0:
                            await asyncio.sleep(wait)
                    self.stats.count_message(packet.kind)
                    now_s[0] = packet.due_s
                    send(link.apply(sequencer.stamp(packet.data)))
                check_targets()
                self.stats.imu_samples += n_samples
                self.stats.stream_time_s = t_end
            send(link.flush())
            await _drain(transport)
        finally:
            worker.shutdown(wait=False, cancel_futures=True)
            self.stats.wall_time_s = time.perf_counter() - start_wall
            transport.close()
        return self.stats


async def _resolve(loop: asyncio.AbstractEventLoop, host: str, port: int) -> tuple[str, int]:
    if not 0 < port < 65536:
        raise ValueError(f"bad UDP port {port}")
    try:
        info = await loop.getaddrinfo(host, port, family=socket.AF_INET, type=socket.SOCK_DGRAM)
    except socket.gaierror as exc:
        raise ValueError(f"cannot resolve {host!r}: {exc}") from exc
    return info[0][4][:2]


async def _drain(transport: asyncio.DatagramTransport) -> None:
    """Wait until asyncio has handed every buffered datagram to the kernel."""
    while transport.get_write_buffer_size() > 0:
        await asyncio.sleep(0.001)
