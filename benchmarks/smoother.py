"""The smoother (``estimators.smooth``, ``replay --smooth``) against the online eskf, VQF
online and offline, and the autopilot's own attitude, on the dev recordings.

    python benchmarks/smoother.py [--json out.json]      # about 3 minutes

* **BROAD** (9 dev trials): leave-one-trial-out over a small grid of the eskf's noise
  parameters (below), chosen for the smoothed and, separately, for the online filter:
  each trial scored with the point chosen on the other 8 (lowest mean total), i.e.
  *cross-validated*; beside them the defaults (in-sample: they were chosen on these
  trials) and VQF 2.x online and offline (defaults).
* **PX4 SIH** flights (``../shared/data/px4_sih`` and ``tests/data/sitl``), every phase
  scored (whole recordings, and the worst phase): eskf online and smoothed with the
  defaults (chosen looking at these flights: in-sample), PX4's own attitude.
* A diagnostic, not a score: BROAD's inclination against the truth taken
  ``TRUTH_EARLIER_MS`` earlier (the IMU's clock against the optical system's; on the
  fast trials every filter matches that truth better), for the smoothed defaults and
  VQF offline: how much of the worst trial is the recordings' timing.

The smoother runs the same model with the same parameters as the online filter; nothing
is tuned for it except by the leave-one-out here.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.accuracy import DATA, REPO, Trial, broad_trials, sitl_trials, vqf_rows
from estimators import smooth
from estimators.metrics import rms_errors
from replay.align import earlier_on_grid

GRID: dict[str, tuple[float, ...]] = {
    "mag_noise": (0.15, 0.25, 0.4),
    "gyro_noise": (0.005, 0.008, 0.012),
    "gyro_rate_noise": (0.001, 0.002, 0.004),
    "velocity_rw": (0.1, 0.3),
    "mag_delay": (0.0, 0.005, 0.01),
}


#: How much earlier the diagnostic takes BROAD's truth [ms].
TRUTH_EARLIER_MS = 2.0


def smoothed(trial: Trial, **params: float):
    run = trial.runs[0]
    return smooth("eskf", trial.gyr, trial.acc, trial.mag, rate_hz=trial.rate_hz,
                  world=trial.world, dt=trial.dt, declination=trial.declination,
                  vel=run.vel, vel_age=run.vel_age, airborne=trial.airborne,
                  imu_delay=trial.imu_delay,
                  **{**run.params, **params})


def leave_one_out(scores: np.ndarray) -> np.ndarray:
    """scores (points, trials, 2: total, inclination) -> (trials, 2): each trial scored
    with the point of lowest mean total over the other trials."""
    n = scores.shape[1]
    out = np.empty((n, 2))
    for j in range(n):
        others = [k for k in range(n) if k != j]
        best = int(np.argmin(scores[:, others, 0].mean(axis=1)))
        out[j] = scores[best, j]
    return out


def broad_part(doc: dict) -> dict[str, np.ndarray]:
    trials = broad_trials(DATA / "broad")
    points = [dict(zip(GRID, v, strict=True)) for v in itertools.product(*GRID.values())]
    on = np.empty((len(points), len(trials), 2))
    sm = np.empty_like(on)
    for i, p in enumerate(points):
        for j, t in enumerate(trials):
            res = smoothed(t, **p)
            e_on, e_sm = t.score(res.online.q), t.score(res.q)
            on[i, j] = e_on.total_deg, e_on.inclination_deg
            sm[i, j] = e_sm.total_deg, e_sm.inclination_deg
    rows: dict[str, np.ndarray] = {"eskf smoothed, cross-validated": leave_one_out(sm),
                                   "eskf online, cross-validated": leave_one_out(on)}
    defaults = [smoothed(t) for t in trials]
    rows["eskf smoothed, defaults (in-sample)"] = np.array(
        [[t.score(r.q).total_deg, t.score(r.q).inclination_deg]
         for t, r in zip(trials, defaults, strict=True)])
    rows["eskf online, defaults (in-sample)"] = np.array(
        [[t.score(r.online.q).total_deg, t.score(r.online.q).inclination_deg]
         for t, r in zip(trials, defaults, strict=True)])
    for name in ("vqf online", "vqf offline"):
        rows[name] = np.array([[t.score(vqf_rows(t)[name]).total_deg,
                                t.score(vqf_rows(t)[name]).inclination_deg] for t in trials])
    timing = {}
    for label, qs in (("eskf smoothed, defaults", [r.q for r in defaults]),
                      ("vqf offline", [vqf_rows(t)["vqf offline"] for t in trials])):
        timing[label] = []
        for t, q in zip(trials, qs, strict=True):
            truth = earlier_on_grid(t.truth, t.rate_hz, TRUTH_EARLIER_MS / 1000.0)
            ok = t.scored & np.all(np.isfinite(truth), axis=1)
            timing[label].append(rms_errors(q[ok], truth[ok]).inclination_deg)
    print("BROAD dev trials: total / inclination RMS [deg]; mean, worst trial")
    print(f"{'':38s}" + "".join(f"{t.name:>12s}" for t in trials) + "   mean total  worst incl")
    for label, v in rows.items():
        print(f"{label:38s}" + "".join(f"{a:6.2f}/{b:5.2f}" for a, b in v)
              + f"   {v[:, 0].mean():10.3f}  {v[:, 1].max():10.3f}")
        doc["broad"][label] = {"per_trial": {t.name: list(map(float, x))
                                             for t, x in zip(trials, v, strict=True)},
                               "mean_total_deg": float(v[:, 0].mean()),
                               "worst_inclination_deg": float(v[:, 1].max())}
    print(f"diagnostic, not a score: inclination against the truth {TRUTH_EARLIER_MS:g} ms "
          f"earlier")
    for label, v in timing.items():
        print(f"{label:38s}" + "".join(f"{x:12.2f}" for x in v) + f"   {'':10s}  {max(v):10.3f}")
    doc["broad"]["inclination_vs_truth_earlier"] = {
        "ms": TRUTH_EARLIER_MS, **{label: dict(zip((t.name for t in trials), v, strict=True))
                                   for label, v in timing.items()}}
    return rows


def flights_part(doc: dict) -> list[tuple[str, dict]]:
    trials = sitl_trials([DATA / "px4_sih", REPO / "tests" / "data" / "sitl"])
    out = []
    print("\nPX4 / ArduPilot SITL flights, whole recordings (worst phase): total / "
          "inclination [deg]")
    for t in (t for t in trials if t.name.startswith("px4")):
        res = smoothed(t)
        cells = {}
        for label, q in (("online", res.online.q), ("smoothed", res.q),
                         ("autopilot", t.autopilot)):
            e = t.score(q)
            phases = t.phase_scores(q)
            worst = max(phases.items(), key=lambda kv: kv[1].total_deg) if phases else None
            cells[label] = {"total_deg": e.total_deg, "inclination_deg": e.inclination_deg,
                            "worst_phase": None if worst is None else
                            [worst[0], worst[1].total_deg]}
        ratio = cells["smoothed"]["total_deg"] / cells["autopilot"]["total_deg"]
        cells["smoothed_vs_autopilot"] = ratio
        print(f"  {t.name:14s}" + "  ".join(
            f"{k} {c['total_deg']:.3f}/{c['inclination_deg']:.3f} ({c['worst_phase'][0]} "
            f"{c['worst_phase'][1]:.2f})" for k, c in cells.items() if isinstance(c, dict))
            + f"  smoothed/PX4 {ratio:.2f}")
        doc["flights"][t.name] = cells
        out.append((t.name, cells))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, help="write the numbers as JSON")
    args = ap.parse_args(argv)
    began = time.perf_counter()
    doc: dict = {"grid": GRID, "broad": {}, "flights": {}}
    rows = broad_part(doc)
    flights = flights_part(doc)
    sm, on = rows["eskf smoothed, cross-validated"], rows["eskf online, cross-validated"]
    vqf_off = rows["vqf offline"]
    crit = [
        ("BROAD smoothed mean total <= 0.85x eskf online (both cross-validated)",
         sm[:, 0].mean(), 0.85 * on[:, 0].mean()),
        ("BROAD smoothed mean total <= 0.8x VQF offline",
         sm[:, 0].mean(), 0.8 * vqf_off[:, 0].mean()),
        ("BROAD smoothed worst-trial inclination <= VQF offline's worst",
         sm[:, 1].max(), vqf_off[:, 1].max()),
    ] + [(f"{name}: smoothed total <= 0.7x PX4's own", c["smoothed"]["total_deg"],
          0.7 * c["autopilot"]["total_deg"]) for name, c in flights
         if name in ("px4-agg", "px4-box")]
    print("\ncriteria (issue 21):")
    for text, got, bound in crit:
        print(f"  {'met    ' if got <= bound else 'NOT MET'} {text}: {got:.3f} vs {bound:.3f}")
    doc["criteria"] = [{"criterion": c, "measured": g, "bound": b, "met": bool(g <= b)}
                       for c, g, b in crit]
    print(f"{time.perf_counter() - began:.0f} s")
    if args.json:
        args.json.write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
