"""``tune --scheduler``: the sweep as tasks on a Dask cluster, one log (or a share of the
grid on one log) per task.

The local sweep (``replay.tune.sweep``) loads every log in the parent and forks workers
that score grid points; a cluster's workers share no memory with the client, so here a
task is a path, the options and a list of grid points: the worker loads the log itself
and returns a (points, 3) array of scores. A log is split into several tasks only when
there are too few logs to keep a cluster busy (each share loads the log again).

Every number comes from ``replay.tune.score_params``, the local sweep's own rule, and
the result is an ordinary ``Sweep`` in the same file order: the same sweep, bit for bit,
as ``--jobs``, and the same cross-validation.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estimators.spec import EstimatorSpec

from .corpus_task import absolute, failure_reason
from .dataset import ReplayInputError
from .evaluate import Prepared
from .parallel import run
from .progress import Progress
from .tune import ParamAxis, Sweep, damage_notes, grid_points, score_params

#: Aim for at least this many tasks (a log's grid is split when there are fewer logs) ...
MIN_TASKS = 32
#: ... but never give a task fewer grid points than this (each task loads its log).
MIN_POINTS_PER_TASK = 8


@dataclass(frozen=True)
class TuneInputs:
    """How to read the logs (the replay's input options)."""

    board: str | None = None
    imu: str | None = None
    reference: str = "auto"
    declination_deg: float | None = None
    aid: str = "auto"


def tunable(prep: Prepared, path: object) -> Prepared:
    """The prepared log, or the error ``tune`` gives for a log it cannot tune on."""
    if prep.q_ref is None or not prep.scored.any():
        raise ReplayInputError(f"{path}: no reference attitude to tune against"
                               + (f" ({prep.unscored})" if prep.unscored else ""))
    return prep


def unusable(display: str, exc: BaseException, load_path: str | None = None) -> str:
    """Why a log cannot be tuned on, naming it once, as the user gave it (a worker
    loads it at ``load_path``, its absolute path)."""
    text = failure_reason(exc)
    if load_path:
        text = text.replace(load_path, display)
    return text if display in text else f"{display}: {text}"


def prepare_log(path: str, inputs: TuneInputs) -> Prepared:
    from .cli import require_reference
    from .evaluate import prepare
    from .readers import load

    rec = load(path, board=inputs.board, imu=inputs.imu, reference=inputs.reference)
    require_reference(rec, inputs.reference)
    return tunable(prepare(rec, declination_deg=inputs.declination_deg, aid=inputs.aid), path)


def sweep_share(display: str, load_path: str, inputs: TuneInputs, estimator: str,
                fixed: dict[str, float], points: tuple[dict[str, float], ...], init: str
                ) -> dict:
    """Scores of ``points`` on one log: {"scores": (P, 3), "six_d", "notes"} (the
    reader's damage notes) or {"error"}."""
    from .evaluate import is_six_d

    try:
        prep = prepare_log(load_path, inputs)
    except Exception as exc:
        return {"error": unusable(display, exc, load_path)}
    scores = np.array([score_params(prep, EstimatorSpec(estimator, {**fixed, **p}), init)
                       for p in points]).reshape(len(points), 3)
    return {"scores": scores, "six_d": is_six_d(prep.recording, estimator),
            "notes": damage_notes(prep.recording)}


def shares(n_points: int, n_logs: int) -> list[slice]:
    """How a log's grid is cut into tasks (see MIN_TASKS / MIN_POINTS_PER_TASK)."""
    want = math.ceil(MIN_TASKS / max(n_logs, 1))
    k = max(1, min(want, n_points // MIN_POINTS_PER_TASK))
    edges = np.linspace(0, n_points, k + 1).round().astype(int)
    return [slice(int(a), int(b)) for a, b in itertools.pairwise(edges.tolist())]


def sweep_on_cluster(files: Sequence[Path], inputs: TuneInputs, estimator: str,
                     axes: Sequence[ParamAxis], fixed: dict[str, float], init: str,
                     scheduler: str, progress: bool = True) -> tuple[Sweep, list[str]]:
    """The sweep of ``replay.tune.sweep``, computed by the workers at ``scheduler``, over
    the logs a worker could tune on, and the reasons the others were left out (in file
    order). Raises ReplayInputError when no log is left."""
    points = grid_points(estimator, axes, fixed)  # bad names fail here, before any work
    cuts = shares(len(points), len(files))
    tasks = [(str(f), absolute(Path(f)), inputs, estimator, dict(fixed), points[c], init)
             for f in files for c in cuts]
    bar = Progress(len(tasks)) if progress else None
    began = time.perf_counter()
    outcome = run(sweep_share, tasks, scheduler=scheduler,
                  on_crash=lambda task, why: {"error": f"{task[0]}: {why}"},
                  on_done=lambda i, r: bar.advance() if bar else None)
    if outcome.interrupted and bar is not None:
        bar.interrupt()
    per_file = [outcome.results[f * len(cuts):(f + 1) * len(cuts)] for f in range(len(files))]
    errors = [next((r["error"] for r in rs if r is not None and "error" in r), None)
              for rs in per_file]
    kept = [f for f, e in enumerate(errors) if e is None]
    left_out = [e for e in errors if e is not None]
    if not kept:
        raise ReplayInputError(no_log_left(left_out))
    results = np.full((len(points), len(kept), 3), np.nan)
    done = np.ones(len(points), dtype=bool)
    six_d = False
    notes: list[tuple[str, ...]] = []
    for column, f in enumerate(kept):
        for c, r in enumerate(per_file[f]):
            if r is None:
                done[cuts[c]] = False
                continue
            results[cuts[c], column] = r["scores"]
            six_d |= bool(r["six_d"])
        notes.append(next((tuple(r["notes"]) for r in per_file[f] if r is not None), ()))
    sweep = Sweep(estimator, tuple(axes), dict(fixed), tuple(str(files[f]) for f in kept),
                  points, results[:, :, 0], results[:, :, 1], results[:, :, 2],
                  time.perf_counter() - began, "inclination" if six_d else "total", done,
                  outcome.interrupted, tuple(notes))
    return sweep, left_out


def no_log_left(reasons: Sequence[str]) -> str:
    """The error when every log was left out: the first reasons, and how many more."""
    more = f" (and {len(reasons) - 3} more)" if len(reasons) > 3 else ""
    return (reasons[0] if len(reasons) == 1
            else "no log to tune on: " + "; ".join(reasons[:3]) + more)
