"""Speed of the emulator offline: CPU seconds per simulated minute of ``hil.simulate``.

    python benchmarks/simulate_speed.py [--profiles flight handheld_flight gentle]
                                        [--rate 1000] [--duration 60] [--repeat 3]

Each profile is simulated ``--repeat`` times (a board at ``--rate`` Hz, ``--duration``
seconds, no faults); the figure is this process's CPU time per run (the machine is
shared: wall time would add whatever else runs), printed as min / median / max. The
first run of all is a warm-up and not counted (imports, first allocations).
``--truth-ahead 0`` evaluates the motion chunk by chunk (the sampling loop before it was
evaluated a second ahead), for a side-by-side figure.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: use this checkout's emulator
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil import EmulatorConfig, simulate
from hil.source import TRUTH_AHEAD_S


def simulate_cpu_s(config: EmulatorConfig, truth_ahead_s: float) -> float:
    """CPU seconds of one offline run with a chosen lookahead."""
    start = time.process_time()
    simulate(config, truth_ahead_s)
    return time.process_time() - start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--profiles", nargs="+", default=["flight", "handheld_flight", "gentle"])
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--truth-ahead", type=float, default=TRUTH_AHEAD_S,
                    help=f"seconds of truth evaluated at once (default {TRUTH_AHEAD_S})")
    args = ap.parse_args()
    simulate_cpu_s(EmulatorConfig(profile="static", duration_s=1.0), args.truth_ahead)
    print(f"hil.simulate, {args.rate:g} Hz, {args.duration:g} s, truth ahead "
          f"{args.truth_ahead:g} s: CPU s per simulated minute (min / median / max of "
          f"{args.repeat})")
    for profile in args.profiles:
        config = EmulatorConfig(profile=profile, rate_hz=args.rate, duration_s=args.duration)
        per_minute = sorted(simulate_cpu_s(config, args.truth_ahead) * 60.0 / args.duration
                            for _ in range(args.repeat))
        print(f"  {profile:<16} {per_minute[0]:6.2f} {statistics.median(per_minute):6.2f} "
              f"{per_minute[-1]:6.2f}")


if __name__ == "__main__":
    main()
