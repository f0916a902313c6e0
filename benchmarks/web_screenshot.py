"""The web view's picture in the docs: a bridge with the built-in emulator, watched by
headless Chromium, after it has flown a while.

    python benchmarks/web_screenshot.py [--out docs/web_view.png] [--seconds 25]

Starts `attitude-bridge run --web 127.0.0.1:0` (emulator as a PX4 with a GPS: aiding,
the autopilot's own attitude and the simulator's truth all shown), opens the page in
Debian's chromium through Playwright, waits, and saves a full-page screenshot. Exit
code 1 if the page reported an error or showed no vehicle.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "web_view.png")
    parser.add_argument("--seconds", type=float, default=25.0)
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as tmp:
        status = Path(tmp) / "status.json"
        bridge = subprocess.Popen(
            [sys.executable, "-m", "bridge.app.cli", "run", "--web", "127.0.0.1:0",
             "--status-file", str(status), "--emulator-autopilot", "px4", "--emulator-gps",
             "-e", "eskf", "-e", "mahony", "-e", "madgwick", "-q"],
            cwd=ROOT, stdout=subprocess.DEVNULL)
        try:
            url = None
            end = time.monotonic() + 60
            while url is None and time.monotonic() < end and bridge.poll() is None:
                try:
                    url = json.loads(status.read_text())["connection"]["web"]["url"]
                except (FileNotFoundError, json.JSONDecodeError, KeyError):
                    time.sleep(0.2)
            if url is None:
                print("the bridge did not start", file=sys.stderr)
                return 1
            with sync_playwright() as p:
                browser = p.chromium.launch(
                    executable_path=os.environ.get("CHROMIUM", "/usr/bin/chromium"),
                    args=CHROMIUM_ARGS)
                page = browser.new_page(viewport={"width": 1200, "height": 1300})
                problems: list[str] = []
                page.on("console", lambda m: problems.append(m.text)
                        if m.type == "error" else None)
                page.on("pageerror", lambda e: problems.append(str(e)))
                page.goto(url)
                time.sleep(args.seconds)
                vehicles = page.locator("section.vehicle").count()
                page.screenshot(path=str(args.out), full_page=True)
                browser.close()
        finally:
            bridge.send_signal(signal.SIGINT)
            bridge.wait(timeout=30)
    print(f"{args.out}: {vehicles} vehicle(s) shown, {len(problems)} page error(s)")
    for problem in problems:
        print(f"  {problem}")
    return 0 if vehicles and not problems else 1


if __name__ == "__main__":
    sys.exit(main())
