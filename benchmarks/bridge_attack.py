"""The bridge under attack: memory, flood fairness, reboot recovery, signing lock-out.

    PYTHONPATH=. python3 benchmarks/bridge_attack.py [memory|flood|reboot|lockout|all]
        [--json out.json]

* memory — the bridge as its own process (``attitude-bridge run``) while a vehicle
  flies at 500 Hz; then 10,000 spoofed IMU sources (distinct sysid/compid/IMU id, 1,000
  of them on the vehicle's own sysid) and 20,000 spoofed peers (distinct 127.x.y.z
  addresses sending a valid autopilot HEARTBEAT and an IMU packet each). Resident
  memory (VmRSS, VmHWM) before and after, and the bridge's summary counts.
* flood — bridge process, a vehicle process flying at 500 Hz (it times each output
  against the send time of the IMU sample it belongs to), and two flood processes
  sending 50 k RAW_IMU/s each from sysid 77. The vehicle's output rate and latency
  percentiles (end to end, and inside the bridge: IMU read -> output written), without
  and with the flood. The flood processes run at nice 19: a real attacker is another
  machine, whose CPU is not taken from the bridge (its packets' kernel path still is).
* reboot — in-process: a vehicle flies at uptimes from 1 to 71.5 min, reboots (2 s of
  silence), is moved, and comes back stamping from 2 s, with and without SYSTEM_TIME.
  Time from its return to the first output, and the error of every output on the new
  timeline against the truth (none may be > 5°: MAVLink output is held while the
  estimate re-initialises).
* lockout — in-process, signing on: while a signed vehicle flies, forged frames with its
  ids, the largest signing timestamp and a bad signature; replays of its genuine frames
  from fresh UDP ports; frames signed with another key. Attempts, and how many the
  bridge accepted or whether the vehicle lost its output.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FLOOD_SENDER = REPO / "benchmarks" / "flood_sender.py"
sys.path.insert(0, str(REPO))

from bridge.app.config import BridgeConfig  # noqa: E402
from bridge.app.service import BridgeService  # noqa: E402
from bridge.wire.codec import signing_key_from_text  # noqa: E402
from bridge.wire.mav import mavlink  # noqa: E402
from estimators import quat as Q  # noqa: E402
from imu import boards  # noqa: E402

RATE = 500.0
STEP_US = 2000
OMEGA = np.radians([0.0, 0.0, 30.0])
MAG_NED = np.array([0.25, 0.0, 0.43])
G = 9.80665


# --- a vehicle ----------------------------------------------------------------------------
def attitude(q0: np.ndarray, t: float) -> np.ndarray:
    return Q.normalize(Q.multiply(q0, Q.from_rotvec(OMEGA * t)))


def raw_imu(t_us: int, q: np.ndarray) -> mavlink.MAVLink_raw_imu_message:
    p = boards.gy86()
    back = p.to_frd.T
    acc = np.round(back @ Q.rotate(Q.conjugate(q), np.array([0, 0, -G])) / p.accel_scale)
    gyr = np.round(back @ OMEGA / p.gyro_scale)
    mag = np.round(back @ Q.rotate(Q.conjugate(q), MAG_NED) / p.mag_scale)
    return mavlink.MAVLink_raw_imu_message(t_us, *map(int, acc), *map(int, gyr),
                                           *map(int, mag), 0, 0)


# A generic vehicle: the synthetic motion (a board turned in place) is nothing a multirotor
# can fly, so the bridge must not apply its multirotor model to it.
HEARTBEAT = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GENERIC,
                                              mavlink.MAV_AUTOPILOT_PX4, 0, 0, 4, 3)


def vehicle_process(port: int, seconds: float, out: mp.Queue, host: str = "127.0.0.1") -> None:
    """Fly in real time; time every ATTITUDE_QUATERNION against its sample's send time."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 * 1024 * 1024)
    sock.bind((host, 0))
    sock.setblocking(False)
    mav = mavlink.MAVLink(None, 1, 1)
    parser = mavlink.MAVLink(None, 255, 0)
    q0 = Q.from_euler(0.2, -0.1, 0.5)
    t0_us = 1_000_000
    sent_at: dict[int, float] = {}
    latencies: list[float] = []
    errors: list[float] = []
    outputs = 0
    start = time.monotonic()
    n = int(seconds * RATE)

    def drain() -> None:
        nonlocal outputs
        while True:
            try:
                data = sock.recv(65536)
            except BlockingIOError:
                return
            now = time.monotonic()
            try:
                msgs = parser.parse_buffer(data) or []
            except Exception:
                continue
            for m in msgs:
                if m.get_type() == "ATTITUDE_QUATERNION":
                    outputs += 1
                    at = sent_at.get(m.time_boot_ms)
                    if at is not None:
                        latencies.append(now - at)
                    t = (m.time_boot_ms * 1000 - t0_us) * 1e-6
                    truth = attitude(q0, t)
                    errors.append(float(np.degrees(Q.angle_between(
                        np.array([m.q1, m.q2, m.q3, m.q4]), truth))))

    for i in range(n):
        due = start + i / RATE
        while (now := time.monotonic()) < due:
            drain()
            time.sleep(min(0.0005, due - now))
        t_us = t0_us + i * STEP_US
        if i % int(RATE) == 0:
            sock.sendto(HEARTBEAT.pack(mav), ("127.0.0.1", port))
            mav.seq = (mav.seq + 1) % 256
        sock.sendto(raw_imu(t_us, attitude(q0, i * STEP_US * 1e-6)).pack(mav),
                    ("127.0.0.1", port))
        mav.seq = (mav.seq + 1) % 256
        sent_at[t_us // 1000] = time.monotonic()
    end = time.monotonic() + 0.5
    while time.monotonic() < end:
        drain()
        time.sleep(0.001)
    lat = np.array(latencies) * 1e3
    err = np.array(errors[25:]) if len(errors) > 25 else np.array([np.nan])
    out.put({"samples_sent": n, "outputs": outputs, "output_rate_hz": outputs / seconds,
             "latency_ms": {k: round(float(np.percentile(lat, p)), 2) for k, p in
                            (("p50", 50), ("p90", 90), ("p99", 99))} if len(lat) else {},
             "max_error_deg": round(float(np.max(err)), 2)})


# --- the bridge as a process ------------------------------------------------------------------
def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_bridge(port: int, *extra: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen(
        [sys.executable, "-m", "bridge.app.cli", "run", "--connect", f"udpin:127.0.0.1:{port}",
         "--estimator", "eskf", *extra], cwd=REPO, env=env, stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL, text=True)
    # Up once it answers a heartbeat with its own.
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(0.5)
    mav = mavlink.MAVLink(None, 250, 1)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        sock.sendto(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(mav),
                    ("127.0.0.1", port))
        try:
            if sock.recv(1024):
                break
        except TimeoutError:
            continue
    sock.close()
    return proc


def stop_bridge(proc: subprocess.Popen) -> str:
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=30)
    return out


def rss_mb(pid: int) -> dict[str, float]:
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            fields[key] = round(int(value.split()[0]) / 1024, 1)
    return fields


def summary_lines(out: str) -> list[str]:
    return [line.strip() for line in out.splitlines()
            if line.strip().startswith(("vehicle ", "connection:"))]


def spoof(port: int, sources: int, peers: int) -> dict[str, int]:
    """10,000 sources x 20 IMU packets, from spoofed addresses; then 20,000 peers."""
    dst = ("127.0.0.1", port)
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(250)]
    for k, s in enumerate(socks):
        s.bind((f"127.0.4.{k + 1}", 0))
    imu = raw_imu(0, Q.from_euler(np.pi, 0, 0))
    sent = 0
    for k in range(sources):
        if k < 1000:  # on the vehicle's own sysid: other components and IMU ids
            sysid, compid, imu_id = 1, 2 + k % 200, k // 200
        else:
            sysid, compid, imu_id = 2 + k % 250, 1 + (k // 250) % 200, (k // 50_000)
        mav = mavlink.MAVLink(None, sysid, compid)
        s = socks[k % len(socks)]
        for j in range(20):
            imu.time_usec = 1_000_000 + j * 2000
            imu.id = imu_id
            s.sendto(imu.pack(mav), dst)
            sent += 1
        if k % 200 == 199:
            time.sleep(0.02)
    for s in socks:
        s.close()
    hb = mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3)
    for k in range(peers):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind((f"127.1.{k // 250}.{k % 250 + 1}", 0))
        mav = mavlink.MAVLink(None, 2 + k % 250, 1)
        s.sendto(hb.pack(mav), dst)
        s.sendto(imu.pack(mav), dst)
        s.close()
        sent += 2
        if k % 500 == 499:
            time.sleep(0.02)
    return {"datagrams": sent}


