"""CPU time of one status tick's live comparison (no sockets).

    python benchmarks/status_cost.py [--estimators 3] [--rate 250]

Every status tick the bridge scores each estimator against the truth and the vehicle's
own attitude over the last 10 s (``bridge.estimate.compare``: a search over 101 and 151
time shifts), and the vehicle's own against the truth. This fills the rings with 10 s
of a turning flight (truth and estimates at the IMU rate, the vehicle's own at 50 Hz)
and times ``compare_all`` + ``vehicle_against_truth`` (best and median of several
repeats, one core, to be robust to a shared machine).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bridge.estimate.compare import compare_all, vehicle_against_truth
from bridge.vehicle.references import TRUTH, VEHICLE, References
from bridge.vehicle.ring import TimeRing
from estimators import quat as Q

WINDOW_S = 10.0
REPEATS = 15


def attitudes(t: np.ndarray, lag_s: float, noise_rad: float, seed: int) -> np.ndarray:
    """A turning, tilting flight's attitude at t - lag, with a little noise."""
    rng = np.random.default_rng(seed)
    tt = t - lag_s
    q = Q.from_euler(0.3 * np.sin(1.3 * tt), 0.2 * np.sin(0.9 * tt + 1.0), 2.0 * np.sin(0.4 * tt))
    return Q.normalize(q + noise_rad * rng.standard_normal(q.shape))


def filled(n_estimators: int, rate_hz: float) -> tuple[References, dict[str, TimeRing]]:
    t = np.arange(0.0, WINDOW_S + 1.0, 1.0 / rate_hz)
    refs = References()
    for ti, qi in zip(t, attitudes(t, 0.0, 0.0, 0), strict=True):
        refs.series[TRUTH].push(float(ti), qi)
    t_own = np.arange(0.0, WINDOW_S + 1.0, 0.02)
    for ti, qi in zip(t_own, attitudes(t_own, 0.01, 0.003, 1), strict=True):
        refs.series[VEHICLE].push(float(ti), qi)
    history = {}
    for k in range(n_estimators):
        ring = TimeRing(len(t) + 10, 4)
        for ti, qi in zip(t, attitudes(t, 0.004 * (k + 1), 0.002, 2 + k), strict=True):
            ring.push(float(ti), qi)
        history[f"est{k}"] = ring
    return refs, history


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--estimators", type=int, default=3)
    ap.add_argument("--rate", type=float, default=250.0, help="IMU and truth rate [Hz]")
    args = ap.parse_args()
    refs, history = filled(args.estimators, args.rate)
    compare_all(history, refs, WINDOW_S)  # compile / warm caches
    vehicle_against_truth(refs, WINDOW_S)
    taken = []
    for _ in range(REPEATS):
        start = time.process_time()
        compare_all(history, refs, WINDOW_S)
        vehicle_against_truth(refs, WINDOW_S)
        taken.append(time.process_time() - start)
    print(f"live comparison, {args.estimators} estimators x (truth, vehicle) + vehicle vs "
          f"truth, {WINDOW_S:g} s window at {args.rate:g} Hz: "
          f"{1e3 * min(taken):.1f} ms CPU per status tick (median "
          f"{1e3 * statistics.median(taken):.1f} ms)")


if __name__ == "__main__":
    main()
