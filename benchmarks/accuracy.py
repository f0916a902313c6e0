"""Accuracy suite: every estimator and the references on real and emulated data, one table.

    python benchmarks/accuracy.py                 # tables + leave-one-trial-out of eskf
    python benchmarks/accuracy.py --quick         # smaller tuning grid, 2 emulator seeds
    python benchmarks/accuracy.py --json out.json

Every recording is scored whole (ground, take-off, flight, touchdown, landing, handling)
and, separately, per phase (``replay.flight.PHASES``); the worst phase is reported.

Trials:

* **BROAD** dev trials (9, ../shared/data/broad): a hand-held IMU with optical truth, ENU,
  started from the first sample, scored over the ``movement`` samples (the dataset's
  protocol). No aiding, no vehicle model.
* **PX4 SIH** flights: a real PX4 flying its SIH quadrotor, truth = HIL_STATE_QUATERNION
  placed by arrival; ../shared/data/px4_sih (2 flights, take-off to landing) and this
  project's tests/data/sitl (2 flights with a touchdown, 10 s on the ground and a second
  take-off: benchmarks/record_sitl_flights.py). The flight state comes from the log's
  HEARTBEAT / EXTENDED_SYS_STATE through the replay's policy (``replay.flight``).
  Declination from the WMM at the flight's position. Runs: *aided* (LOCAL_POSITION_NED
  velocity with its age, as the bridge gets it, and the multirotor drag model while
  airborne), *drag* (the drag model alone), *vel* (aiding alone, ``drag=0``; table only)
  and *generic* (neither: a vehicle of unknown kind). PX4's own ATTITUDE is a row.
* **ArduPilot SITL** flight (tests/data/sitl/arducopter_touchdown.tlog: Copter SITL, two
  flights with a touchdown, RAW_IMU 333 Hz), truth = SIMSTATE placed by arrival; runs and
  the autopilot's own ATTITUDE row as for PX4.
* **Emulator** flights (``hil`` ``flight`` profile, 120 s, seeds 1-3, and the
  ``handheld_flight`` profile: carried by hand, two flights with a touchdown; 250 Hz):
  the GY-86 board calibrated from its own calibration session, GPS at 5 Hz with 100 ms
  latency, the emulator's own flight state; runs as for PX4.
* **Hand-held** emulator profiles (``tilt``, ``gentle``, ``calibration``; the vehicle says
  quadrotor, disarmed on the ground): *drag* (product defaults: the drag model's prior,
  kept off by the flight state) and *generic* (``drag=0``).

Reference rows: gyro integration (``quaternion``, from the true start), VQF 2.x online
and offline (9D, defaults), imufusion (defaults), the autopilot's ATTITUDE, and our other
estimators.

Leave-one-trial-out: the eskf noise parameters on the grid below are chosen on all
trials but one (lowest mean total error over them, each trial weighing the same; a
flight's score is the mean of its aided, drag and generic runs; among the points whose
worst BROAD inclination over those trials stays within 1.8° and whose knock peak stays
within 2.5°) and scored on the one left out, for each trial in turn: *cross-validated*.
The model's structure and the hand-set constants (README, "What was chosen on which
data") were chosen looking at these same recordings, so even the held-out numbers are
not those of data never seen.
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
from replay.references import reference_attitudes

DATA = Path(os.environ.get("ATTITUDE_BRIDGE_DATA",
                           Path(__file__).resolve().parents[2] / "shared" / "data"))
EMULATOR_RATE_HZ = 250.0
EMULATOR_SECONDS = 120.0
HANDHELD_PROFILES = ("tilt", "gentle", "calibration")
HANDHELD_SECONDS = 60.0
REPO = Path(__file__).resolve().parents[1]

#: The grid the leave-one-trial-out tuning chooses from (eskf parameter -> values): one
#: step either side of the defaults on the noise values that matter most.
GRID: dict[str, tuple[float, ...]] = {
    "velocity_prior": (0.1, 0.2, 0.4),
    "velocity_rw": (0.02, 0.1),
    "mag_noise": (0.25, 0.4, 0.6),
    "gyro_noise": (0.005, 0.008, 0.012),
    "gyro_rate_noise": (0.002, 0.003, 0.005),
    "aid_density": (0.4, 0.8, 1.6),
    "mag_delay": (0.0, 0.005, 0.01),
    "drag_noise": (0.1, 0.2, 0.3),
}
#: The tuning may not buy a better mean with a worse worst case than this (issue 9).
WORST_INCLINATION_DEG = 1.8
#: Nor with a filter that a knock tilts further than this: the peak inclination after a
#: 0.2 s, 8 g sideways impact on a board held still (tests/test_eskf.py's shock scenario,
#: which no recording here contains).
KNOCK_PEAK_DEG = 2.5
#: Nor with aiding too weak to hold the tilt through a sustained acceleration: with a
#: clean 10 Hz velocity, 50 ms late, the peak inclination error of a vehicle holding
#: 4 m/s² for 3 s must shrink at least this many times against no aiding
#: (tests/test_estimator_common.py's scenario). The recordings' velocities are an
#: autopilot's estimate or a noisy GPS; a clean one is what a good GPS gives.
AIDING_GAIN_MIN = 3.0
#: Grids that put a value on both sides of every default (docs/accuracy.md, "Grids that
#: bracket the defaults"); ``--grid bracket-1`` / ``bracket-2``. Their choices were not
#: adopted: they buy the generic runs at the cost of BROAD and the aided flights.
_BRACKET_1: dict[str, tuple[float, ...]] = {
    "velocity_prior": (0.1, 0.2, 0.4),
    "velocity_rw": (0.05, 0.1, 0.2),
    "mag_noise": (0.15, 0.25, 0.4),
    "gyro_noise": (0.003, 0.005, 0.008),
    "gyro_rate_noise": (0.003, 0.005, 0.008),
    "aid_density": (0.8, 1.6, 3.2),
    "mag_delay": (0.005, 0.01, 0.02),
}
BRACKET_GRIDS: dict[str, dict[str, tuple[float, ...]]] = {
    "bracket-1": _BRACKET_1,
    # one step further where bracket-1 chose an edge
    "bracket-2": {**_BRACKET_1, "velocity_rw": (0.1, 0.2, 0.4),
                  "gyro_noise": (0.002, 0.003, 0.005), "aid_density": (1.6, 3.2, 6.4)},
}
QUICK_GRID: dict[str, tuple[float, ...]] = {
    "mag_noise": (0.25, 0.4),
    "gyro_rate_noise": (0.0, 0.003),
    "aid_density": (0.8, 1.6),
}


@dataclass
class Run:
    """One way of running an estimator on a trial (a flight: aided, drag, vel, generic)."""

    label: str  # "", "aided", "drag", "vel", "generic"
    vel: np.ndarray | None = None
    vel_age: np.ndarray | None = None
    params: dict[str, float] = field(default_factory=dict)  # e.g. the multirotor model


@dataclass
class Trial:
    """Sensor samples with truth on the IMU clock and the samples that count."""

    name: str
    kind: str  # "broad" | "sitl" | "emulator" | "handheld"
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
    airborne: np.ndarray | None = None  # (N,) 1/0/NaN: the flight state the vehicle tells
    phase: np.ndarray | None = None  # (N,) index into replay.flight.PHASES
    imu_delay: float = 0.0  # s, the IMU stream's filter delay (imu.filter_delay)

    def score(self, q: np.ndarray) -> ErrorRms:
        return rms_errors(q[self.scored], self.truth[self.scored])

    def phase_scores(self, q: np.ndarray) -> dict[str, ErrorRms]:
        """Errors per flight phase present in the trial (empty without phases)."""
        from replay.flight import PHASES

        if self.phase is None:
            return {}
        ok = self.scored & np.all(np.isfinite(q), axis=1)
        return {name: rms_errors(q[ok & (self.phase == k)], self.truth[ok & (self.phase == k)])
                for k, name in enumerate(PHASES) if (ok & (self.phase == k)).any()}


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


def flight_runs(vel: np.ndarray | None, age: np.ndarray | None) -> list[Run]:
    quad = {"drag": MULTIROTOR_DRAG_PER_S}
    aided = [Run("aided", vel, age, quad), Run("vel", vel, age, {"drag": 0.0})] \
        if vel is not None else []
    return [*aided, Run("drag", params=quad), Run("generic")]


def sitl_trials(folders: list[Path]) -> list[Trial]:
    """Every PX4 / ArduPilot SITL tlog with truth in ``folders`` (HIL_STATE_QUATERNION,
    SIMSTATE), scored whole, with its flight state."""
    from replay.align import reference_at
    from replay.declination import resolve
    from replay.evaluate import recording_imu_delay
    from replay.flight import track
    from replay.readers import load

    out = []
    for f in sorted(p for folder in folders for p in folder.glob("*.tlog")):
        rec = load(f, reference="truth")
        if rec.reference is None or rec.reference.kind != "truth":
            continue
        own = load(f, reference="autopilot").reference
        truth = reference_at(rec.reference, rec.t)
        autopilot = reference_at(own, rec.t) if own is not None else None
        v = rec.velocity
        scored = np.all(np.isfinite(truth), axis=1)
        first = int(np.flatnonzero(scored)[0])
        fl = track(rec)
        runs = flight_runs(None if v is None else v.vel,
                           None if v is None else np.nan_to_num(v.age))
        stem = f.stem.replace("sih_", "").replace("px4_", "").replace("aggressive", "agg")
        name = ("ap-" + stem.replace("arducopter_", "") if stem.startswith("arducopter")
                else "px4-" + stem)
        out.append(Trial(name, "sitl", rec.gyr, rec.acc, rec.mag, rec.dt,
                         rec.rate_hz, "NED", truth, scored, resolve(rec).rad, runs,
                         q0=truth[first], autopilot=autopilot,
                         airborne=fl.airborne if fl.known else None, phase=fl.phase,
                         imu_delay=recording_imu_delay(rec).seconds))
    return out


def _emulated(name: str, profile: str, seconds: float, seed: int, gps: bool, kind: str
              ) -> Trial:
    """One emulator recording as the calibrated GY-86 board measures it, scored whole."""
    from bridge.app.calibrate_cli import emulator_samples
    from hil import EmulatorConfig, simulate
    from hil.config import GpsConfig
    from imu.calibration_fit import fit_calibration
    from imu.flight_state import AIRBORNE_LANDED_STATES
    from replay.flight import phases

    gyr, acc, mag, rate = emulator_samples(seed, EMULATOR_RATE_HZ)
    cal, _ = fit_calibration(gyr, acc, mag, rate)
    cfg = EmulatorConfig(profile=profile, duration_s=seconds, seed=seed,
                         rate_hz=EMULATOR_RATE_HZ, gps=GpsConfig() if gps else None)
    rec = simulate(cfg)
    dt = np.diff(rec.time_us, prepend=rec.time_us[0] - round(1e6 / cfg.imu_rate_hz)) * 1e-6
    airborne = (rec.armed & np.isin(rec.landed_state, list(AIRBORNE_LANDED_STATES)))
    if gps:
        vel, age = rec.gps_aiding()
        runs = flight_runs(vel, age)
    else:
        runs = [Run("drag", params={"drag": MULTIROTOR_DRAG_PER_S}), Run("generic")]
    g = cal.gyro(rec.gyr)
    return Trial(name, kind, g, cal.accel(rec.acc), cal.mag(rec.mag), dt, cfg.imu_rate_hz,
                 "NED", rec.truth_q, np.ones(len(dt), dtype=bool),
                 math.radians(cfg.environment.magnetic_declination_deg), runs,
                 q0=rec.truth_q[0], airborne=airborne.astype(float),
                 phase=phases(rec.t_s, g, rec.landed_state.astype(float),
                              rec.armed.astype(float)))


def emulator_trials(seeds: tuple[int, ...]) -> list[Trial]:
    flights = [_emulated(f"emu-{seed}", "flight", EMULATOR_SECONDS, seed, True, "emulator")
               for seed in seeds]
    flights.append(_emulated("emu-hand", "handheld_flight", EMULATOR_SECONDS, 1, True,
                             "emulator"))
    return flights


def handheld_trials() -> list[Trial]:
    return [_emulated(f"hand-{p[:4]}", p, HANDHELD_SECONDS, 1, False, "handheld")
            for p in HANDHELD_PROFILES]


# --- running -------------------------------------------------------------------------------
def run_estimator(trial: Trial, name: str, run: Run, **params: float) -> np.ndarray:
    q0 = trial.q0 if name in ("quaternion", "dcm", "euler") else None
    known = estimators.estimator_class(name).param_names()
    vehicle = {k: v for k, v in run.params.items() if k in known}  # e.g. eskf's drag model
    est = estimators.create(name, rate_hz=trial.rate_hz, world=trial.world, q0=q0,
                            declination=trial.declination,
                            **{"imu_delay": trial.imu_delay, **vehicle, **params})
    res = est.run(trial.gyr, trial.acc, trial.mag, dt=trial.dt, vel=run.vel,
                  vel_age=run.vel_age, airborne=trial.airborne)
    return res.q


#: Runs the tuning objective counts ("vel", aiding without the drag model, is a table
#: row that shows what the drag model adds, not a product configuration).
TUNED_RUNS = ("", "aided", "drag", "generic")


def eskf_score(trial: Trial, params: dict[str, float], tuned_only: bool = False
               ) -> dict[str, ErrorRms]:
    """eskf on every run of the trial (or only the tuned ones), by run label."""
    return {r.label: trial.score(run_estimator(trial, "eskf", r, **params))
            for r in trial.runs if not tuned_only or r.label in TUNED_RUNS}


def _references(trial: Trial, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The reference filters (``replay --compare``'s code) on the trial, by label."""
    runs = reference_attitudes(trial.gyr, trial.acc, trial.mag, trial.rate_hz, trial.world,
                               trial.declination, names)
    return {run.label: run.q for run in runs}


