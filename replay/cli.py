"""``attitude-bridge replay`` and ``attitude-bridge tune`` (SPEC, "Offline tools")."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from .dataset import ReplayInputError

_REFERENCE_HELP = ("which reference to score against: auto (truth when the file has it, "
                   "else the autopilot's attitude), truth, autopilot")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay", help="run estimators over a log (ULog, tlog, BROAD npz, CSV) and score them",
        description="Replay a log through estimators in batch and score them against "
                    "truth when the file has it, else against the autopilot's attitude. "
                    "Default estimators: every registered one except the gyro-only "
                    "integrators (euler, dcm, quaternion).")
    p.add_argument("file", type=Path)
    p.add_argument("--estimator", "-e", action="append", default=[], metavar="NAME[:k=v,...]",
                   help="estimator with optional parameters; repeat to compare several")
    p.add_argument("--report", type=Path, metavar="OUT.html",
                   help="write a self-contained HTML report with figures")
    p.add_argument("--json", type=Path, metavar="OUT.json", help="write the scores as JSON")
    _input_options(p)
    p.set_defaults(func=_replay)

    t = sub.add_parser(
        "tune", help="grid-search one shared parameter set over one or many files",
        description="Search a parameter grid for the set minimising the mean total RMSE "
                    "over all files (one parameter set for all, as in BROAD).")
    t.add_argument("files", type=Path, nargs="+", metavar="FILE")
    t.add_argument("--estimator", "-e", required=True, help="estimator name")
    t.add_argument("--param", "-p", action="append", default=[], required=True,
                   metavar="NAME=LO:HI:N", help="swept parameter (LO:HI:N linspace, "
                   "or V1,V2,...); repeat for a multi-dimensional grid")
    t.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="fixed parameter applied at every grid point")
    t.add_argument("--jobs", "-j", type=int, default=None, help="processes (default: cores)")
    t.add_argument("--out", type=Path, metavar="SWEEP.csv|.json", help="write the sweep")
    t.add_argument("--heatmap", type=Path, metavar="OUT.png",
                   help="figure of mean total RMSE over the first two swept parameters")
    t.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    _input_options(t)
    t.set_defaults(func=_tune)


def _input_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--board", default="ardupilot",
                   help="RAW_IMU board profile for tlogs (imu.boards; default ardupilot)")
    p.add_argument("--imu", default=None, help="tlog IMU message (HIGHRES_IMU, RAW_IMU, "
                   "SCALED_IMU, SCALED_IMU2, SCALED_IMU3; default: first present in that order)")
    p.add_argument("--reference", choices=("auto", "truth", "autopilot"), default="auto",
                   help=_REFERENCE_HELP)
    p.add_argument("--init", choices=("sensors", "reference"), default="sensors",
                   help="start estimators from the first acc+mag sample (default, BROAD "
                        "rule) or from the reference attitude")


def _fail(command: str, exc: Exception) -> int:
    print(f"attitude-bridge {command}: error: {exc}", file=sys.stderr)
    return 2


def _load(path: Path, args: argparse.Namespace):
    from .readers import load

    return load(path, board=args.board, imu=args.imu, reference=args.reference)


def _replay(args: argparse.Namespace) -> int:
    from estimators.spec import EstimatorSpec

    from .evaluate import evaluate

    try:
        specs = [EstimatorSpec.parse(s) for s in args.estimator] or None
        rec = _load(args.file, args)
        if args.reference != "auto" and rec.reference is None:
            raise ReplayInputError(f"{args.file}: no {args.reference} attitude in this file")
        if args.init == "reference" and rec.reference is None:
            raise ReplayInputError(f"{args.file}: --init reference needs a reference attitude")
        ev = evaluate(rec, specs, init=args.init)
    except (ReplayInputError, ValueError) as exc:
        return _fail("replay", exc)
    _print_table(ev)
    if args.json:
        args.json.write_text(json.dumps(ev.as_json(), indent=1), encoding="utf-8")
    if args.report:
        from .report import write_report

        write_report([ev], args.report)
        print(f"report: {args.report}")
    return 0


def _print_table(ev) -> None:
    rec = ev.recording
    ref = rec.reference
    print(f"{rec.path}: {rec.format}, IMU {rec.source}, {rec.n} samples, {rec.duration:.1f} s "
          f"at {rec.rate_hz:.1f} Hz; reference: "
          + (f"{ref.kind} ({ref.source})" if ref else "none (nothing to score against)"))
    for note in rec.notes:
        print(f"  note: {note}")
    if rec.cleanup.dropped:
        print(f"  dropped IMU samples: {rec.cleanup}")
    cols = ("total_deg", "heading_deg", "inclination_deg", "lag_s", "convergence_s")
    width = max(12, *(len(k) for k in ev.scores))
    print(f"{'estimator':<{width}} " + " ".join(f"{c:>15}" for c in cols))
    for label, s in ev.scores.items():
        vals = [getattr(s, c) for c in cols]
        print(f"{label:<{width}} " + " ".join(
            f"{v:15.3f}" if math.isfinite(v) else f"{'-':>15}" for v in vals))


def _tune(args: argparse.Namespace) -> int:
    from estimators.spec import EstimatorSpec

    from .evaluate import prepare
    from .tune import parse_param, sweep

    try:
        axes = [parse_param(p) for p in args.param]
        fixed = EstimatorSpec.parse(f"{args.estimator}:{','.join(args.set)}").params
        prepared = []
        for path in args.files:
            prep = prepare(_load(path, args))
            if prep.q_ref is None or not prep.scored.any():
                raise ReplayInputError(f"{path}: no reference attitude to tune against")
            prepared.append(prep)
        result = sweep(prepared, args.estimator, axes, fixed, jobs=args.jobs,
                       init=args.init, progress=not args.quiet)
        best = result.best
    except (ReplayInputError, ValueError) as exc:
        return _fail("tune", exc)
    i = result.best_index
    print(f"{len(result.points)} parameter sets x {len(prepared)} file(s) in "
          f"{result.seconds:.1f} s")
    print(f"best {args.estimator}: " + ", ".join(f"{k}={v:.6g}" for k, v in best.items())
          + f"  mean total {result.mean_total[i]:.3f} deg (heading "
          f"{result.heading[i].mean():.3f}, inclination {result.inclination[i].mean():.3f})"
          + ("  [6D: minimised inclination]" if result.objective == "inclination" else ""))
    for path, total in zip(result.files, result.total[i], strict=True):
        print(f"  {Path(path).name}: total {total:.3f} deg")
    if args.out:
        (result.write_json if args.out.suffix.lower() == ".json" else result.write_csv)(args.out)
        print(f"sweep: {args.out}")
    if args.heatmap:
        from .report import save_png, sweep_figure

        save_png(sweep_figure(result), args.heatmap)
        print(f"heatmap: {args.heatmap}")
    return 0
