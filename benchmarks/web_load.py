"""How long the live web view takes to show a vehicle: from opening the URL in a fresh
browser tab to the vehicle's first plot drawn.

    python benchmarks/web_load.py [--loads 10] [--busy 0] [--json out.json]

One bridge as a user starts it (``attitude-bridge run --web 127.0.0.1:0 -e eskf -e
mahony``, the built-in emulator as the source, as ``tests/test_bridge_web.py`` runs it),
and Debian's headless Chromium driven by Playwright. Each load is a new browser context
(no cache, no cookies) whose blank tab is open before the clock starts: the browser's
own start-up is not the page's. The clock stops when the vehicle's section has a
canvas (BokehJS parsed, the first frame drawn). ``--busy N`` runs N busy loops beside
it, for a machine that is doing other work (the test suite's three workers on two
cores are about that). Prints each load's time, the median and the worst.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from web_latency import CHROMIUM_ARGS  # noqa: E402

VEHICLE_PLOT = 'section[data-sysid="1"] canvas'


def _busy() -> None:
    while True:
        pass


def _status(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _serving(status: Path, bridge: subprocess.Popen) -> str:
    """The web view's URL once the bridge compares its vehicle with the truth."""
    end = time.monotonic() + 90.0
    while time.monotonic() < end:
        st = _status(status)
        url = st.get("connection", {}).get("web", {}).get("url")
        if url and st.get("vehicles", {}).get("1", {}).get("compare", {}).get("truth"):
            return url
        if bridge.poll() is not None:
            break
        time.sleep(0.2)
    raise SystemExit(f"web_load: the bridge did not serve a vehicle (exit {bridge.poll()})")


def page_loads(url: str, loads: int) -> list[float]:
    """Seconds from opening ``url`` to the vehicle's first plot, one per fresh context."""
    from playwright.sync_api import sync_playwright

    chromium = os.environ.get("CHROMIUM", "/usr/bin/chromium")
    times = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
        try:
            for _ in range(loads):
                context = browser.new_context(viewport={"width": 1200, "height": 1400})
                page = context.new_page()
                page.goto("about:blank")
                t0 = time.monotonic()
                page.goto(url)
                page.wait_for_selector(VEHICLE_PLOT, timeout=60000)
                times.append(time.monotonic() - t0)
                context.close()
        finally:
            browser.close()
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--loads", type=int, default=10, help="page loads (default 10)")
    ap.add_argument("--busy", type=int, default=0, help="busy loops beside it (default 0)")
    ap.add_argument("--json", type=Path, help="write the results here")
    args = ap.parse_args()
    if args.loads < 1 or args.busy < 0:
        ap.error("--loads must be at least 1 and --busy not negative")
    loops = [mp.Process(target=_busy, daemon=True) for _ in range(args.busy)]
    with tempfile.TemporaryDirectory() as tmp:
        status = Path(tmp) / "status.json"
        bridge = subprocess.Popen(
            [sys.executable, "-m", "bridge.app.cli", "run", "--web", "127.0.0.1:0",
             "--status-file", str(status), "-e", "eskf", "-e", "mahony", "-q"],
            cwd=ROOT, stdout=subprocess.DEVNULL)
        try:
            url = _serving(status, bridge)
            for loop in loops:
                loop.start()
            times = page_loads(url, args.loads)
        finally:
            for loop in loops:
                loop.terminate()
            bridge.terminate()
            bridge.wait(timeout=30)
    print("page to the vehicle's first plot [s]: " + " ".join(f"{t:.2f}" for t in times))
    print(f"median {statistics.median(times):.2f} s, worst {max(times):.2f} s over "
          f"{len(times)} loads; {args.busy} busy loop(s) beside, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.2f}")
    if args.json:
        args.json.write_text(json.dumps({"loads_s": times, "busy": args.busy,
                                         "median_s": statistics.median(times),
                                         "worst_s": max(times)}, indent=1))


if __name__ == "__main__":
    main()
