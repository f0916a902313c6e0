"""One log of a corpus replay: what a worker process runs, and all it sends back.

A task is a path and the options; the worker loads the log itself and returns a small
dict of scores (a few kB), never the time series. So a worker holds one log at a time
and its memory is bounded by the largest log, not by the corpus, whether the worker is
a local process or a Dask worker on another machine; and the parent holds only dicts.

The steps and their errors are the single-file replay's (``replay.cli``): the same
reader call, the same reference check, ``replay.evaluate.evaluate`` for every number,
and a log that fails gets the same one-line reason the single-file replay prints after
"error:". Wall times (``Score.run_s``) are left out: the summary must be the same on one
core, on a process pool and on a cluster.
"""

from __future__ import annotations

import contextlib
import io
import math
from dataclasses import dataclass
from pathlib import Path

from estimators.spec import EstimatorSpec
from imu.vehicles import type_name

from .dataset import ReplayInputError

DEBUG_ENV = "ATTITUDE_BRIDGE_DEBUG"
SCORED, NOT_SCORED, FAILED = "scored", "not scored", "failed"
#: Score fields that measure the machine, not the estimator: kept out of the summary.
TIMING_FIELDS = ("run_s",)


@dataclass(frozen=True)
class ReplayOptions:
    """The single-file replay's options that a worker needs (small, picklable)."""

    specs: tuple[EstimatorSpec, ...] | None = None  # None: evaluate's defaults
    board: str | None = None
    imu: str | None = None
    reference: str = "auto"
    init: str = "sensors"
    declination_deg: float | None = None
    aid: str = "auto"
    smooth: bool = False  # also the eskf smoothed over each log (replay --smooth)
    compare: tuple[str, ...] = ()  # reference filters beside ours (replay --compare)


def failure_reason(exc: BaseException) -> str:
    """The one line the single-file replay prints after "error:" for this exception."""
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
    text = " ".join((str(exc).strip() or type(exc).__name__).split())
    if isinstance(exc, ValueError | OSError):  # ReplayInputError is a ValueError
        return text
    return (f"internal error ({type(exc).__name__}: {text}); this is a bug: replay this log "
            f"alone with {DEBUG_ENV}=1 for the traceback")


def clean(value: object) -> object:
    """JSON-safe and comparable: NaN/inf become None (NaN != NaN would make two equal
    summaries compare unequal), recursively through dicts and lists."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [clean(v) for v in value]
    return value


def replay_log(display: str, load_path: str, options: ReplayOptions) -> dict:
    """Load and score one log; never raises for a bad log (the batch goes on).

    ``display`` is the path as the user gave it (what the summary shows and sorts by);
    ``load_path`` the one to open (absolute, for a worker whose working folder differs).
    A reason naming ``load_path`` is rewritten to ``display``, so it reads exactly as the
    single-file replay's, wherever the log was read.
    """
    from .cli import require_reference
    from .evaluate import evaluate
    from .readers import load

    entry: dict = {"file": display, "status": FAILED, "reason": None}
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # pyulog prints on damaged files
            rec = load(load_path, board=options.board, imu=options.imu,
                       reference=options.reference)
            require_reference(rec, options.reference)
            if options.init == "reference" and rec.reference is None:
                raise ReplayInputError(f"{load_path}: --init reference needs a reference "
                                       f"attitude")
            ev = evaluate(rec, list(options.specs) if options.specs else None,
                          init=options.init, declination_deg=options.declination_deg,
                          aid=options.aid, smooth=options.smooth,
                          compare=options.compare)
    except Exception as exc:  # one bad log must not stop the batch
        entry["reason"] = failure_reason(exc).replace(load_path, display)
        return entry
    prep = ev.prepared
    entry.update(
        format=rec.format, vehicle=type_name(rec.mav_type), samples=rec.n,
        duration_s=rec.duration, rate_hz=rec.rate_hz, reference=ev.reference_kind,
        estimators=_scores_json(ev.scores))
    if ev.vs_smoothed:  # no truth: every run against the smoothed one (labelled, per log)
        entry["vs_smoothed"] = {"reference": ev.smoothed_label + " (not truth)",
                                "estimators": _scores_json(ev.vs_smoothed)}
    scored = any(math.isfinite(s.total_deg) or math.isfinite(s.inclination_deg)
                 for s in ev.scores.values())
    if scored:
        entry["status"] = SCORED
    else:
        entry["status"] = NOT_SCORED
        entry["reason"] = (f"{ev.not_run}; estimators not run" if ev.not_run
                           else prep.unscored or "no estimator started on a scored sample")
    return clean(entry)


def warm(specs: tuple[EstimatorSpec, ...] = (), smooth: bool = True) -> None:
    """Make a worker ready for its first log: import the readers (pymavlink's dialect,
    pyulog) and load the estimators' compiled kernels (``specs``, default: replay's
    defaults; and the smoother's) by scoring a second of synthetic data. Loading them
    from numba's on-disk cache takes about a second, which otherwise lands in whichever
    log a fresh worker gets first. Never raises: it only saves time, and a real problem
    shows in the tasks that follow."""
    from .evaluate import default_specs, evaluate
    from .synthetic import SyntheticConfig, generate

    with contextlib.suppress(Exception):
        from pymavlink.dialects.v20 import ardupilotmega  # noqa: F401  (the tlog reader's)
        from pyulog import ULog  # noqa: F401  (the ULog reader's)

        from .readers import load  # noqa: F401
    with contextlib.suppress(Exception):
        evaluate(generate(SyntheticConfig(duration_s=1.0)), list(specs or default_specs()),
                 smooth=smooth)


def _scores_json(scores: dict) -> dict:
    return {label: {k: v for k, v in s.as_json().items() if k not in TIMING_FIELDS}
            for label, s in scores.items()}


def crashed(display: str, why: str) -> dict:
    """The entry of a log whose worker died or could not run it (not the log's fault
    as far as we know, but it has no scores)."""
    return {"file": display, "status": FAILED, "reason": why}


def absolute(path: Path) -> str:
    return str(path if path.is_absolute() else Path.cwd() / path)
