"""Accuracy suite: every estimator and the references on real and emulated data, one table.

    python benchmarks/accuracy.py                 # tables + leave-one-trial-out of eskf
    python benchmarks/accuracy.py --quick         # smaller tuning grid, 2 emulator seeds
    python benchmarks/accuracy.py --json out.json

Trials:

* **BROAD** dev trials (9, ../shared/data/broad): a hand-held IMU with optical truth, ENU,
  started from the first sample, scored over the ``movement`` samples (the dataset's
  protocol). No aiding, no vehicle model.
* **PX4 SIH** flights (../shared/data/px4_sih): a real PX4 flying its SIH quadrotor;
  truth = HIL_STATE_QUATERNION placed by arrival, scored after take-off (climbed 1 m);
  declination from the WMM at the flight's position. Run *aided* (LOCAL_POSITION_NED
  velocity, placed by arrival with its age, as the bridge gets it), *unaided* (the
  multirotor drag model: the vehicle's HEARTBEAT says quadrotor) and *generic* (no aiding,
  no vehicle model: what a vehicle of unknown kind gets). PX4's own ATTITUDE from the
  same log is a reference row.
* **Emulator** flights (``hil`` ``flight`` profile, 120 s, seeds 1-3, 250 Hz): the GY-86
  board calibrated from its own calibration session, GPS at 5 Hz with 100 ms latency;
  aided, unaided and generic like the PX4 flights; scored after 10 s.

Reference rows: gyro integration (``quaternion``, from the true start), VQF 2.x online
and offline (9D, defaults), imufusion (defaults), PX4's ATTITUDE, and our other
estimators.

Leave-one-trial-out: the eskf noise parameters on the grid below are chosen on all
trials but one (lowest mean total error over them, each trial weighing the same; a
flight's score is the mean of its aided, unaided and generic runs; among the points
whose worst BROAD inclination over those trials stays within 1.8°) and scored on the one
left out, for each trial in turn. The table reports that held-out score, its mean and its
worst trial, beside the defaults' own scores.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: use this checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import estimators
from estimators import quat as Q
from estimators.base import G
from estimators.eskf import MULTIROTOR_DRAG_PER_S
from estimators.metrics import ErrorRms, attitude_errors, rms_errors

DATA = Path(os.environ.get("ATTITUDE_BRIDGE_DATA",
                           Path(__file__).resolve().parents[2] / "shared" / "data"))
EMULATOR_RATE_HZ = 250.0
EMULATOR_SECONDS = 120.0
EMULATOR_SETTLE_S = 10.0
TAKEOFF_CLIMB_M = 1.0

#: The grid the leave-one-trial-out tuning chooses from (eskf parameter -> values).
GRID: dict[str, tuple[float, ...]] = {
    "velocity_prior": (0.1, 0.2, 0.4),
    "velocity_rw": (0.02, 0.1),
    "mag_noise": (0.15, 0.25, 0.4),
    "gyro_noise": (0.008, 0.012, 0.018),
    "gyro_rate_noise": (0.0, 0.002, 0.003, 0.005),
    "vel_aid_noise": (0.4, 0.8),
    "velocity_scale": (0.5, 1.0),
    "velocity_scale_tau": (0.25, 0.5, 1.0),
}
#: The tuning may not buy a better mean with a worse worst case than this (issue 9).
WORST_INCLINATION_DEG = 1.8
#: Nor with a filter that a knock tilts further than this: the peak inclination after a
#: 0.2 s, 8 g sideways impact on a board held still (tests/test_eskf.py's shock scenario,
#: which no recording here contains).
KNOCK_PEAK_DEG = 2.5
QUICK_GRID: dict[str, tuple[float, ...]] = {
    "velocity_prior": (0.2,),
    "velocity_rw": (0.1,),
    "mag_noise": (0.25, 0.4),
    "gyro_noise": (0.008,),
    "gyro_rate_noise": (0.0, 0.003),
    "vel_aid_noise": (0.4, 0.8),
}


@dataclass
class Run:
    """One way of running an estimator on a trial (a flight is run aided and unaided)."""

    label: str  # "", "aided", "unaided"
    vel: np.ndarray | None = None
    vel_age: np.ndarray | None = None
    params: dict[str, float] = field(default_factory=dict)  # e.g. the multirotor model


@dataclass
class Trial:
    """Sensor samples with truth on the IMU clock and the samples that count."""

    name: str
    kind: str  # "broad" | "px4" | "emulator"
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray | None
    dt: np.ndarray
    rate_hz: float
    world: str
    truth: np.ndarray  # (N, 4), NaN where unknown
    scored: np.ndarray  # (N,) bool
    declination: float  # rad, for the estimators' output
    runs: list[Run]
    q0: np.ndarray | None = None  # start attitude for gyro integration (truth)
    autopilot: np.ndarray | None = None  # (N, 4) the vehicle's own estimate

    def score(self, q: np.ndarray) -> ErrorRms:
        return rms_errors(q[self.scored], self.truth[self.scored])


# --- loading ------------------------------------------------------------------------------
def broad_trials(folder: Path) -> list[Trial]:
    out = []
    for f in sorted(folder.glob("*.npz")):
        with np.load(f) as d:
            rate = float(d["rate"])
            n = len(d["gyr"])
            truth = np.asarray(d["quat_ref"], dtype=float)
            scored = d["movement"].astype(bool) & np.all(np.isfinite(truth), axis=1)
            out.append(Trial(f.stem.split("_")[0], "broad",
                             *(np.ascontiguousarray(d[k], dtype=float)
                               for k in ("gyr", "acc", "mag")),
                             np.full(n, 1.0 / rate), rate, "ENU", truth, scored, 0.0,
                             [Run("")]))
    return out


def _takeoff_time(t: np.ndarray, vel: np.ndarray) -> float:
    """First time the vehicle has climbed TAKEOFF_CLIMB_M (vertical velocity integrated)."""
    vz = vel[:, 2].copy()
    have = np.isfinite(vz)
    idx = np.where(have, np.arange(len(vz)), 0)
    np.maximum.accumulate(idx, out=idx)
    vz = np.where(have[idx], vz[idx], 0.0)
    climb = -np.cumsum(vz * np.gradient(t))
    above = np.flatnonzero(climb > TAKEOFF_CLIMB_M)
    return float(t[above[0]]) if above.size else float(t[0])


def px4_trials(folder: Path) -> list[Trial]:
    from replay.align import reference_at
    from replay.declination import resolve
    from replay.readers import load

    out = []
    for f in sorted(folder.glob("*.tlog")):
        rec = load(f, reference="truth")
        own = load(f, reference="autopilot").reference
        truth = reference_at(rec.reference, rec.t)
        autopilot = reference_at(own, rec.t) if own is not None else None
        v = rec.velocity
        takeoff = _takeoff_time(rec.t, v.vel)
        scored = (rec.t >= takeoff) & np.all(np.isfinite(truth), axis=1)
        first = int(np.flatnonzero(np.all(np.isfinite(truth), axis=1))[0])
        dec = resolve(rec).rad
        quad = {"drag": MULTIROTOR_DRAG_PER_S}
        runs = [Run("aided", v.vel, np.nan_to_num(v.age), quad), Run("unaided", params=quad),
                Run("generic")]
        name = f.stem.replace("sih_", "px4").replace("aggressive", "agg")
        out.append(Trial(name, "px4", rec.gyr, rec.acc, rec.mag, rec.dt, rec.rate_hz, "NED",
                         truth, scored, dec, runs, q0=truth[first], autopilot=autopilot))
    return out


def emulator_trials(seeds: tuple[int, ...]) -> list[Trial]:
    from bridge.calibrate_cli import emulator_samples
    from hil import EmulatorConfig, simulate
    from hil.config import GpsConfig
    from imu.calibration_fit import fit_calibration

    out = []
    for seed in seeds:
        gyr, acc, mag, rate = emulator_samples(seed, EMULATOR_RATE_HZ)
        cal, _ = fit_calibration(gyr, acc, mag, rate)
        cfg = EmulatorConfig(profile="flight", duration_s=EMULATOR_SECONDS, seed=seed,
                             rate_hz=EMULATOR_RATE_HZ, gps=GpsConfig())
        rec = simulate(cfg)
        vel, age = rec.gps_aiding()
        dt = np.diff(rec.time_us, prepend=rec.time_us[0] - round(1e6 / cfg.imu_rate_hz)) * 1e-6
        quad = {"drag": MULTIROTOR_DRAG_PER_S}
        out.append(Trial(f"emu-{seed}", "emulator", cal.gyro(rec.gyr), cal.accel(rec.acc),
                         cal.mag(rec.mag), dt, cfg.imu_rate_hz, "NED", rec.truth_q,
                         rec.t_s >= EMULATOR_SETTLE_S,
                         math.radians(cfg.environment.magnetic_declination_deg),
                         [Run("aided", vel, age, quad), Run("unaided", params=quad),
                          Run("generic")],
                         q0=rec.truth_q[0]))
    return out


# --- running -------------------------------------------------------------------------------
def run_estimator(trial: Trial, name: str, run: Run, **params: float) -> np.ndarray:
    q0 = trial.q0 if name in ("quaternion", "dcm", "euler") else None
    known = estimators.estimator_class(name).param_names()
    vehicle = {k: v for k, v in run.params.items() if k in known}  # e.g. eskf's drag model
    return estimators.batch(name, trial.gyr, trial.acc, trial.mag, rate_hz=trial.rate_hz,
                            world=trial.world, q0=q0, dt=trial.dt, vel=run.vel,
                            vel_age=run.vel_age, declination=trial.declination,
                            **{**vehicle, **params})


def eskf_score(trial: Trial, params: dict[str, float]) -> dict[str, ErrorRms]:
    """eskf on every run of the trial, by run label."""
    return {r.label: trial.score(run_estimator(trial, "eskf", r, **params))
            for r in trial.runs}


def _true_north(q_enu: np.ndarray, trial: Trial) -> np.ndarray:
    """A reference filter's magnetic-north ENU quaternion in the trial's world frame,
    turned to true north by the trial's declination (0 for BROAD, whose truth is
    magnetic)."""
    if trial.world == "ENU":
        return q_enu
    q = Q.ned_to_enu(q_enu)  # the NED <-> ENU swap is its own inverse
    return Q.multiply(Q.from_axis_angle(np.array([0.0, 0.0, 1.0]), trial.declination), q)


def vqf_rows(trial: Trial) -> dict[str, np.ndarray]:
    import vqf

    ts = 1.0 / trial.rate_hz
    mag = np.ascontiguousarray(np.nan_to_num(trial.mag)) if trial.mag is not None else None
    gyr, acc = np.ascontiguousarray(trial.gyr), np.ascontiguousarray(trial.acc)
    return {"vqf online": _true_north(vqf.VQF(ts).updateBatch(gyr, acc, mag)["quat9D"], trial),
            "vqf offline": _true_north(vqf.offlineVQF(gyr, acc, mag, ts)["quat9D"], trial)}


def imufusion_row(trial: Trial) -> np.ndarray:
    import imufusion

    ahrs = imufusion.Ahrs()
    settings = imufusion.AhrsSettings()
    # imufusion 1.3 ignores AhrsSettings(convention=...) given to the constructor.
    ned = trial.world == "NED"
    settings.convention = imufusion.CONVENTION_NED if ned else imufusion.CONVENTION_ENU
    settings.sample_rate = trial.rate_hz
    ahrs.set_settings(settings)
    g, a = np.degrees(trial.gyr), trial.acc / 9.80665
    mag = trial.mag if trial.mag is not None else None
    out = np.empty((len(g), 4))
    for i in range(len(g)):
        if mag is not None and np.all(np.isfinite(mag[i])):
            ahrs.update(g[i], a[i], mag[i])
        else:
            ahrs.update_no_magnetometer(g[i], a[i])
        out[i] = ahrs.get_quaternion()
    if not ned:
        return out
    return Q.multiply(Q.from_axis_angle(np.array([0.0, 0.0, 1.0]), trial.declination), out)


# --- tables --------------------------------------------------------------------------------
@dataclass
class Row:
    label: str
    cells: dict[str, ErrorRms]  # column -> errors


def columns(trials: list[Trial]) -> list[tuple[Trial, Run]]:
    return [(t, r) for t in trials for r in t.runs]


def col_name(trial: Trial, run: Run) -> str:
    return trial.name + (f"/{run.label[0]}" if run.label else "")


def reference_rows(trials: list[Trial], names: list[str]) -> list[Row]:
    rows: dict[str, Row] = {}

    def put(label: str, trial: Trial, run: Run, q: np.ndarray) -> None:
        rows.setdefault(label, Row(label, {})).cells[col_name(trial, run)] = trial.score(q)

    for trial, run in columns(trials):
        for name in names:
            put(name, trial, run, run_estimator(trial, name, run))
        if run.label == "generic":
            continue  # the same data as "unaided" for everything but eskf's vehicle model
        if run.label in ("", "unaided"):  # the references take no aiding: one column each
            for label, q in vqf_rows(trial).items():
                put(label, trial, run, q)
            put("imufusion", trial, run, imufusion_row(trial))
            if trial.autopilot is not None:
                put("PX4 ATTITUDE", trial, run, trial.autopilot)
    return list(rows.values())


def format_table(title: str, rows: list[Row], cols: list[str], metric: str) -> str:
    width = max(22, *(len(r.label) + 1 for r in rows))
    head = f"{title:<{width}}" + "".join(f"{c:>10}" for c in cols) + f"{'mean':>8}{'worst':>8}"
    lines = [head]
    for r in rows:
        vals = [getattr(r.cells[c], metric) if c in r.cells else math.nan for c in cols]
        have = [v for v in vals if math.isfinite(v)]
        mean = float(np.mean(have)) if have else math.nan
        worst = float(np.max(have)) if have else math.nan
        lines.append(f"{r.label:<{width}}" + "".join(
            f"{v:>10.2f}" if math.isfinite(v) else f"{'':>10}" for v in vals)
            + f"{mean:>8.2f}{worst:>8.2f}")
    return "\n".join(lines)


# --- leave one trial out ------------------------------------------------------------------
def grid_points(grid: dict[str, tuple[float, ...]]) -> list[dict[str, float]]:
    return [dict(zip(grid, values, strict=True)) for values in itertools.product(*grid.values())]


def trial_total(scores: dict[str, ErrorRms]) -> float:
    """One number per trial for the tuning objective: mean total over its runs."""
    return float(np.mean([s.total_deg for s in scores.values()]))


def trial_worst_inclination(scores: dict[str, ErrorRms]) -> float:
    return float(max(s.inclination_deg for s in scores.values()))


def knock_peak_inclination_deg(params: dict[str, float], rate_hz: float = 400.0) -> float:
    """Peak inclination error of eskf with ``params`` on a tilted board held still for
    12 s that takes a 0.2 s, 8 g sideways knock at 2 s (no magnetometer disturbance)."""
    n = int(12 * rate_hz)
    truth = np.tile(Q.from_euler(np.radians(15.9), np.radians(9.2), np.radians(30.0)), (n, 1))
    specific_force = np.tile([0.0, 0.0, -G], (n, 1))
    specific_force[int(2 * rate_hz):int(2.2 * rate_hz), 0] += 8.0 * G
    body = Q.conjugate(truth)
    acc = Q.rotate(body, specific_force)
    mag = Q.rotate(body, np.tile([0.21, 0.0, 0.43], (n, 1)))
    q = estimators.batch("eskf", np.zeros_like(acc), acc, mag, rate_hz=rate_hz, **params)
    return float(np.degrees(attitude_errors(q, truth).inclination).max())


def choose(totals: np.ndarray, inclinations: np.ndarray, kinds: list[str],
           knock_deg: np.ndarray | None = None) -> int:
    """The grid point with the lowest mean total over the given trials among those whose
    worst BROAD inclination stays within WORST_INCLINATION_DEG (worst-case inclination is
    a headline number, not something a good mean may buy) and whose knock peak stays
    within KNOCK_PEAK_DEG; all points if none does."""
    broad = [k == "broad" for k in kinds]
    worst = inclinations[:, broad].max(axis=1) if any(broad) else np.zeros(len(totals))
    eligible = worst <= WORST_INCLINATION_DEG
    if knock_deg is not None:
        eligible &= knock_deg <= KNOCK_PEAK_DEG
    mean = totals.mean(axis=1)
    return int(np.argmin(np.where(eligible, mean, np.inf)) if eligible.any()
               else np.argmin(mean))


def leave_one_out(trials: list[Trial], grid: dict[str, tuple[float, ...]],
                  progress: Callable[[str], None] = print
                  ) -> tuple[list[dict[str, float]], np.ndarray, list[tuple]]:
    """Scores of every grid point on every trial, and per trial the held-out result.

    Returns (points, (totals[p, t], worst inclinations[p, t], trial kinds), held_out[t])
    where held_out[t] is (the point chosen without trial t, that point's errors on trial
    t by run label)."""
    points = grid_points(grid)
    scores = []
    began = time.perf_counter()
    for k, p in enumerate(points):
        scores.append([eskf_score(t, p) for t in trials])
        if k % 10 == 9 or k == len(points) - 1:
            progress(f"  grid {k + 1}/{len(points)} ({time.perf_counter() - began:.0f} s)")
    totals = np.array([[trial_total(s) for s in row] for row in scores])
    incl = np.array([[trial_worst_inclination(s) for s in row] for row in scores])
    knock = np.array([knock_peak_inclination_deg(p) for p in points])
    kinds = [t.kind for t in trials]
    held_out = []
    for j in range(len(trials)):
        best = choose(np.delete(totals, j, axis=1), np.delete(incl, j, axis=1),
                      kinds[:j] + kinds[j + 1:], knock)
        held_out.append((points[best], scores[best][j]))
    return points, (totals, incl, kinds, knock), held_out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small grid, emulator seeds 1-2")
    ap.add_argument("--no-loto", action="store_true", help="tables only, no tuning")
    ap.add_argument("--json", type=Path, help="write the numbers as JSON")
    args = ap.parse_args(argv)
    began = time.perf_counter()
    seeds = (1, 2) if args.quick else (1, 2, 3)
    trials = (broad_trials(DATA / "broad") + px4_trials(DATA / "px4_sih")
              + emulator_trials(seeds))
    print(f"loaded {len(trials)} trials in {time.perf_counter() - began:.0f} s")
    cols = [col_name(t, r) for t, r in columns(trials)]
    others = ["quaternion", "mahony", "madgwick", "kalman"]
    eskf_row = Row("eskf (defaults)", {})
    for t in trials:
        for label, err in eskf_score(t, {}).items():
            eskf_row.cells[col_name(t, Run(label))] = err
    rows = [eskf_row, *reference_rows(trials, others)]
    doc: dict = {"columns": cols, "rows": {}}
    held_row = None
    if not args.no_loto:
        grid = QUICK_GRID if args.quick else GRID
        print(f"leave-one-trial-out over {len(grid_points(grid))} eskf parameter sets "
              f"({', '.join(grid)}) and {len(trials)} trials")
        points, (totals, incl, kinds, knock), held = leave_one_out(trials, grid)
        best = choose(totals, incl, kinds, knock)
        best_all = points[best]
        print(f"knock peak inclination: defaults {knock_peak_inclination_deg({}):.2f}°, "
              f"chosen {knock[best]:.2f}°, {int((knock <= KNOCK_PEAK_DEG).sum())} of "
              f"{len(points)} points within {KNOCK_PEAK_DEG}°")
        print("chosen on all trials (what the defaults should be): "
              + ", ".join(f"{k}={v:g}" for k, v in best_all.items()))
        doc["chosen_on_all"] = best_all
        held_row = Row("eskf leave-one-out", {})
        for t, (_, errs) in zip(trials, held, strict=True):
            for label, err in errs.items():
                held_row.cells[col_name(t, Run(label))] = err
        rows.insert(1, held_row)
        chosen = {t.name: p for t, (p, _) in zip(trials, held, strict=True)}
        doc["loto_choices"] = chosen
        print("parameters chosen without each trial:")
        for name, p in chosen.items():
            print(f"  {name:>12}: " + ", ".join(f"{k}={v:g}" for k, v in p.items()))
    print()
    for metric, title in (("total_deg", "total RMSE [deg]"), ("heading_deg", "heading"),
                          ("inclination_deg", "inclination")):
        print(format_table(title, rows, cols, metric))
        print()
    print("columns: BROAD trial number; px4*/emu-* flights, /a aided, /u unaided with the "
          "multirotor model, /g generic (neither); the references take no aiding and no "
          "vehicle model and appear under /u")
    print(f"{time.perf_counter() - began:.0f} s")
    for r in rows:
        doc["rows"][r.label] = {c: {"total_deg": e.total_deg, "heading_deg": e.heading_deg,
                                    "inclination_deg": e.inclination_deg}
                                for c, e in r.cells.items()}
    if args.json:
        args.json.write_text(json.dumps(doc, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