def bench_memory() -> dict:
    port = free_port()
    proc = start_bridge(port)
    q: mp.Queue = mp.get_context("spawn").Queue()
    vehicle = mp.get_context("spawn").Process(target=vehicle_process, args=(port, 40.0, q))
    vehicle.start()
    time.sleep(8.0)
    before = rss_mb(proc.pid)
    t = time.monotonic()
    attack = spoof(port, 10_000, 20_000)
    attack["seconds"] = round(time.monotonic() - t, 1)
    time.sleep(2.0)
    after = rss_mb(proc.pid)
    flying = q.get(timeout=120)
    vehicle.join()
    out = stop_bridge(proc)
    return {"before": before, "after": after, "attack": attack, "vehicle": flying,
            "summary": summary_lines(out)}


def bench_flood(rate: float = 100_000.0, seconds: float = 10.0) -> dict:
    result = {}
    for label, flood_rate in (("baseline", 0.0), ("flood", rate)):
        port = free_port()
        proc = start_bridge(port)
        q: mp.Queue = mp.get_context("spawn").Queue()
        vehicle = mp.get_context("spawn").Process(target=vehicle_process,
                                                  args=(port, seconds, q))
        vehicle.start()
        time.sleep(1.0)
        floods = [subprocess.Popen(["nice", "-n", "19", sys.executable, str(FLOOD_SENDER),
                                    str(port), str(seconds - 1.0), str(flood_rate / 2)],
                                   stdout=subprocess.PIPE, text=True)
                  for _ in range(2 if flood_rate else 0)]
        cpu0 = _cpu_s(proc.pid)
        flying = q.get(timeout=120)
        vehicle.join()
        cpu = _cpu_s(proc.pid) - cpu0
        if floods:
            flying["flood_sent"] = sum(int(f.communicate(timeout=30)[0].strip())
                                       for f in floods)
            flying["flood_rate_hz"] = round(flying["flood_sent"] / (seconds - 1.0))
        flying["bridge_cpu_percent"] = round(100.0 * cpu / seconds, 1)
        flying["summary"] = summary_lines(stop_bridge(proc))
        result[label] = flying
    base = result["baseline"]["output_rate_hz"]
    result["flood"]["rate_vs_baseline"] = round(result["flood"]["output_rate_hz"] / base, 3)
    return result


