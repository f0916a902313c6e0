"""Run estimators over a Recording in batch and score them against its reference."""

from __future__ import annotations

import inspect
import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

import estimators
from estimators import metrics
from estimators import quat as Q
from estimators.spec import EstimatorSpec
from estimators.vehicle_model import model_params
from imu import filter_delay
from imu.filter_delay import FilterDelay
from imu.flight_state import state_name
from imu.vehicles import type_name

from .align import DEFAULT_MAX_GAP_S, measure_lag, reference_at
from .dataset import Recording, Reference, ReplayInputError
from .declination import Declination, check_against_reference, resolve
from .flight import PHASES, FlightTrack, track
from .references import ReferenceRun, reference_runs

#: Gyro-only integrators: left out of the default comparison (they only drift), still
#: available by name with --estimator.
GYRO_ONLY = frozenset({"euler", "dcm", "quaternion"})
CONVERGED_DEG = 5.0  # convergence: total error below this ...
CONVERGED_HOLD_S = 1.0  # ... for at least this long
#: Below this IMU rate, gyro integration between samples misses most of the motion
#: (a tlog's 3 Hz RAW_IMU): the estimators are not run at all.
MIN_RATE_HZ = 20.0
AID_CHOICES = ("auto", "velocity", "none")
#: What a format calls its score mask, and what the mask selects, for the footnotes
SCORE_MASK_NAMES = {"csv": ("score column", "row"), "npz": ("movement array", "sample")}


def amount(x: float, decimals: int = 1, tiny: bool = True) -> str:
    """A duration, rate or jitter for a one-line summary: fixed decimals in the range
    real logs have, else three digits with an exponent (a nonsense rate is not 300
    digits). ``tiny``: also an exponent below the decimals (a rate of 1e-300 Hz is not
    "0.0 Hz"); without it they read as zero (a jitter of 1e-12 ms)."""
    small = tiny and abs(x) < 10.0**-decimals
    if x == 0.0 or (abs(x) < 1e6 and not small):
        return f"{x:.{decimals}f}"
    return f"{x:.3g}"


def default_specs() -> list[EstimatorSpec]:
    """Every registered estimator except the gyro-only integrators (all if that is none)."""
    names = estimators.names()
    chosen = [n for n in names if n not in GYRO_ONLY] or names
    return [EstimatorSpec(n) for n in chosen]


@dataclass(frozen=True)
class Prepared:
    """A recording with its reference on the IMU clock and the samples that count."""

    recording: Recording
    q_ref: np.ndarray | None  # (N, 4) or None without reference
    scored: np.ndarray  # (N,) bool: reference known and inside the score mask
    declination: Declination = field(default_factory=lambda: Declination(0.0, "none"))
    aid: str = "none"  # "velocity": the recording's velocity goes to the estimators
    aid_note: str = ""  # what aiding the log offers and what is done with it
    unscored: str = ""  # why nothing can be scored ("" when something can)
    flight: FlightTrack | None = None  # the vehicle's flight state and phases per sample
    #: how old the IMU samples are when sent (an autopilot's low-pass filter): the
    #: estimators' ``imu_delay``
    imu_delay: FilterDelay = filter_delay.NONE


def prepare(rec: Recording, method: str = "slerp", max_gap: float = DEFAULT_MAX_GAP_S,
            declination_deg: float | None = None, aid: str = "auto") -> Prepared:
    """Reference on the IMU times, scored samples, declination and aiding for ``rec``."""
    dec = resolve(rec, declination_deg)
    aid, aid_note = _choose_aid(rec, aid)
    flight = track(rec)
    delay = recording_imu_delay(rec)
    if rec.reference is None:
        return Prepared(rec, None, np.zeros(rec.n, dtype=bool), dec, aid, aid_note,
                        "no reference attitude in the file: nothing to score against",
                        flight, delay)
    q_ref = reference_at(rec.reference, rec.t, method, max_gap)
    scored = np.all(np.isfinite(q_ref), axis=1)
    if rec.score_mask is not None:
        scored &= rec.score_mask
    why = "" if scored.any() else unscored_reason(rec, rec.reference, q_ref, max_gap)
    return Prepared(rec, q_ref, scored, dec, aid, aid_note, why, flight, delay)


