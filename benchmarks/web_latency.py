"""Does the web view slow the MAVLink path? Bridge latency at 1 kHz with 0, 1 and 5
browsers watching.

    python benchmarks/web_latency.py [--rounds 3] [--shared] [--json out.json]

Per condition and round: a fresh bridge (`attitude-bridge run --web`, eskf + mahony +
madgwick, every sample answered: --out-rate 0) and a sender process pacing RAW_IMU at
1 kHz for 45 s that times, on its own clock, each sample's ATTITUDE_QUATERNION coming
back (send -> receive over loopback UDP, matched by the sample's time). The browsers
(Debian's chromium, headless, one page each, driven by Playwright) are loaded before
and start drawing during the first 35 s; the last 10 s are measured while they draw.
Conditions are interleaved round by round (none, 1, 5, 5 of another bridge, none, ...)
so that drift of this noisy machine falls on all of them. "5 of another bridge" loads
the machine as five viewers do (a second bridge on the browsers' core, watched by five
pages) with no work for the measured bridge: what the view costs the bridge is the
difference between it and "5 viewers". Also reported: the bridge's own in-process
latency (packet read -> attitude sent, its status file) and the view's dropped frames.

Where things run: by default the bridge has core 0 to itself and the browsers and the
sender share the other, as when the people watching use their own machines (a page
drawing at its rate costs a fifth of a core: five of them would take a 2-core companion
computer's second core). The sender sleeps between packets and runs SCHED_FIFO (when
root) so that the browsers beside it cannot delay its clock. ``--shared`` puts
everything on both cores, as if the five browsers ran on the companion itself.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing as mp
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from playwright.sync_api import TimeoutError as PageTimeout

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bridge_throughput import encoded_raw_imu  # noqa: E402

from bridge.wire.mav import mavlink  # noqa: E402
from hil.sitl import free_udp_port  # noqa: E402

RATE_HZ = 1000.0
#: The browsers open and start drawing within PRIME_S (five pages on one busy core take
#: up to ~25 s to build); the last MEASURE_S are measured.
PRIME_S, MEASURE_S = 35.0, 10.0
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]


BRIDGE_CPU, OTHERS_CPU = 0, 1
START_US = 1_000_000  # the first sample's board time (benchmarks/bridge_throughput.py)


def _sender(port: int, n: int, result: mp.Queue, cpu: int | None) -> None:
    """Send n RAW_IMU at RATE_HZ, sleeping between packets; the latency of each
    ATTITUDE_QUATERNION that comes back, by the sample it answers (its time_boot_ms)."""
    if cpu is not None:
        with contextlib.suppress(AttributeError, OSError):
            os.sched_setaffinity(0, {cpu})
        with contextlib.suppress(AttributeError, OSError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
    packets = encoded_raw_imu(n, RATE_HZ, start_us=START_US)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    parser = mavlink.MAVLink(None, 0, 0)
    sent = np.full(n, np.nan)
    back = np.full(n, np.nan)
    step_ms = 1e3 / RATE_HZ

    def drain() -> None:
        while True:
            try:
                data = sock.recv(65536)
            except BlockingIOError:
                return
            now = time.perf_counter()
            for m in parser.parse_buffer(data) or ():
                if m.get_type() == "ATTITUDE_QUATERNION":
                    i = round((m.time_boot_ms - START_US / 1e3) / step_ms)
                    if 0 <= i < n and np.isnan(back[i]):
                        back[i] = now

    period = 1.0 / RATE_HZ
    t0 = time.perf_counter()
    for i in range(n):
        due = t0 + i * period
        while (now := time.perf_counter()) < due:
            if select.select([sock], [], [], due - now)[0]:
                drain()
        sent[i] = time.perf_counter()
        sock.sendto(packets[i], ("127.0.0.1", port))
    end = time.perf_counter() + 1.0
    while (now := time.perf_counter()) < end:
        if select.select([sock], [], [], end - now)[0]:
            drain()
    result.put({"latency_s": (back - sent).tolist()})


def _status(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return {}


def one_run(browser, viewers: int, folder: Path, shared: bool,
            elsewhere: str | None = None) -> dict:
    """One bridge, ``viewers`` pages on it (or on the bridge at ``elsewhere``)."""
    port = free_udp_port()
    status = folder / f"status_{port}.json"
    pin = [] if shared else ["taskset", "-c", str(BRIDGE_CPU)]
    bridge = subprocess.Popen(
        [*pin, sys.executable, "-m", "bridge.app.cli", "run", "--connect",
         f"udpin:127.0.0.1:{port}", "--web", "127.0.0.1:0", "--status-file", str(status),
         "--out-rate", "0", "--imu-rate", str(RATE_HZ), "-e", "eskf", "-e", "mahony",
         "-e", "madgwick", "-q"], stdout=subprocess.DEVNULL)
    contexts = []
    launched = time.monotonic()
    try:
        end = time.monotonic() + 60
        while not _status(status).get("connection", {}).get("web"):
            if bridge.poll() is not None or time.monotonic() > end:
                raise SystemExit(f"the bridge did not start (exit {bridge.poll()})")
            time.sleep(0.1)
        url = elsewhere or _status(status)["connection"]["web"]["url"]
        for _ in range(viewers):  # loaded before the data comes: BokehJS parsed, waiting
            context = browser.new_context(viewport={"width": 1200, "height": 1400})
            page = context.new_page()
            page.goto(url)
            page.wait_for_selector("#connection:text('live')", timeout=30000)
            contexts.append((context, page))
        result: mp.Queue = mp.get_context("spawn").Queue()
        n = int((PRIME_S + MEASURE_S) * RATE_HZ)
        sender = mp.get_context("spawn").Process(
            target=_sender, args=(port, n, result, None if shared else OTHERS_CPU))
        started = time.monotonic()
        sender.start()
        drawing = 0  # pages showing the vehicle by the end of PRIME_S (five pages on one
        for _, page in contexts:  # busy core may not be: they are measured open anyway)
            left_ms = max(1.0, (started + PRIME_S - time.monotonic()) * 1e3)
            try:
                page.wait_for_selector("section.vehicle canvas", timeout=left_ms)
                drawing += 1
            except PageTimeout:
                pass
        ready_s = time.monotonic() - started if drawing == len(contexts) else None
        out = result.get(timeout=PRIME_S + MEASURE_S + 60)
        sender.join()
        frames = [p.evaluate("window.attitudeView.frames") for _, p in contexts]
        st = _status(status)
        up_s = time.monotonic() - launched
    finally:
        for context, _ in contexts:
            context.close()
        bridge.send_signal(signal.SIGINT)
        bridge.wait(timeout=30)
    lat = np.array(out["latency_s"][-int(MEASURE_S * RATE_HZ):]) * 1e3
    lost = int(np.isnan(lat).sum())
    lat = lat[np.isfinite(lat)]
    vehicle = next(iter(st.get("vehicles", {}).values()), {})
    return {"viewers": viewers, "on": "another bridge" if elsewhere else "this bridge",
            "received": int(lat.size), "unanswered": lost,
            "p50_ms": float(np.percentile(lat, 50)), "p99_ms": float(np.percentile(lat, 99)),
            "max_ms": float(lat.max()),
            "in_bridge_p99_ms": vehicle.get("latency_ms", {}).get("p99"),
            "frames_dropped": st.get("connection", {}).get("web", {}).get("frames_dropped"),
            # the view's own time on the bridge's event loop, per second of the run
            "view_work_ms_per_s": round(st.get("connection", {}).get("web", {})
                                        .get("work_ms", 0.0) / up_s, 3),
            "frames_seen_by_pages": frames, "pages_drawing": drawing,
            "pages_drawing_after_s": None if ready_s is None else round(ready_s, 1)}


def _decoy_bridge(folder: Path, shared: bool) -> tuple[subprocess.Popen, str]:
    """Another bridge (built-in emulator) on the browsers' core: five pages drawing it
    load the machine as five viewers do, without any work for the measured bridge."""
    status = folder / "decoy.json"
    pin = [] if shared else ["taskset", "-c", str(OTHERS_CPU)]
    proc = subprocess.Popen([*pin, sys.executable, "-m", "bridge.app.cli", "run", "--web",
                             "127.0.0.1:0", "--status-file", str(status), "-e", "eskf", "-e",
                             "mahony", "-e", "madgwick", "-q"], stdout=subprocess.DEVNULL)
    end = time.monotonic() + 60
    while not (url := _status(status).get("connection", {}).get("web", {}).get("url")):
        if proc.poll() is not None or time.monotonic() > end:
            raise SystemExit("the decoy bridge did not start")
        time.sleep(0.1)
    return proc, url


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--shared", action="store_true",
                        help="no pinning: the browsers share the bridge's cores")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    chromium = os.environ.get("CHROMIUM", "/usr/bin/chromium")
    if not args.shared:  # the browsers (launched from here) on the other core
        os.sched_setaffinity(0, {OTHERS_CPU})
    conditions = (("none", 0, False), ("1 viewer", 1, False), ("5 viewers", 5, False),
                  ("5 viewers of another bridge", 5, True))
    runs = []
    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as p:
        decoy = _decoy_bridge(Path(tmp), args.shared)
        browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
        try:
            for r in range(args.rounds):
                for name, viewers, elsewhere in conditions:
                    run = one_run(browser, viewers, Path(tmp), args.shared,
                                  decoy[1] if elsewhere else None)
                    run.update(condition=name, round=r)
                    runs.append(run)
                    print(json.dumps(run), flush=True)
        finally:
            browser.close()
            decoy[0].send_signal(signal.SIGINT)
            decoy[0].wait(timeout=30)
    summary = {}
    for name, _, _ in conditions:
        mine = [r for r in runs if r["condition"] == name]
        p99 = [r["p99_ms"] for r in mine]
        summary[name] = {"p99_ms_runs": [round(x, 3) for x in p99],
                         "p99_ms_median": round(float(np.median(p99)), 3),
                         "p50_ms_median": round(float(np.median([r["p50_ms"] for r in mine])),
                                                3)}
    base = summary["none"]["p99_ms_median"]
    for name, _, _ in conditions[1:]:
        summary[name]["p99_vs_none"] = round(summary[name]["p99_ms_median"] / base, 3)
    for name, _, _ in conditions:
        mine = [r for r in runs if r["condition"] == name]
        summary[name]["in_bridge_p99_ms_runs"] = [r["in_bridge_p99_ms"] for r in mine]
        summary[name]["view_work_ms_per_s_median"] = round(float(np.median(
            [r["view_work_ms_per_s"] for r in mine])), 3)
    # The same machine load, with and without work for this bridge: the five pages draw
    # in both, watching this bridge or another one (round by round).
    same = [a["p99_ms"] / b["p99_ms"] for a, b in zip(
        (r for r in runs if r["condition"] == "5 viewers"),
        (r for r in runs if r["condition"] == "5 viewers of another bridge"), strict=True)]
    summary["5 viewers"]["p99_vs_same_load_runs"] = [round(x, 3) for x in same]
    summary["5 viewers"]["p99_vs_same_load_median"] = round(float(np.median(same)), 3)
    report = {"rate_hz": RATE_HZ, "measure_s": MEASURE_S, "shared_cores": args.shared,
              "summary": summary, "runs": runs}
    print(json.dumps(summary, indent=2))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