def _cpu_s(pid: int) -> float:
    parts = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


# --- in-process scenarios ---------------------------------------------------------------------
class Flyer:
    """A vehicle on one UDP socket in this event loop, collecting the bridge's output."""

    def __init__(self, port: int, key: bytes | None = None, host: str = "127.0.0.1") -> None:
        self.dst = ("127.0.0.1", port)
        self.mav = mavlink.MAVLink(None, 1, 1)
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.timestamp = int((time.time() - 1420070400) * 1e5)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, 0))
        self.sock.setblocking(False)
        self.parser = mavlink.MAVLink(None, 255, 0)
        self.outputs: list = []
        self.arrivals: list[float] = []  # perf_counter() of each output
        asyncio.get_running_loop().add_reader(self.sock.fileno(), self._readable)

    def _readable(self) -> None:
        while True:
            try:
                data = self.sock.recv(65536)
            except BlockingIOError:
                return
            try:
                msgs = self.parser.parse_buffer(data) or []
            except Exception:
                continue
            new = [m for m in msgs if m.get_type() == "ATTITUDE_QUATERNION"]
            self.outputs += new
            self.arrivals += [time.perf_counter()] * len(new)

    def pack(self, msg) -> bytes:
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf

    def send(self, msg) -> bytes:
        buf = self.pack(msg)
        self.sock.sendto(buf, self.dst)
        return buf

    async def fly(self, seconds: float, t0_us: int, q0: np.ndarray, between=None) -> int:
        start = time.perf_counter()
        n = int(seconds * RATE)
        for i in range(n):
            t_us = t0_us + i * STEP_US
            if i % int(RATE) == 0:
                self.send(HEARTBEAT)
            self.send(raw_imu(t_us % 2**64, attitude(q0, i * STEP_US * 1e-6)))
            if between is not None:
                between(i, t_us)
            if i % 25 == 24:
                await asyncio.sleep(max(0.0, start + (i + 1) / RATE - time.perf_counter()))
        return t0_us + n * STEP_US

    def close(self) -> None:
        asyncio.get_running_loop().remove_reader(self.sock.fileno())
        self.sock.close()


async def with_bridge(coro_fn, **settings):
    cfg = BridgeConfig(connect="udpin:127.0.0.1:0", **settings)
    service = BridgeService(cfg)
    stop = asyncio.Event()
    task = asyncio.create_task(service.run(stop))
    await service.ready.wait()
    try:
        return await coro_fn(service)
    finally:
        stop.set()
        await task