def unscored_reason(rec: Recording, ref: Reference, q_ref: np.ndarray, max_gap: float
                    ) -> str:
    """Why no IMU sample is scored: the reference ``ref`` (``q_ref`` on the IMU clock)
    has no attitude at all, the score mask selects nothing, the two miss each other, or
    the reference misses the IMU in time."""
    mask = rec.score_mask
    if ref.valid == 0 or mask is None:
        return attitude_gap(ref, "reference", rec.t, "the IMU", max_gap)
    name, unit = SCORE_MASK_NAMES.get(rec.format, ("score mask", "sample"))
    if not mask.any():
        return f"the file's {name} selects no {unit}"
    has_ref = np.all(np.isfinite(q_ref), axis=1)
    if has_ref.any():
        return (f"no {unit} with a reference inside the file's {name} "
                f"({np.count_nonzero(has_ref)} with a reference, {np.count_nonzero(mask)} "
                f"selected)")
    return attitude_gap(ref, "reference", rec.t, "the IMU", max_gap)


def attitude_gap(ref: Reference, label: str, t: np.ndarray, where: str,
                 max_gap: float) -> str:
    """Why an attitude (the reference, the autopilot's) is on none of the IMU times
    ``t``: it has no sample, no valid quaternion, or none within ``max_gap`` of them."""
    n = ref.t.shape[0]
    if n == 0:
        return f"{label} ({ref.source}) has no samples"
    if ref.valid == 0:
        return f"{label} ({ref.source}) has no valid quaternion ({n} of {n} zero or not a number)"
    dropped = f"; dropped {ref.cleanup}" if ref.cleanup.dropped else ""
    return (f"{label} ({ref.source}, {ref.t[0]:.1f}..{ref.t[-1]:.1f} s{dropped}) does not "
            f"overlap {where} ({t[0]:.1f}..{t[-1]:.1f} s) with gaps under {max_gap:g} s")


def recording_imu_delay(rec: Recording) -> FilterDelay:
    """The IMU stream's filter delay (imu.filter_delay) from the log's autopilot,
    parameters and vehicle type."""
    return filter_delay.imu_filter_delay(rec.mav_autopilot, rec.params, rec.mav_type)


def vehicle_note(rec: Recording) -> str:
    kind = type_name(rec.mav_type)
    if rec.mav_type is None:
        return "unknown (no HEARTBEAT or MAV_TYPE in the log): no vehicle model"
    model = ("eskf's multirotor drag model while airborne" if model_params("eskf", rec.mav_type)
             else "no vehicle model")
    return f"{kind} ({rec.mav_type_source}): {model}"


def flight_kwargs(prep: Prepared, sl: slice) -> dict[str, np.ndarray]:
    """The ``airborne`` keyword for ``Estimator.run`` (empty when the log says nothing:
    the estimator then decides from the data)."""
    if prep.flight is None or not prep.flight.known:
        return {}
    return {"airborne": prep.flight.airborne[sl]}


def estimators_take_velocity() -> bool:
    """Whether this version's estimators accept the ``vel`` / ``vel_age`` aiding input."""
    from estimators.base import Estimator

    return "vel" in inspect.signature(Estimator.run).parameters


def _choose_aid(rec: Recording, aid: str) -> tuple[str, str]:
    if aid not in AID_CHOICES:
        raise ValueError(f"aid must be one of {AID_CHOICES}, got {aid!r}")
    v = rec.velocity
    if aid == "velocity" and v is None:
        raise ReplayInputError(f"{rec.path}: --aid velocity: the log has no velocity "
                               f"(tlog LOCAL_POSITION_NED, GLOBAL_POSITION_INT, GPS_RAW_INT; "
                               f"ULog vehicle_local_position, vehicle_gps_position)")
    if v is None:
        return "none", "none: no velocity in the log"
    ages = v.age[np.isfinite(v.age)]
    offer = (f"velocity from {v.source} ({v.count} measurements, median age "
             f"{1e3 * float(np.median(ages)):.0f} ms)")
    if aid == "none":
        return "none", f"none (--aid none); the log has {offer}"
    if not estimators_take_velocity():
        return "none", f"none: the log has {offer}, but this version's estimators take no aiding"
    return "velocity", offer


