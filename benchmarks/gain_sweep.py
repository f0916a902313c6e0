"""The seed paper's finding on emulator data: complementary-filter gains too small lag
behind, too large oscillate and pass noise through.

Runs the HIL emulator (``hil.simulate``, profile ``flight`` by default) and sweeps Mahony's
``kp`` (ki = 0) over a log grid. For each gain it measures, against the emulator's truth:
total RMSE, how long the filter takes to pull a 30° initial roll error down by 1/e
(its time constant, ideally 1/kp: the "lags behind" side) and the high-frequency part
of the error (RMS of the error minus its 0.5 s moving average: the "passes noise
through" side). Writes a PNG.

    PYTHONPATH=. python3 benchmarks/gain_sweep.py [--out docs/gain_sweep.png]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import estimators
from estimators import metrics
from estimators import quat as Q
from replay.align import estimate_lag
from replay.emulator import simulate
from replay.evaluate import EstimatorSpec, prepare, run_estimator
from replay.figures import save_png

INITIAL_ROLL_ERROR_DEG = 30.0
SETTLED_DEG = INITIAL_ROLL_ERROR_DEG / np.e  # one time constant of the correction
HF_WINDOW_S = 0.5


def moving_average(x: np.ndarray, n: int) -> np.ndarray:
    return np.convolve(x, np.ones(n) / n, mode="same")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="flight")
    ap.add_argument("--rate", type=float, default=250.0)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("docs/gain_sweep.png"))
    args = ap.parse_args()

    began = time.perf_counter()
    rec = simulate(args.profile, args.rate, args.duration, args.seed)
    prep = prepare(rec)
    q_true = prep.q_ref
    # Start every filter 30° off in roll, so the slow side shows as slow convergence.
    q0 = Q.multiply(q_true[0], Q.from_euler(np.radians(INITIAL_ROLL_ERROR_DEG), 0.0, 0.0))
    gains = np.geomspace(0.01, 30.0, 25)
    n_hf = max(3, round(HF_WINDOW_S * rec.rate_hz))
    rows, series = [], {}
    for kp in gains:
        spec = EstimatorSpec("mahony", {"kp": float(kp), "ki": 0.0})
        run = run_estimator(prep, spec)  # from the first sample, as replay does
        est = estimators.create("mahony", rate_hz=rec.rate_hz, world="NED", q0=q0,
                                kp=float(kp), ki=0.0)
        res = est.run(rec.gyr, rec.acc, rec.mag, dt=rec.dt)
        err = np.degrees(metrics.attitude_errors(res.q, q_true).total)
        settled = np.flatnonzero(err < SETTLED_DEG)
        t_settle = rec.t[settled[0]] - rec.t[0] if settled.size else np.nan
        e_run = np.degrees(metrics.attitude_errors(run.q, q_true).total)
        hf = e_run - moving_average(e_run, n_hf)
        core = slice(n_hf, -n_hf)
        rms = metrics.rms_errors(run.q, q_true)
        lag = estimate_lag(rec.t, run.q, q_true, max_lag_s=3.0)
        rows.append((kp, rms.total_deg, t_settle, float(np.sqrt(np.mean(hf[core] ** 2))), lag))
        series[kp] = np.degrees(Q.to_euler(run.q))
    table = np.array(rows)
    best = int(np.nanargmin(table[:, 1]))
    print(f"emulator {args.profile}, {rec.n} samples at {rec.rate_hz:.0f} Hz, "
          f"{len(gains)} gains in {time.perf_counter() - began:.1f} s")
    print(f"{'kp':>8} {'total_deg':>10} {'settle_s':>9} {'hf_noise_deg':>12} {'lag_s':>7}")
    for kp, total, settle, hf, lag in table:
        print(f"{kp:8.3f} {total:10.3f} {settle:9.2f} {hf:12.4f} {lag:7.3f}")
    print(f"best kp = {table[best, 0]:.3f} ({table[best, 1]:.3f} deg)")

    fig, (ax1, ax3) = plt.subplots(2, 1, figsize=(10, 9.5), height_ratios=(1.2, 1))
    ax1.loglog(table[:, 0], table[:, 1], "o-", color="C0", label="total RMSE [deg]")
    ax1.loglog(table[:, 0], table[:, 3], "s--", color="C2",
               label=f"high-frequency error (> 1/{HF_WINDOW_S:g} s) [deg]")
    ax1.set_xlabel("Mahony kp [rad/s per unit error]")
    ax1.set_ylabel("error [deg]")
    ax2 = ax1.twinx()
    ax2.loglog(table[:, 0], table[:, 2], "^:", color="C3",
               label=f"time constant: {INITIAL_ROLL_ERROR_DEG:g}° initial error below "
                     f"{SETTLED_DEG:.1f}° [s]")
    ax2.loglog(table[:, 0], 1.0 / table[:, 0], color="C3", lw=0.6, alpha=0.6,
               label="1/kp (ideal time constant) [s]")
    ax2.set_ylabel("convergence time [s]", color="C3")
    ax1.axvline(table[best, 0], color="0.5", lw=0.8)
    lines = ax1.get_legend_handles_labels()
    lines2 = ax2.get_legend_handles_labels()
    ax1.legend(lines[0] + lines2[0], lines[1] + lines2[1], fontsize=8, loc="upper center",
               bbox_to_anchor=(0.5, -0.14), ncol=2)
    ax1.set_title(f"Gain sweep on emulator data ({args.profile}, {rec.rate_hz:.0f} Hz): "
                  "too small lags behind, too large passes noise through")
    ax1.grid(alpha=0.3, which="both")

    t = rec.t - rec.t[0]
    window = (t > 0.4 * args.duration) & (t < 0.4 * args.duration + 6.0)
    truth = np.degrees(Q.to_euler(q_true))
    ax3.plot(t[window], truth[window, 1], color="black", lw=2, label="truth")
    for kp, style in ((gains[2], "C1"), (table[best, 0], "C0"), (gains[-1], "C2")):
        ax3.plot(t[window], series[kp][window, 1], color=style, lw=0.9, label=f"kp={kp:.3g}")
    ax3.set_xlabel("time [s]")
    ax3.set_ylabel("pitch [deg]")
    ax3.legend(fontsize=8)
    ax3.grid(alpha=0.3)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_png(fig, args.out)
    print(f"figure: {args.out}")


if __name__ == "__main__":
    main()
