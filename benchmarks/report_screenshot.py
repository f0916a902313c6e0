"""Render a replay report in headless Chromium and check that the plots were drawn.

    python benchmarks/report_screenshot.py [LOG] [--out report.png]

Writes the interactive report of LOG (default: the PX4 SIH box flight) to a temporary
folder, opens it offline in Debian's ``chromium`` (``apt-get install chromium``) with
networking disabled, saves a screenshot and counts what the canvases drew: the
estimator colours (Bokeh's Category10) and the black reference line must be there,
which only happens if the inlined BokehJS ran. Exit code 1 when they are not.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

DEFAULT_LOG = ROOT.parent / "shared" / "data" / "px4_sih" / "sih_box.tlog"
WIDTH, HEIGHT = 1100, 2600
CATEGORY10 = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728")  # the first four estimators


def screenshot(html: Path, png: Path, profile: Path) -> None:
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        raise SystemExit("chromium not found: apt-get install chromium")
    cmd = [browser, "--headless", "--no-sandbox", "--disable-gpu",
           "--disable-background-networking", "--no-first-run", "--hide-scrollbars",
           f"--user-data-dir={profile}", f"--window-size={WIDTH},{HEIGHT}",
           "--virtual-time-budget=20000", f"--screenshot={png}", html.as_uri()]
    subprocess.run(cmd, check=True, capture_output=True, timeout=180)


def colour_pixels(img: np.ndarray, hex_colour: str, tol: int = 40) -> int:
    rgb = np.array([int(hex_colour[i:i + 2], 16) for i in (1, 3, 5)])
    return int(np.count_nonzero(np.all(np.abs(img[..., :3].astype(int) - rgb) < tol, axis=-1)))


def main() -> int:
    from matplotlib.image import imread

    from replay import evaluate, load
    from replay.report import write_report

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", nargs="?", type=Path, default=DEFAULT_LOG)
    ap.add_argument("--out", type=Path, default=Path("report_screenshot.png"))
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        html = write_report([evaluate(load(args.log))], Path(tmp) / "report.html")
        screenshot(html, args.out.resolve(), Path(tmp) / "profile")
    img = (imread(args.out) * 255).astype(np.uint8)
    counts = {c: colour_pixels(img, c) for c in CATEGORY10}
    black = colour_pixels(img, "#000000", tol=30)
    print(f"screenshot {args.out}: {img.shape[1]}x{img.shape[0]} px; estimator colours "
          + ", ".join(f"{c} {n}" for c, n in counts.items()) + f"; reference/text black {black}")
    rendered = all(n > 500 for n in counts.values())
    print("plots rendered" if rendered else "PLOTS NOT RENDERED")
    return 0 if rendered else 1


if __name__ == "__main__":
    raise SystemExit(main())