def aiding_kwargs(prep: Prepared, sl: slice) -> dict[str, np.ndarray]:
    """The aiding keywords for ``Estimator.run`` over the samples ``sl`` (empty: none)."""
    v = prep.recording.velocity
    if prep.aid != "velocity" or v is None:
        return {}
    return {"vel": v.vel[sl], "vel_age": v.age[sl]}


@dataclass(frozen=True)
class Run:
    """One estimator's output over the recording."""

    spec: EstimatorSpec
    q: np.ndarray  # (N, 4), NaN before the estimator started
    flags: np.ndarray  # (N,) uint8, estimators._core.F_*
    bias: np.ndarray  # (N, 3) rad/s
    counters: estimators.SampleCounters
    seconds: float  # wall time of the batch run
    air_model: np.ndarray | None = None  # (N,) bool: ran its in-flight model (eskf's drag)


def run_estimator(prep: Prepared, spec: EstimatorSpec, init: str = "sensors") -> Run:
    """Batch-run one estimator with the IMU's own time steps.

    ``init="sensors"`` starts from the first usable acc(+mag) sample (the BROAD rule);
    ``"reference"`` starts at the first sample with a reference, from that attitude (to
    compare filters without the initial-heading question, e.g. PX4 applies declination).
    """
    rec = prep.recording
    sl, q0, params = run_inputs(prep, spec, init)
    est = estimators.create(spec.name, rate_hz=rec.rate_hz, world=rec.world, q0=q0, **params)
    began = time.perf_counter()
    res = est.run(rec.gyr[sl], rec.acc[sl], None if rec.mag is None else rec.mag[sl],
                  dt=rec.dt[sl], **aiding_kwargs(prep, sl), **flight_kwargs(prep, sl))
    seconds = time.perf_counter() - began
    return placed(prep, spec, sl, res, est.counters, seconds)


def run_inputs(prep: Prepared, spec: EstimatorSpec, init: str = "sensors"
               ) -> tuple[slice, np.ndarray | None, dict]:
    """Where a run starts, from which attitude, with which parameters (see run_estimator)."""
    rec = prep.recording
    start, q0 = 0, None
    if init == "reference":
        if prep.q_ref is None or not prep.scored.any():
            raise ValueError("init='reference' needs a reference attitude in the file")
        start = int(np.argmax(np.all(np.isfinite(prep.q_ref), axis=1)))
        q0 = prep.q_ref[start]
    elif init != "sensors":
        raise ValueError(f"init must be 'sensors' or 'reference', got {init!r}")
    params = {"declination": prep.declination.rad, "imu_delay": prep.imu_delay.seconds,
              **model_params(spec.name, rec.mav_type),
              **spec.params}  # -e ...:declination=, :imu_delay=, :drag= win
    return slice(start, None), q0, params


def placed(prep: Prepared, spec: EstimatorSpec, sl: slice, res: estimators.BatchResult,
           counters: estimators.SampleCounters, seconds: float) -> Run:
    """A batch result over ``sl`` as a Run over the whole recording."""
    rec = prep.recording
    q = np.full((rec.n, 4), np.nan)
    flags = np.zeros(rec.n, dtype=np.uint8)
    bias = np.full((rec.n, 3), np.nan)
    started = res.initialised
    q[sl][started] = res.q[started]
    flags[sl] = res.flags
    air_model = np.zeros(rec.n, dtype=bool)
    air_model[sl] = res.air_model
    bias[sl] = res.bias
    return Run(spec, q, flags, bias, counters, seconds, air_model)