def errors_deg(msgs: list, t0_us: int, q0: np.ndarray) -> np.ndarray:
    if not msgs:
        return np.array([])
    est = np.array([[m.q1, m.q2, m.q3, m.q4] for m in msgs])
    truth = np.array([attitude(q0, ((m.time_boot_ms - t0_us // 1000) % 2**32) * 1e-3)
                      for m in msgs])
    return np.degrees(Q.angle_between(est, truth))


async def reboot_case(uptime_min: float, system_time: bool) -> dict:
    async def run(bridge):
        v = Flyer(bridge.port)
        q0, q_after = Q.from_euler(0.2, -0.1, 0.5), Q.from_euler(-0.3, 0.25, 2.3)
        t0 = int(uptime_min * 60e6)
        await v.fly(3.0, t0, q0)
        await asyncio.sleep(2.0)
        boot0 = 2_000_000
        if system_time:
            v.send(mavlink.MAVLink_system_time_message(0, boot0 // 1000 - 50))
        returned = time.perf_counter()
        end = await v.fly(6.0, boot0, q_after)
        await asyncio.sleep(0.3)
        new = [(at, m) for at, m in zip(v.arrivals, v.outputs, strict=True)
               if boot0 // 1000 <= m.time_boot_ms < end // 1000]
        after = [m for _, m in new]
        err = errors_deg(after, boot0, q_after)
        v.close()
        bridge.publish_status()
        st = bridge.last_status[1]
        first = min(m.time_boot_ms for m in after) - boot0 // 1000 if after else None
        return {"uptime_min": uptime_min, "system_time": system_time,
                "reboot_flagged": st["flags"]["reboot"], "restarts": st["restarts"],
                "first_output_wall_s": round(new[0][0] - returned, 3) if new else None,
                "first_output_board_s": None if first is None else first / 1e3,
                "outputs_after": len(after),
                "max_error_deg": round(float(err.max()), 3) if len(err) else None,
                "outputs_over_5deg": int((err > 5.0).sum()),
                "held_initialising": st["held_initialising"]}

    return await with_bridge(run, out_rate=50.0)


def bench_reboot() -> list[dict]:
    cases = [(m, s) for m in (1.0, 30.0, 53.7, 60.0, 71.5) for s in (False, True)]
    return [asyncio.run(reboot_case(m, s)) for m, s in cases]


async def lockout_case() -> dict:
    key_file = Path(tempfile.mkdtemp()) / "key"
    key_file.write_text("benchmark key")
    key = signing_key_from_text("benchmark key")
    other = signing_key_from_text("not the key")

    async def run(bridge):
        v = Flyer(bridge.port, key)
        rogue = mavlink.MAVLink(None, 1, 1)
        rogue.signing.secret_key = other
        rogue.signing.sign_outgoing = True
        rogue.signing.timestamp = 2**48 - 10
        attempts = {"forged_max_timestamp": 0, "replayed_new_port": 0, "wrong_key": 0}
        captured: list[bytes] = []
        q0 = Q.from_euler(0.1, 0.1, 0.3)
        orig = v.send

        def capture(msg):
            buf = orig(msg)
            captured.append(buf)
            return buf

        v.send = capture

        def attack(i: int, t_us: int) -> None:
            if i % 10 == 5:
                b = bytearray(v.pack(raw_imu(t_us + 1000, Q.from_euler(np.pi, 0, 0))))
                b[-12:-6] = (2**48 - 1).to_bytes(6, "little")
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                    s.sendto(bytes(b), v.dst)
                attempts["forged_max_timestamp"] += 1
            if i % 10 == 7 and captured:
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                    s.sendto(captured[-2], v.dst)
                attempts["replayed_new_port"] += 1
            if i % 10 == 9:
                buf = raw_imu(t_us + 1500, Q.from_euler(np.pi, 0, 0)).pack(rogue)
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                    s.sendto(buf, v.dst)
                attempts["wrong_key"] += 1

        t0 = 1_000_000
        end = await v.fly(10.0, t0, q0, attack)
        await asyncio.sleep(0.3)
        conn = bridge.link_status()
        genuine = len(captured)
        outs = [m for m in v.outputs if t0 // 1000 <= m.time_boot_ms < end // 1000]
        last_2s = [m for m in outs if m.time_boot_ms >= (end - 2_000_000) // 1000]
        err = errors_deg(outs[25:], t0, q0)
        v.close()
        accepted_attack = conn["messages_in"] - genuine - 1  # the probe heartbeat aside
        return {"attempts": attempts, "total_attempts": sum(attempts.values()),
                "accepted_attack_frames": max(0, accepted_attack),
                "refused": {k: conn[k] for k in ("bad_signature", "replayed",
                                                 "unsigned_rejected")},
                "vehicle_output_rate_last_2s_hz": len(last_2s) / 2.0,
                "max_error_deg": round(float(err.max()), 3),
                "locked_out": len(last_2s) < 0.9 * 100}

    return await with_bridge(run, out_rate=50.0, signing_key=f"file:{key_file}")


def bench_lockout() -> dict:
    return asyncio.run(lockout_case())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("what", nargs="?", default="all",
                    choices=("memory", "flood", "reboot", "lockout", "all"))
    ap.add_argument("--json", metavar="PATH")
    args = ap.parse_args()
    results = {}
    for name, fn in (("lockout", bench_lockout), ("reboot", bench_reboot),
                     ("memory", bench_memory), ("flood", bench_flood)):
        if args.what in (name, "all"):
            print(f"--- {name}", flush=True)
            results[name] = fn()
            print(json.dumps(results[name], indent=1), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