def vqf_rows(trial: Trial) -> dict[str, np.ndarray]:
    return _references(trial, ("vqf", "vqf-offline"))


def imufusion_row(trial: Trial) -> np.ndarray:
    return _references(trial, ("imufusion",))["imufusion"]


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
            continue  # the same data as "drag" for everything but eskf's vehicle model
        if run.label in ("", "drag"):  # the references take no aiding: one column each
            for label, q in vqf_rows(trial).items():
                put(label, trial, run, q)
            put("imufusion", trial, run, imufusion_row(trial))
            if trial.autopilot is not None:
                put("autopilot ATTITUDE", trial, run, trial.autopilot)
    return list(rows.values())


def format_table(title: str, rows: list[Row], cols: list[str], metric: str) -> str:
    width = max(22, *(len(r.label) + 1 for r in rows))
    cw = max(10, *(len(c) + 1 for c in cols))
    head = f"{title:<{width}}" + "".join(f"{c:>{cw}}" for c in cols) + f"{'mean':>8}{'worst':>8}"
    lines = [head]
    for r in rows:
        vals = [getattr(r.cells[c], metric) if c in r.cells else math.nan for c in cols]
        have = [v for v in vals if math.isfinite(v)]
        mean = float(np.mean(have)) if have else math.nan
        worst = float(np.max(have)) if have else math.nan
        lines.append(f"{r.label:<{width}}" + "".join(
            f"{v:>{cw}.2f}" if math.isfinite(v) else f"{'':>{cw}}" for v in vals)
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


def aiding_gain(params: dict[str, float], rate_hz: float = 200.0) -> float:
    """Peak inclination error unaided over aided in a sustained acceleration (level,
    accelerating north at 4 m/s² from 2 to 5 s; velocity at 10 Hz, 50 ms late)."""
    n = int(8 * rate_hz)
    a = np.zeros((n, 3))
    a[int(2 * rate_hz):int(5 * rate_hz), 0] = 4.0
    rng = np.random.default_rng(5)
    acc = np.tile([0.0, 0.0, -G], (n, 1)) + a + rng.normal(0.0, 0.05, (n, 3))
    mag = np.tile([0.2, 0.0, 0.45], (n, 1)) + rng.normal(0.0, 0.002, (n, 3))
    vel_true = np.cumsum(a, axis=0) / rate_hz
    vel, age = np.full((n, 3), np.nan), np.zeros(n)
    late, step = round(0.05 * rate_hz), round(rate_hz / 10.0)
    vel[late::step] = vel_true[:n - late:step]
    age[late::step] = late / rate_hz
    truth = Q.identity(n)
    gyr = np.zeros((n, 3))
    plain = estimators.batch("eskf", gyr, acc, mag, rate_hz=rate_hz, q0=Q.identity(), **params)
    aided = estimators.batch("eskf", gyr, acc, mag, rate_hz=rate_hz, q0=Q.identity(), vel=vel,
                             vel_age=age, **params)
    return float(attitude_errors(plain, truth).inclination.max()
                 / attitude_errors(aided, truth).inclination.max())


def choose(totals: np.ndarray, inclinations: np.ndarray, kinds: list[str],
           knock_deg: np.ndarray | None = None, gain: np.ndarray | None = None) -> int:
    """The grid point with the lowest mean total over the given trials among those whose
    worst BROAD inclination stays within WORST_INCLINATION_DEG (worst-case inclination is
    a headline number, not something a good mean may buy) and whose knock peak stays
    within KNOCK_PEAK_DEG; all points if none does."""
    broad = [k == "broad" for k in kinds]
    worst = inclinations[:, broad].max(axis=1) if any(broad) else np.zeros(len(totals))
    eligible = worst <= WORST_INCLINATION_DEG
    if knock_deg is not None:
        eligible &= knock_deg <= KNOCK_PEAK_DEG
    if gain is not None:
        eligible &= gain >= AIDING_GAIN_MIN
    mean = totals.mean(axis=1)
    return int(np.argmin(np.where(eligible, mean, np.inf)) if eligible.any()
               else np.argmin(mean))


#: The trials the grid workers score (set before the pool forks, so each worker gets
#: them without pickling 22 recordings per task).
_GRID_TRIALS: list[Trial] = []


def _score_points(points: list[dict[str, float]]) -> list[list[dict[str, ErrorRms]]]:
    return [[eskf_score(t, p, tuned_only=True) for t in _GRID_TRIALS] for p in points]


def _score_grid(trials: list[Trial], points: list[dict[str, float]], jobs: int | None,
                progress: Callable[[str], None]) -> list[list[dict[str, ErrorRms]]]:
    """eskf's tuned runs on every trial for every grid point, in grid order, on ``jobs``
    processes (``replay.parallel``, forked: the compiled kernels and the loaded trials
    are shared, not rebuilt per task)."""
    from replay.parallel import run

    global _GRID_TRIALS
    _GRID_TRIALS = trials
    pieces = [(points[k:k + 10],) for k in range(0, len(points), 10)]
    began, scored = time.perf_counter(), 0

    def done(_: int, piece: list[list[dict[str, ErrorRms]]]) -> None:
        nonlocal scored
        scored += len(piece)
        progress(f"  grid {scored}/{len(points)} ({time.perf_counter() - began:.0f} s)")

    def crashed(_: tuple, reason: str) -> None:
        raise RuntimeError(f"a grid worker failed: {reason}")

    out = run(_score_points, pieces, on_crash=crashed, jobs=jobs, on_done=done)
    if out.interrupted:
        raise KeyboardInterrupt
    return [row for piece in out.results for row in piece]


def leave_one_out(trials: list[Trial], grid: dict[str, tuple[float, ...]],
                  progress: Callable[[str], None] = print, jobs: int | None = 1
                  ) -> tuple[list[dict[str, float]], np.ndarray, list[tuple]]:
    """Scores of every grid point on every trial, and per trial the held-out result.

    Returns (points, (totals[p, t], worst inclinations[p, t], trial kinds), held_out[t])
    where held_out[t] is (the point chosen without trial t, that point's errors on trial
    t by run label)."""
    points = grid_points(grid)
    scores = _score_grid(trials, points, jobs, progress)
    totals = np.array([[trial_total(s) for s in row] for row in scores])
    incl = np.array([[trial_worst_inclination(s) for s in row] for row in scores])
    knock = np.array([knock_peak_inclination_deg(p) for p in points])
    gain = np.array([aiding_gain(p) for p in points])
    kinds = [t.kind for t in trials]
    held_out = []
    for j in range(len(trials)):
        best = choose(np.delete(totals, j, axis=1), np.delete(incl, j, axis=1),
                      kinds[:j] + kinds[j + 1:], knock, gain)
        held_out.append((points[best], scores[best][j]))
    return points, (totals, incl, kinds, knock, gain), held_out


def phase_lines(trials: list[Trial], labels: dict[str, Callable[[Trial], np.ndarray | None]]
                ) -> list[str]:
    """Per flight trial and row: the whole-recording total, then the worst phase."""
    lines = ["by phase (whole recording total°, then the worst phase: total°):"]
    for trial in trials:
        if trial.phase is None:
            continue
        cells = []
        for label, get in labels.items():
            q = get(trial)
            if q is None:
                continue
            ph = trial.phase_scores(q)
            worst = max(ph.items(), key=lambda kv: kv[1].total_deg)
            cells.append(f"{label} {trial.score(q).total_deg:.2f} "
                         f"({worst[0]} {worst[1].total_deg:.2f})")
        lines.append(f"  {trial.name:>10}: " + "; ".join(cells))
    return lines


def criteria_lines(trials: list[Trial], rows: dict[str, Row]) -> list[str]:
    """The accuracy criteria of issue 17, each with its numbers and a verdict."""
    eskf = rows["eskf (defaults)"].cells
    out = []

    def verdict(ok: bool) -> str:
        return "ok" if ok else "NOT MET"

    for t in trials:
        if t.kind in ("sitl", "emulator"):
            a, d = eskf.get(f"{t.name}/a"), eskf.get(f"{t.name}/d")
            v = eskf.get(f"{t.name}/v")
            if a and d and v:
                best = min(d.total_deg, v.total_deg)
                out.append(f"{t.name}: aided {a.total_deg:.3f} vs best of drag-only "
                           f"{d.total_deg:.3f} / aiding-only {v.total_deg:.3f}: "
                           f"{a.total_deg / best:.3f}x {verdict(a.total_deg <= best)}")
        if t.kind == "sitl" and "autopilot ATTITUDE" in rows:
            own = rows["autopilot ATTITUDE"].cells.get(f"{t.name}/d")
            a = eskf.get(f"{t.name}/a")
            if own and a:
                ok = a.total_deg <= own.total_deg and a.inclination_deg <= own.inclination_deg
                out.append(f"{t.name}: eskf {a.total_deg:.3f}/{a.inclination_deg:.3f} vs autopilot "
                           f"{own.total_deg:.3f}/{own.inclination_deg:.3f} (total/incl): "
                           f"{verdict(ok)}")
        if t.kind == "handheld":
            d, g = eskf[f"{t.name}/d"], eskf[f"{t.name}/g"]
            out.append(f"{t.name}: defaults {d.total_deg:.3f} vs drag=0 {g.total_deg:.3f}: "
                       f"{d.total_deg / g.total_deg:.3f}x "
                       f"{verdict(d.total_deg <= 1.1 * g.total_deg)}")
    broad = [t.name for t in trials if t.kind == "broad"]
    for label in ("eskf leave-one-out", "eskf (defaults)"):
        if label not in rows or "vqf online" not in rows:
            continue
        mine = [rows[label].cells[b] for b in broad]
        vqf = [rows["vqf online"].cells[b] for b in broad]
        m, mv = np.mean([e.total_deg for e in mine]), np.mean([e.total_deg for e in vqf])
        w, wv = max(e.inclination_deg for e in mine), max(e.inclination_deg for e in vqf)
        out.append(f"BROAD {label}: mean total {m:.3f} vs VQF online {mv:.3f} ({m / mv:.3f}x, "
                   f"{verdict(m <= 0.9 * mv)} at 0.9x); worst inclination {w:.3f} vs VQF "
                   f"{wv:.3f} {verdict(w <= wv)}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small grid, emulator seeds 1-2")
    ap.add_argument("--no-loto", action="store_true", help="tables only, no tuning")
    ap.add_argument("--json", type=Path, help="write the numbers as JSON")
    ap.add_argument("--jobs", type=int,
                    help="processes that score the grid (default: every core)")
    ap.add_argument("--grid", choices=sorted(BRACKET_GRIDS),
                    help="tune over a grid that brackets every default instead of GRID "
                         "(2187 points, about 30 min)")
    args = ap.parse_args(argv)
    if args.jobs is not None and args.jobs < 1:
        ap.error(f"--jobs {args.jobs}: expected a number of processes >= 1")
    began = time.perf_counter()
    seeds = (1, 2) if args.quick else (1, 2, 3)
    trials = (broad_trials(DATA / "broad")
              + sitl_trials([DATA / "px4_sih", REPO / "tests" / "data" / "sitl"])
              + emulator_trials(seeds) + handheld_trials())
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
        grid = BRACKET_GRIDS[args.grid] if args.grid else QUICK_GRID if args.quick else GRID
        print(f"leave-one-trial-out over {len(grid_points(grid))} eskf parameter sets "
              f"({', '.join(grid)}) and {len(trials)} trials")
        points, (totals, incl, kinds, knock, gain), held = leave_one_out(trials, grid,
                                                                           jobs=args.jobs)
        best = choose(totals, incl, kinds, knock, gain)
        print(f"aiding gain in a sustained acceleration: defaults {aiding_gain({}):.2f}x, "
              f"chosen {gain[best]:.2f}x, {int((gain >= AIDING_GAIN_MIN).sum())} of "
              f"{len(points)} points at least {AIDING_GAIN_MIN}x")
        unconstrained = points[int(np.argmin(totals.mean(axis=1)))]
        print("lowest mean total without the constraints: "
              + ", ".join(f"{k}={v:g}" for k, v in unconstrained.items()))
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
    print("columns: BROAD trial number; px4-*/ap-*/emu-* flights and hand-* hand-held emulator "
          "recordings, /a aided + drag model, /d drag model only, /v aiding only (drag=0), "
          "/g generic (neither); the drag model runs only while the vehicle says it is "
          "airborne; the references take no aiding and no vehicle model and appear under /d")
    print()
    by_label = {r.label: r for r in rows}
    aided = {t.name: next((r for r in t.runs if r.label == "aided"), None) for t in trials}
    print("\n".join(phase_lines(trials, {
        "eskf": lambda t: run_estimator(t, "eskf", aided[t.name]) if aided[t.name] else
        run_estimator(t, "eskf", t.runs[0]),
        "autopilot": lambda t: t.autopilot,
        "vqf": lambda t: vqf_rows(t)["vqf online"]})))
    print()
    print("criteria (issue 17):")
    print("\n".join("  " + line for line in criteria_lines(trials, by_label)))
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