@dataclass(frozen=True)
class Score:
    """Errors of one estimator against the reference (degrees unless named _s)."""

    total_deg: float
    heading_deg: float
    inclination_deg: float
    roll_deg: float  # RMS of the Euler-angle differences, wrapped to ±180°
    pitch_deg: float
    yaw_deg: float
    lag_s: float  # estimate behind reference (cross-correlation); NaN if not observable
    convergence_s: float  # until total error < CONVERGED_DEG for CONVERGED_HOLD_S; NaN: never
    samples: int  # scored samples
    acc_rejected_frac: float  # share of running samples with the accelerometer rejected
    mag_rejected_frac: float
    skipped: int  # samples the estimator could not use at all
    run_s: float  # batch wall time
    six_d: bool = False  # no magnetometer used: judge on inclination only (BROAD rule)
    reasons: dict[str, str] = field(default_factory=dict)  # column -> why it is NaN
    #: phase -> {"total_deg", "inclination_deg", "samples"} (replay.flight.PHASES)
    phases: dict[str, dict[str, float]] = field(default_factory=dict)

    @property
    def worst_phase(self) -> tuple[str, float] | None:
        """The phase with the largest error (total, or inclination when 6D)."""
        key = "inclination_deg" if self.six_d else "total_deg"
        scored = {p: v[key] for p, v in self.phases.items() if math.isfinite(v[key])}
        if not scored:
            return None
        name = max(scored, key=scored.get)
        return name, scored[name]

    def as_json(self) -> dict:
        """Plain dict with NaN as None (JSON has no NaN), ``reasons`` for the None ones."""
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in asdict(self).items()}


def six_d_reason(rec: Recording) -> str:
    """Why heading is not scored on a 6D run (:func:`is_six_d`)."""
    if rec.mag_dropped:
        return (f"no usable magnetometer reading ({rec.mag_dropped} of {rec.mag_dropped} "
                f"NaN, infinite or zero): heading not observable (6D, see inclination)")
    if rec.mag is None:
        return "no magnetometer in the file: heading not observable (6D, see inclination)"
    return "the estimator uses no magnetometer: heading not observable (6D, see inclination)"


def is_six_d(rec: Recording, name: str) -> bool:
    """True when heading is unobservable: no magnetometer in the file, or an estimator
    that declares ``uses_magnetometer = False``. BROAD judges those on inclination only."""
    cls = estimators.estimator_class(name)
    return rec.mag is None or not getattr(cls, "uses_magnetometer", True)


def never_started(run: Run, running: np.ndarray) -> str:
    """Why an estimator has no attitude on any scored sample, from its sample counts."""
    c = run.counters
    if not c.samples:  # an attitude that is no run of ours (a reference filter's)
        return "no attitude on any scored sample (outside its time span or in its gaps)"
    if c.samples and c.skipped == c.samples:
        return ("the estimator skipped every sample (gyro not finite or beyond twice its "
                "full scale, or a bad time step)")
    if not running.any() and c.acc_unusable >= c.samples - c.skipped:
        return ("the estimator never started: no usable accelerometer sample (NaN, about "
                "zero or saturated) to start from")
    return "the estimator never started on a scored sample"


