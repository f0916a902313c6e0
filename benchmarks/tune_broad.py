"""Speed of `tune`: a 100-point Mahony grid (kp x ki, 10 x 10) over the 9 BROAD trials.

Loads the trials once, sweeps with ``--jobs`` processes and reports the wall time of the
sweep (loading and the one-off numba compile excluded, printed separately), the best
shared parameter set and its per-trial errors. Writes the heatmap.

    PYTHONPATH=. python3 benchmarks/tune_broad.py [--jobs 2] [--out docs/broad_mahony_sweep.png]

The same run from the command line (includes loading):
    attitude-bridge tune ../shared/data/broad/*.npz -e mahony -p kp=0.1:2:10 -p ki=0:0.01:10 -j 2
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from replay.evaluate import prepare
from replay.figures import save_png, sweep_figure
from replay.readers import load
from replay.tune import ParamAxis, sweep

DATA = Path(os.environ.get("ATTITUDE_BRIDGE_DATA",
                           Path(__file__).resolve().parents[2] / "shared" / "data"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--estimator", default="mahony")
    ap.add_argument("--out", type=Path, default=Path("docs/broad_mahony_sweep.png"))
    args = ap.parse_args()
    files = sorted((DATA / "broad").glob("*.npz"))
    began = time.perf_counter()
    prepared = [prepare(load(f)) for f in files]
    samples = sum(p.recording.n for p in prepared)
    loaded = time.perf_counter()
    axes = [ParamAxis("kp", np.linspace(0.1, 2.0, 10)), ParamAxis("ki", np.linspace(0, 0.01, 10))]
    result = sweep(prepared, args.estimator, axes, jobs=args.jobs, progress=True)
    print(f"{len(files)} trials, {samples} samples, loaded in {loaded - began:.1f} s")
    print(f"{len(result.points)} parameter sets x {len(files)} trials on {args.jobs} process(es): "
          f"{result.seconds:.1f} s wall "
          f"({len(result.points) * samples / result.seconds / 1e6:.2f} M samples/s scored)")
    i = result.best_index
    print(f"best {result.best}: mean total {result.mean_total[i]:.3f} deg")
    for f, total in zip(files, result.total[i], strict=True):
        print(f"  {f.name}: {total:.3f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_png(sweep_figure(result), args.out)
    print(f"heatmap: {args.out}")


if __name__ == "__main__":
    main()
