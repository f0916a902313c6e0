"""Grid search for one shared parameter set that minimises the mean total RMSE over files
(mean inclination RMSE when heading is unobservable: 6D estimator or no magnetometer).

BROAD's rule: one parameter set for all trials, judged by the plain mean over them. Each
grid point runs the estimator over every file (batch, compiled) and is one task for a
process pool; recordings are loaded once in the parent and inherited by the workers
(fork), so only parameter dicts and a few floats cross process boundaries.
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import multiprocessing as mp
import signal
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

import estimators
from estimators import metrics
from estimators.spec import EstimatorSpec, to_internal

from .dataset import Recording
from .evaluate import Prepared, is_six_d, run_estimator
from .parallel import workers_for
from .progress import Progress

__all__ = ["ParamAxis", "Progress", "Sweep", "damage_notes", "grid_points", "library_axis",
           "parse_param", "score_params", "sweep"]


@dataclass(frozen=True)
class ParamAxis:
    """One swept parameter and its grid values."""

    name: str
    values: np.ndarray
    text: str = field(default="", compare=False)  # as given (``-p kp=1,2``), for errors


#: The largest grid a sweep takes: a million points is days on one core for a long log;
#: a typo (kp=0:1:100000000) should not look like a hang.
MAX_GRID_POINTS = 1_000_000


def parse_param(text: str) -> ParamAxis:
    """``kp=0.1:3:30`` (30 values from 0.1 to 3 inclusive), ``kp=0.1,0.5,2`` or ``kp=1``."""
    name, sep, spec = text.partition("=")
    if not sep or not name.strip():
        raise ValueError(f"--param {text!r}: expected NAME=LO:HI:N or NAME=V1,V2,...")
    try:
        if ":" in spec:
            parts = spec.split(":")
            if len(parts) != 3:
                raise ValueError
            lo, hi, n = float(parts[0]), float(parts[1]), int(parts[2])
            if n < 1 or not (math.isfinite(lo) and math.isfinite(hi)):
                raise ValueError
        else:
            values = np.array([float(v) for v in spec.split(",")])
    except ValueError:
        raise ValueError(f"--param {text!r}: expected NAME=LO:HI:N (N >= 1 integer) or "
                         f"NAME=V1,V2,... with numbers") from None
    if ":" in spec:
        if n > MAX_GRID_POINTS:  # before np.linspace allocates them
            raise ValueError(f"--param {text!r}: {n:,} values (at most {MAX_GRID_POINTS:,} "
                             f"in a grid)")
        values = np.linspace(lo, hi, n)
    return ParamAxis(name.strip(), values, text)


def library_axis(axis: ParamAxis, estimator: str) -> ParamAxis:
    """The axis under the library's name and in its unit: ``bias_limit_dps=1,20`` sweeps
    ``bias_limit`` in rad/s, converted as ``-e NAME:k=v`` and ``--set`` convert (the
    user surface's degree aliases); an unknown name fails here, listing the valid ones."""
    cls = estimators.estimator_class(estimator)
    try:
        name, _ = to_internal(cls, axis.name, float(axis.values[0]))
    except ValueError as exc:
        raise _refused(axis, exc) from None
    if name == axis.name:
        return axis
    values = np.array([to_internal(cls, axis.name, float(v))[1] for v in axis.values])
    return ParamAxis(name, values, axis.text)


def check_values(cls: type[estimators.Estimator], axis: ParamAxis,
                 fixed: dict[str, float]) -> None:
    """Every value of the axis passes the estimator's own checks (finite, within the
    parameter's bounds), as a single value does: a value it refuses would otherwise
    reach the sweep and score as a row of NaN."""
    for value in np.unique(axis.values):
        try:
            cls.make_params(**{**fixed, axis.name: float(value)})
        except ValueError as exc:
            raise _refused(axis, exc) from None


def _refused(axis: ParamAxis, exc: ValueError) -> ValueError:
    """The estimator's refusal, naming the ``--param`` it came from as the user gave it."""
    return ValueError(f"--param {axis.text or axis.name!r}: {exc}")


@dataclass(frozen=True)
class Sweep:
    """Per grid point and file: total / heading / inclination RMSE [deg]."""

    estimator: str
    axes: tuple[ParamAxis, ...]
    fixed: dict[str, float]
    files: tuple[str, ...]
    points: tuple[dict[str, float], ...]
    total: np.ndarray  # (P, F)
    heading: np.ndarray  # (P, F)
    inclination: np.ndarray  # (P, F)
    seconds: float
    objective: str = "total"  # "inclination" for 6D estimators/files (BROAD rule)
    done: np.ndarray | None = None  # (P,) bool: scored (all True unless interrupted)
    interrupted: bool = False  # stopped by Ctrl-C: only the ``done`` points are real
    notes: tuple[tuple[str, ...], ...] = ()  # per file: damage_notes (empty: none known)

    def __post_init__(self) -> None:
        if self.done is None:
            object.__setattr__(self, "done", np.ones(len(self.points), dtype=bool))

    @property
    def mean_total(self) -> np.ndarray:
        """Mean over files; NaN when any file failed for that grid point."""
        return self.total.mean(axis=1)

    @property
    def mean_objective(self) -> np.ndarray:
        """What is minimised: mean total RMSE, or mean inclination RMSE for 6D."""
        return (self.inclination if self.objective == "inclination" else self.total).mean(axis=1)

    @property
    def best_index(self) -> int:
        m = np.where(self.done, self.mean_objective, np.nan)
        if not np.isfinite(m).any():
            raise ValueError("no grid point produced a finite score")
        return int(np.nanargmin(m))

    @property
    def best(self) -> dict[str, float]:
        return {**self.fixed, **self.points[self.best_index]}

    def unscored_files(self) -> list[str]:
        """Files with no finite score at any scored grid point: the estimator never ran
        on a scored sample of theirs (no usable gyro or accelerometer), whatever the
        parameters; they would make every mean NaN."""
        if not self.done.any():
            return []
        dead = ~np.isfinite(self.total[self.done]).any(axis=0)
        return [f for f, d in zip(self.files, dead, strict=True) if d]

    def without(self, files: Sequence[str]) -> Sweep:
        """The same sweep over the other files."""
        keep = np.array([f not in set(files) for f in self.files], dtype=bool)
        return replace(self, files=tuple(f for f, k in zip(self.files, keep, strict=True)
                                         if k),
                       total=self.total[:, keep], heading=self.heading[:, keep],
                       inclination=self.inclination[:, keep],
                       notes=tuple(n for n, k in zip(self.notes, keep, strict=False) if k))

    def notes_of(self, index: int) -> tuple[str, ...]:
        """The damage notes of file ``index`` (none when the sweep was made without)."""
        return self.notes[index] if index < len(self.notes) else ()

    def grid(self, values: np.ndarray | None = None) -> np.ndarray:
        """Scores reshaped to the grid: axis order as given on the command line."""
        v = self.mean_objective if values is None else values
        return v.reshape([len(a.values) for a in self.axes])

    def write_csv(self, path: str | Path) -> None:
        """One row per scored grid point (an interrupted sweep keeps the ones done)."""
        names = [a.name for a in self.axes]
        with Path(path).open("w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow([*names, "mean_total_deg", "mean_heading_deg", "mean_inclination_deg",
                        *(f"total_deg[{Path(p).name}]" for p in self.files)])
            for i, point in enumerate(self.points):
                if not self.done[i]:
                    continue
                w.writerow([*(point[n] for n in names), self.mean_total[i],
                            self.heading[i].mean(), self.inclination[i].mean(),
                            *self.total[i]])

    def write_json(self, path: str | Path, extra: dict | None = None) -> None:
        """The sweep as JSON; ``extra`` adds top-level keys (the cross-validation)."""

        def clean(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        doc = {
            "estimator": self.estimator, "files": list(self.files), "fixed": self.fixed,
            "params": {a.name: a.values.tolist() for a in self.axes},
            "objective": f"mean {self.objective} RMSE [deg]",
            "best": self.best if self.done.any() else None,
            "best_mean_total_deg": (clean(self.mean_total[self.best_index])
                                    if self.done.any() else None),
            "best_mean_inclination_deg": (clean(self.inclination[self.best_index].mean())
                                          if self.done.any() else None),
            "seconds": self.seconds, "interrupted": self.interrupted,
            "points": [{"params": p, "mean_total_deg": clean(self.mean_total[i]),
                        "total_deg": [clean(v) for v in self.total[i]],
                        "inclination_deg": [clean(v) for v in self.inclination[i]]}
                       for i, p in enumerate(self.points) if self.done[i]],
            "notes": {f: list(self.notes_of(k)) for k, f in enumerate(self.files)},
            **(extra or {}),
        }
        Path(path).write_text(json.dumps(doc, indent=1), encoding="utf-8")


def damage_notes(rec: Recording) -> tuple[str, ...]:
    """The reader's notes on what the log lost, in the single-file replay's words: a
    score on a damaged log should not read as one on a whole log."""
    notes = list(rec.damage)
    if rec.cleanup.dropped:
        notes.append(f"dropped IMU samples: {rec.cleanup}")
    return tuple(notes)


# Set in the parent before the pool forks; workers read it instead of receiving arrays.
_PREPARED: list[Prepared] = []
_TASK: tuple[str, dict[str, float], str] = ("", {}, "sensors")


def _ignore_sigint() -> None:
    """Pool workers leave Ctrl-C to the parent, which stops the pool and keeps results."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def score_params(prep: Prepared, spec: EstimatorSpec, init: str) -> np.ndarray:
    """[total, heading, inclination] RMSE [deg] of one parameter set on one prepared file
    (NaN when the estimator refuses the values or never runs on a scored sample). The
    one scoring rule of every sweep: local (:func:`sweep`) and on a cluster
    (``replay.tune_tasks``)."""
    out = np.full(3, np.nan)
    try:
        run = run_estimator(prep, spec, init)
    except ValueError:  # e.g. a parameter value the estimator refuses
        return out
    keep = prep.scored & np.all(np.isfinite(run.q), axis=1)
    if keep.any():
        r = metrics.rms_errors(run.q[keep], prep.q_ref[keep])
        out[:] = (r.total_deg, r.heading_deg, r.inclination_deg)
    return out


def _score_point(index_params: tuple[int, dict[str, float]]) -> tuple[int, np.ndarray]:
    """(index, [[total, heading, inclination] per file]) for one grid point."""
    index, params = index_params
    name, fixed, init = _TASK
    spec = EstimatorSpec(name, {**fixed, **params})
    return index, np.array([score_params(prep, spec, init) for prep in _PREPARED]
                           ).reshape(len(_PREPARED), 3)


def grid_points(estimator: str, axes: Sequence[ParamAxis], fixed: dict[str, float]
                ) -> tuple[dict[str, float], ...]:
    """Every combination of the swept values, in the axes' order (the last varies
    fastest); unknown names, a parameter swept twice and a value the estimator refuses
    fail here, before any work."""
    cls = estimators.estimator_class(estimator)
    names = [a.name for a in axes]
    if len(set(names)) != len(names):
        raise ValueError(f"a parameter is swept twice: {names}")
    size = math.prod(len(a.values) for a in axes)
    if size > MAX_GRID_POINTS:
        raise ValueError(f"a grid of {size:,} points (at most {MAX_GRID_POINTS:,}): fewer "
                         f"values per --param, or tune in stages")
    both = sorted(set(names) & set(fixed))
    if both:
        raise ValueError(f"{', '.join(both)}: both swept (-p) and fixed (--set or "
                         f"-e {estimator}:...); give it one way")
    cls.make_params(**fixed)  # first alone: an error there is not the --param's
    for axis in axes:
        check_values(cls, axis, fixed)
    return tuple(dict(zip(names, map(float, combo), strict=True))
                 for combo in itertools.product(*(a.values for a in axes)))


def sweep(prepared: Sequence[Prepared], estimator: str, axes: Sequence[ParamAxis],
          fixed: dict[str, float] | None = None, jobs: int | None = None,
          init: str = "sensors", progress: bool = True) -> Sweep:
    """Score every grid point on every prepared file; ``jobs`` processes (default: cores).

    Ctrl-C (KeyboardInterrupt) stops the sweep: the result has ``interrupted`` set and
    ``done`` marks the points scored so far.
    """
    global _PREPARED, _TASK
    fixed = dict(fixed or {})
    points = grid_points(estimator, axes, fixed)
    if not prepared or not all(p.q_ref is not None and p.scored.any() for p in prepared):
        raise ValueError("every file needs a reference attitude to tune against")
    _PREPARED, _TASK = list(prepared), (estimator, fixed, init)
    jobs = workers_for(jobs, len(points))
    bar = Progress(len(points)) if progress else None
    results = np.full((len(points), len(prepared), 3), np.nan)
    done = np.zeros(len(points), dtype=bool)
    began = time.perf_counter()
    tasks = list(enumerate(points))
    interrupted = False
    try:
        i, r = _score_point(tasks[0])  # compile (or load the kernel cache) once, in the parent
        results[i], done[i] = r, True
        if bar:
            bar.advance()
        if jobs == 1:
            for task in tasks[1:]:
                i, r = _score_point(task)
                results[i], done[i] = r, True
                if bar:
                    bar.advance()
        else:
            with mp.get_context("fork").Pool(jobs, initializer=_ignore_sigint) as pool:
                chunk = max(1, len(tasks) // (jobs * 8))
                try:
                    for i, r in pool.imap_unordered(_score_point, tasks[1:], chunksize=chunk):
                        results[i], done[i] = r, True
                        if bar:
                            bar.advance()
                except KeyboardInterrupt:
                    pool.terminate()
                    raise
    except KeyboardInterrupt:
        interrupted = True
        if bar:
            bar.stream.write("\n")
    seconds = time.perf_counter() - began
    _PREPARED = []
    six_d = any(is_six_d(p.recording, estimator) for p in prepared)
    return Sweep(estimator, tuple(axes), fixed,
                 tuple(str(p.recording.path) for p in prepared), points,
                 results[:, :, 0], results[:, :, 1], results[:, :, 2], seconds,
                 "inclination" if six_d else "total", done, interrupted,
                 tuple(damage_notes(p.recording) for p in prepared))