def score(prep: Prepared, run: Run, six_d: bool | None = None, unscored: str = "") -> Score:
    """``six_d``: judge on inclination only (default: :func:`is_six_d` of the run's
    estimator; given for an attitude that is no estimator of ours, the autopilot's).
    ``unscored``: why such an attitude is on no scored sample, should it be (its own
    reason: an estimator's, from its sample counts, would not apply)."""
    rec = prep.recording
    six_d = is_six_d(rec, run.spec.name) if six_d is None else six_d
    keep = prep.scored & np.all(np.isfinite(run.q), axis=1)
    running = np.all(np.isfinite(run.q), axis=1)
    n_run = max(int(running.sum()), 1)
    acc_rej = float(np.count_nonzero(run.flags[running] & estimators.base._core.F_ACC_REJECTED))
    mag_rej = float(np.count_nonzero(run.flags[running] & estimators.base._core.F_MAG_REJECTED))
    nan = float("nan")
    if prep.q_ref is None or not keep.any():
        why = prep.unscored or unscored or never_started(run, running)
        return Score(nan, nan, nan, nan, nan, nan, nan, nan, 0, acc_rej / n_run,
                     mag_rej / n_run, run.counters.skipped, run.seconds, six_d,
                     {c: why for c in SCORE_COLUMNS})
    rms = metrics.rms_errors(run.q[keep], prep.q_ref[keep])
    euler = euler_errors(run.q[keep], prep.q_ref[keep])
    euler_rms = np.degrees(np.sqrt(np.mean(euler**2, axis=0)))
    errors = metrics.attitude_errors(run.q, prep.q_ref)
    reasons: dict[str, str] = {}
    lag, why = measure_lag(rec.t, run.q, prep.q_ref, keep)
    if why:
        reasons["lag_s"] = why
    err_deg = np.degrees(errors.total)
    err_deg[~keep] = np.nan
    converged, why = convergence(rec.t, err_deg)
    if why:
        reasons["convergence_s"] = why
    total, heading, yaw = rms.total_deg, rms.heading_deg, float(euler_rms[2])
    if six_d:  # BROAD: without a magnetometer heading is not observable
        total = heading = yaw = nan
        why = six_d_reason(rec)
        reasons.update(total_deg=why, heading_deg=why, yaw_deg=why)
        if "convergence_s" not in reasons:
            converged = nan  # measured on the total error, which includes heading
            reasons["convergence_s"] = why
    return Score(
        phases=phase_scores(prep, run, keep, six_d),
        total_deg=total, heading_deg=heading, inclination_deg=rms.inclination_deg,
        roll_deg=float(euler_rms[0]), pitch_deg=float(euler_rms[1]), yaw_deg=yaw,
        lag_s=float(lag), convergence_s=converged,
        samples=rms.samples, acc_rejected_frac=acc_rej / n_run,
        mag_rejected_frac=mag_rej / n_run, skipped=run.counters.skipped, run_s=run.seconds,
        six_d=six_d, reasons=reasons)


def phase_scores(prep: Prepared, run: Run, keep: np.ndarray, six_d: bool
                 ) -> dict[str, dict[str, float]]:
    """RMS errors of the scored samples in each flight phase the recording has."""
    if prep.flight is None or prep.q_ref is None:
        return {}
    out = {}
    for k, name in enumerate(PHASES):
        sel = keep & (prep.flight.phase == k)
        if not sel.any():
            continue
        rms = metrics.rms_errors(run.q[sel], prep.q_ref[sel])
        out[name] = {"total_deg": float("nan") if six_d else rms.total_deg,
                     "inclination_deg": rms.inclination_deg, "samples": int(sel.sum())}
    return out


SCORE_COLUMNS = ("total_deg", "heading_deg", "inclination_deg", "roll_deg", "pitch_deg",
                 "yaw_deg", "lag_s", "convergence_s")


def euler_errors(q_est: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
    """(N, 3) roll/pitch/yaw differences (rad) wrapped to (-pi, pi]."""
    d = Q.to_euler(q_est) - Q.to_euler(q_ref)
    return np.angle(np.exp(1j * d))


def convergence(t: np.ndarray, err_deg: np.ndarray, threshold: float = CONVERGED_DEG,
                hold_s: float = CONVERGED_HOLD_S) -> tuple[float, str]:
    """(:func:`convergence_time`, "" or why it is NaN).

    An error already below the threshold at the first scored sample says nothing about
    the estimator (every estimator would show that sample's time): NaN, with the reason.
    """
    good = np.isfinite(err_deg)
    if not good.any():
        return float("nan"), "no scored sample"
    value = convergence_time(t, err_deg, threshold, hold_s)
    if not math.isfinite(value):
        return value, f"never within {threshold:g}° for {hold_s:g} s"
    first = float(t[good][0] - t[0])
    if value <= first:
        return float("nan"), (f"already within {threshold:g}° at the first scored sample "
                              f"(t = {first:.2f} s): nothing to converge from")
    return value, ""


def convergence_time(t: np.ndarray, err_deg: np.ndarray, threshold: float = CONVERGED_DEG,
                     hold_s: float = CONVERGED_HOLD_S) -> float:
    """Seconds from the first sample until the error is below ``threshold`` for ``hold_s``.

    Samples without a reference (NaN error) neither break nor count towards the hold.
    """
    good = np.isfinite(err_deg)
    below = err_deg[good] < threshold
    tg = t[good]
    if not below.any():
        return float("nan")
    # Start of each run of consecutive "below" samples and where it ends.
    edges = np.diff(np.concatenate(([0], below.astype(np.int8), [0])))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    for s, e in zip(starts, ends, strict=True):
        if tg[e] - tg[s] >= hold_s or e == len(tg) - 1:
            return float(tg[s] - t[0])
    return float("nan")


@dataclass(frozen=True)
class Evaluation:
    """Everything a report or the JSON output needs about one file."""

    prepared: Prepared
    runs: dict[str, Run]
    scores: dict[str, Score]
    not_run: str = ""  # why the estimators were not run at all ("" when they were)
    #: with --smooth on a log without truth: every other run and the autopilot's own
    #: attitude against the smoothed eskf (not truth: labelled so wherever shown)
    vs_smoothed: dict[str, Score] = field(default_factory=dict)
    smoothed_label: str = ""  # the smoothed run's label ("" without --smooth)
    #: with --compare: each reference filter's run (its attitude, and what its samples
    #: needed), by label
    references: dict[str, ReferenceRun] = field(default_factory=dict)

    @property
    def recording(self) -> Recording:
        return self.prepared.recording

    @property
    def reference_kind(self) -> str | None:
        ref = self.recording.reference
        return None if ref is None else ref.kind

    def flight_json(self) -> dict | None:
        fl = self.prepared.flight
        if fl is None:
            return None
        return {"note": fl.note(), "source": fl.source, "reports": fl.events_source,
                "flap_fallbacks": fl.flap_fallbacks,
                "switches": [{"t": sw.t, "state": state_name(sw.airborne), "source": sw.source}
                             for sw in fl.switches],
                "bands": [{"start": a, "end": b, "state": n}
                          for a, b, n in fl.bands(self.recording.t)]}

    def as_json(self) -> dict:
        rec = self.recording
        return {
            "file": str(rec.path),
            "format": rec.format,
            "reference": self.reference_kind,
            "reference_source": None if rec.reference is None else rec.reference.source,
            "imu_source": rec.source,
            "world": rec.world,
            "samples": rec.n,
            "duration_s": rec.duration,
            "rate_hz": rec.rate_hz, "jitter_ms": round(rec.jitter_ms, 3),
            "dropped_imu_samples": asdict(rec.cleanup),
            "notes": list(rec.notes),
            "warnings": list(rec.warnings),
            "board": rec.board,
            "declination_deg": self.prepared.declination.deg,
            "declination_source": self.prepared.declination.source,
            "imu_delay_ms": round(self.prepared.imu_delay.ms, 3),
            "imu_delay_source": self.prepared.imu_delay.source,
            "aiding": self.prepared.aid,
            "aiding_note": self.prepared.aid_note,
            "vehicle": vehicle_note(self.prepared.recording),
            "flight_state": self.flight_json(),
            "not_scored": self.prepared.unscored or None,
            "not_run": self.not_run or None,
            "estimators": {label: s.as_json() for label, s in self.scores.items()},
            "vs_smoothed": ({"reference": self.smoothed_label + " (not truth)",
                             "estimators": {label: s.as_json()
                                            for label, s in self.vs_smoothed.items()}}
                            if self.vs_smoothed else None),
        }


def evaluate(rec: Recording, specs: list[EstimatorSpec | str] | None = None,
             init: str = "sensors", method: str = "slerp",
             declination_deg: float | None = None, aid: str = "auto",
             min_rate_hz: float = MIN_RATE_HZ, smooth: bool = False,
             compare: tuple[str, ...] = ()) -> Evaluation:
    """Run and score every estimator (default: :func:`default_specs`), and the
    autopilot's own attitude when the reference is another (the truth).

    ``smooth``: also the first eskf of ``specs`` (or the default eskf) smoothed over the
    whole recording (:mod:`replay.smoothing`); without a truth, everything is also
    scored against it (:attr:`Evaluation.vs_smoothed`).

    ``compare``: reference filters by other people (:mod:`replay.references`: ``vqf``,
    ``vqf-offline``, ``imufusion``) run on the same samples and scored the same way,
    as rows of their own.

    Below ``min_rate_hz`` nothing is run (:attr:`Evaluation.not_run` says why): numbers
    from a gyro sampled a few times a second would describe the sampling, not a filter.
    """
    chosen = [EstimatorSpec.parse(s) if isinstance(s, str) else s
              for s in (specs or default_specs())]
    for spec in chosen:  # unknown names and parameters fail before any work
        estimators.estimator_class(spec.name).make_params(**spec.params)
    prep = prepare(rec, method, declination_deg=declination_deg, aid=aid)
    for spec in chosen:  # -e NAME:declination_deg=... as --declination-deg
        check_against_reference(rec, float(spec.params.get("declination", 0.0)),
                                spec.label)
    if rec.rate_hz < min_rate_hz:
        return Evaluation(prep, {}, {}, f"IMU at {amount(rec.rate_hz)} Hz is too slow to "
                                        f"estimate attitude from (needs >= {min_rate_hz:g} Hz)")
    from .smoothing import (
        AUTOPILOT,
        SMOOTHED,
        against_smoothed,
        against_smoothed_extra,
        autopilot_run,
        smoothed_run,
    )

    runs = {s.label: run_estimator(prep, s, init) for s in chosen}
    smoothed_label = ""
    if smooth:
        spec = next((s for s in chosen if s.name == "eskf"), EstimatorSpec("eskf"))
        smoothed_label = spec.label + SMOOTHED
        runs[smoothed_label] = smoothed_run(prep, spec, init)
    scores = {label: score(prep, r) for label, r in runs.items()}
    own = autopilot_run(prep)
    if own is not None:
        scores[AUTOPILOT] = score(prep, own, six_d=False, unscored=autopilot_gap(prep))
    references = {ref.label: ref for ref in reference_runs(rec, prep.declination.rad, compare)}
    for label, ref in references.items():
        scores[label] = score(prep, _reference_as_run(ref), six_d=ref.six_d)
    vs_smoothed = {}
    if smooth and (rec.reference is None or rec.reference.kind != "truth"):
        vs_smoothed = against_smoothed(prep, runs, runs[smoothed_label])
        vs_smoothed.update(against_smoothed_extra(prep, runs[smoothed_label], {
            label: (_reference_as_run(ref), ref.six_d) for label, ref in references.items()}))
    return Evaluation(prep, runs, scores, vs_smoothed=vs_smoothed,
                      smoothed_label=smoothed_label, references=references)


def autopilot_gap(prep: Prepared) -> str:
    """Why the autopilot's attitude is on no scored sample, should it be."""
    own = prep.recording.autopilot
    if own is None or not prep.scored.any():
        return ""
    return attitude_gap(own, "the autopilot's attitude", prep.recording.t[prep.scored],
                        "the scored IMU samples", DEFAULT_MAX_GAP_S)


def _reference_as_run(ref: ReferenceRun) -> Run:
    """A reference filter's attitude in the shape :func:`score` takes."""
    n = len(ref.q)
    return Run(EstimatorSpec(ref.label), ref.q, np.zeros(n, dtype=np.uint8),
               np.full((n, 3), np.nan), estimators.SampleCounters(), ref.seconds)
