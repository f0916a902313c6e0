"""``attitude-bridge replay`` and ``attitude-bridge tune`` (SPEC, "Offline tools")."""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
from pathlib import Path

from bridge.app.config_checks import check_output_file as check_writable_file
from bridge.app.config_checks import check_outputs

from .dataset import ReplayInputError

_REFERENCE_HELP = ("which reference to score against: auto (truth when the file has it, "
                   "else the autopilot's attitude), truth, autopilot")
INTERRUPTED = 130  # exit code after Ctrl-C, as a shell reports SIGINT


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay", help="run estimators over a log (ULog, tlog, BROAD npz, CSV) and score them",
        description="Replay a log through estimators in batch and score them against "
                    "truth when the file has it, else against the autopilot's attitude. "
                    "Default estimators: every registered one except the gyro-only "
                    "integrators (euler, dcm, quaternion). Several logs (files, folders: "
                    "every log inside, recursively; quoted glob patterns) are a corpus: "
                    "replayed in parallel, one summary per log, per estimator, per vehicle "
                    "type and per flight phase; a log that fails is reported with its "
                    "reason and the rest go on (exit 0 if any log was scored, else 2).")
    p.add_argument("paths", type=path_argument, nargs="+", metavar="PATH",
                   help="a log file; or several files, folders, patterns (a corpus)")
    p.add_argument("--estimator", "-e", action="append", default=[], metavar="NAME[:k=v,...]",
                   help="estimator with optional parameters; repeat to compare several")
    p.add_argument("--smooth", action="store_true",
                   help="also the eskf smoothed over the whole recording (forward, then "
                        "back: the best attitude the log allows); without a truth in the "
                        "log, every estimator and the autopilot are also scored against it "
                        "(labelled: it is not truth)")
    p.add_argument("--compare", action="append", default=[], metavar="NAME[,NAME...]",
                   help="also run other people's filters on the same samples and score "
                        "them the same way: vqf (online), vqf-offline (sees the whole "
                        "log), imufusion (needs the 'compare' extra)")
    p.add_argument("--report", type=Path, metavar="OUT.html",
                   help="write a self-contained interactive HTML report (needs the "
                        "'report' extra: bokeh); a corpus: the summary's tables and a "
                        "box chart per estimator")
    p.add_argument("--json", type=Path, metavar="OUT.json",
                   help="write the scores as JSON (a corpus: the summary)")
    p.add_argument("--csv", type=Path, metavar="OUT.csv",
                   help="write the time series (t, q and Euler per estimator, reference, "
                        "errors, flags) for PlotJuggler or pandas; a corpus: one row of "
                        "scores per log")
    p.add_argument("--png", type=Path, metavar="DIR",
                   help="write the figures as PNG files into DIR (needs matplotlib); one "
                        "log only, refused for a corpus")
    p.add_argument("--jobs", "-j", type=int, default=None,
                   help="several logs: processes (default: cores)")
    p.add_argument("--quiet", "-q", action="store_true",
                   help="several logs: no progress bar")
    _scheduler_option(p)
    _input_options(p)
    p.set_defaults(func=_replay)

    t = sub.add_parser(
        "tune", help="grid-search one shared parameter set over one or many files",
        description="Search a parameter grid for the set minimising the mean total RMSE "
                    "over all files (one parameter set for all, as in BROAD). Ctrl-C "
                    "stops early and keeps the points done so far.")
    t.add_argument("files", type=path_argument, nargs="+", metavar="PATH",
                   help="log files, folders (every log inside, recursively), patterns")
    t.add_argument("--estimator", "-e", required=True, metavar="NAME[:k=v,...]",
                   help="estimator, with parameters fixed at every grid point")
    t.add_argument("--param", "-p", action="append", default=[], required=True,
                   metavar="NAME=LO:HI:N", help="swept parameter (LO:HI:N linspace, "
                   "or V1,V2,...); repeat for a multi-dimensional grid")
    t.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="fixed parameter applied at every grid point")
    t.add_argument("--jobs", "-j", type=int, default=None, help="processes (default: cores)")
    t.add_argument("--out", type=Path, metavar="SWEEP.csv|.json", help="write the sweep")
    t.add_argument("--heatmap", type=Path, metavar="OUT.png",
                   help="figure of mean total RMSE over the first two swept parameters")
    t.add_argument("--quiet", "-q", action="store_true",
                   help="no progress bar, no per-log damage notes (--out JSON keeps them)")
    t.add_argument("--cross-validate", action="store_true",
                   help="also choose the grid point on all logs but one (or one group) and "
                        "score it on the held-out one: the cross-validated error beside "
                        "the in-sample one (computed from the same sweep)")
    t.add_argument("--group-by", choices=("log", "folder"), default="log",
                   help="with --cross-validate: hold out one log (default) or one folder "
                        "of logs at a time")
    _scheduler_option(t)
    _input_options(t)
    t.set_defaults(func=_tune)


def _scheduler_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT", default=None,
                   help="run on this Dask cluster instead of local processes (replay: "
                        "with several logs; extra 'cluster'; every worker reads the logs at "
                        "the same paths)")


def _input_options(p: argparse.ArgumentParser) -> None:
    from imu.boards import PROFILES

    p.add_argument("--board", default=None, choices=sorted(PROFILES),
                   help="RAW_IMU board profile for tlogs (default: detected, the profile "
                        "that gives 1 g at rest)")
    p.add_argument("--imu", default=None, help="tlog IMU message (HIGHRES_IMU, RAW_IMU, "
                   "SCALED_IMU, SCALED_IMU2, SCALED_IMU3; default: first present in that order)")
    p.add_argument("--reference", choices=("auto", "truth", "autopilot"), default="auto",
                   help=_REFERENCE_HELP)
    p.add_argument("--init", choices=("sensors", "reference"), default="sensors",
                   help="start estimators from the first acc+mag sample (default, BROAD "
                        "rule) or from the reference attitude")
    p.add_argument("--declination-deg", type=float, default=None, metavar="DEG",
                   help="magnetic declination, east positive (default: the vehicle's "
                        "EKF2_MAG_DECL / COMPASS_DEC, else the World Magnetic Model at the "
                        "log's position and date)")
    p.add_argument("--aid", choices=("velocity", "none"), default=None,
                   help="velocity aiding from the log (default: velocity when the log has it)")


def path_argument(text: str) -> Path:
    """argparse's type for PATH: an empty one refused in argparse's one line (as a Path
    it would already be ".", the current folder, replayed whole)."""
    from .logpaths import log_path

    try:
        return log_path(text)
    except ReplayInputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def check_jobs(jobs: int | None) -> None:
    """``--jobs`` below 1 refused, as the corpus replay refuses it, also where it would
    not be used (one log replays in this process) or be read as "every core" (tune)."""
    from .parallel import workers_for

    workers_for(jobs, 1)


def check_scheduler_address(address: str | None) -> None:
    """A ``--scheduler`` that is no address refused also where one log runs here."""
    if address is not None:
        from .cluster import check_address

        check_address(address)


def _fail(command: str, exc: Exception | str) -> int:
    print(f"attitude-bridge {command}: error: {exc}", file=sys.stderr)
    return 2


def _load(path: Path, args: argparse.Namespace):
    from .readers import load

    rec = load(path, board=args.board, imu=args.imu, reference=args.reference)
    require_reference(rec, args.reference)
    return rec


def require_reference(rec, wanted: str) -> None:
    """The reference asked for was loaded ("auto": any, or none); else an error naming
    the file and the references it has: scoring against another kind instead would
    answer another question without saying so."""
    if wanted == "auto" or (rec.reference is not None and rec.reference.kind == wanted):
        return
    raise ReplayInputError(f"{rec.path}: no {wanted} attitude in this file (references it "
                           f"has: {', '.join(rec.references) or 'none'})")


def check_output_file(path: Path | None, option: str) -> None:
    """Refuse an output path before any work: its folder must exist and be writable."""
    if path is not None:  # (a ValueError, which every command here reports in one line)
        check_writable_file(path, option)


def check_output_dir(path: Path | None, option: str) -> None:
    """A folder to write into: it exists, or its parent does (it is created then)."""
    if path is None:
        return
    if path.exists() and not path.is_dir():
        raise ReplayInputError(f"{option} {path}: exists and is not a folder")
    if not path.exists():
        check_output_file(path, option)
    elif not os.access(path, os.W_OK):
        raise ReplayInputError(f"{option} {path}: folder is not writable")


def require_module(module: str, option: str) -> None:
    if importlib.util.find_spec(module) is None:
        raise ReplayInputError(f"{option} needs {module}: pip install 'attitude-bridge[report]'")


def compared_references(args: argparse.Namespace) -> tuple[str, ...]:
    """``--compare``'s reference filters, checked (names, packages) before any work."""
    from .references import check_available, parse_compare

    names = parse_compare(args.compare)
    check_available(names)
    return names


def _replay(args: argparse.Namespace) -> int:
    from estimators.spec import EstimatorSpec

    from .evaluate import evaluate
    from .logpaths import is_corpus

    if is_corpus(args.paths):
        from .corpus_cli import replay_corpus

        return replay_corpus(args)
    args.file = args.paths[0]
    try:
        check_jobs(args.jobs)
        check_scheduler_address(args.scheduler)
        check_outputs(((args.report, "--report"), (args.json, "--json"),
                       (args.csv, "--csv")), [Path(args.file)])
        check_output_dir(args.png, "--png")
        if args.report:
            require_module("bokeh", "--report")
        if args.png:
            require_module("matplotlib", "--png")
        specs = [EstimatorSpec.parse(s) for s in args.estimator] or None
        compare = compared_references(args)
        rec = _load(args.file, args)
        if args.init == "reference" and rec.reference is None:
            raise ReplayInputError(f"{args.file}: --init reference needs a reference attitude")
        ev = evaluate(rec, specs, init=args.init, declination_deg=args.declination_deg,
                      aid=args.aid or "auto", smooth=args.smooth, compare=compare)
    except (ReplayInputError, ValueError) as exc:
        return _fail("replay", exc)
    from .summary import print_summary

    print_summary(ev)
    try:
        if args.json:
            args.json.write_text(json.dumps(ev.as_json(), indent=1), encoding="utf-8")
            print(f"json: {args.json}")
        if args.csv:
            from .timeseries import write_csv

            write_csv(ev, args.csv)
            print(f"csv: {args.csv}")
        if args.report:
            from .report import write_report

            write_report([ev], args.report)
            print(f"report: {args.report}")
        if args.png:
            from .figures import write_pngs

            for path in write_pngs(ev, args.png):
                print(f"png: {path}")
    except OSError as exc:  # disk full, permissions changed meanwhile
        return _fail("replay", f"cannot write output: {exc}")
    return 0


def _tune(args: argparse.Namespace) -> int:
    from estimators.spec import EstimatorSpec

    from .crossval import check_groups, cross_validate, identical_logs
    from .evaluate import prepare
    from .logpaths import expand
    from .tune import library_axis, parse_param, sweep
    from .tune_tasks import TuneInputs, no_log_left, sweep_on_cluster, tunable, unusable

    try:
        check_jobs(args.jobs)
        check_outputs(((args.out, "--out"), (args.heatmap, "--heatmap")),
                      expand(args.files))
        if args.heatmap:
            require_module("matplotlib", "--heatmap")
        if args.group_by != "log" and not args.cross_validate:
            raise ReplayInputError("--group-by goes with --cross-validate")
        # -e NAME[:k=v,...] and --set k=v both fix parameters (the swept ones excepted)
        spec = EstimatorSpec.parse(args.estimator)
        axes = [library_axis(parse_param(p), spec.name) for p in args.param]
        extra = EstimatorSpec.parse(f"{spec.name}:{','.join(args.set)}").params
        twice = sorted(set(spec.params) & set(extra))
        if twice:
            raise ReplayInputError(f"{', '.join(twice)}: given in -e and in --set")
        fixed = {**spec.params, **extra}
        args.estimator = spec.name
        files = expand(args.files)
        if args.cross_validate:
            check_groups([str(f) for f in files], args.group_by)
            for same in identical_logs([str(f) for f in files]):
                print(f"attitude-bridge tune: {', '.join(same)} have the same content: "
                      f"held out together", file=sys.stderr)
        if args.scheduler:
            inputs = TuneInputs(args.board, args.imu, args.reference, args.declination_deg,
                                args.aid or "auto")
            result, left_out = sweep_on_cluster(files, inputs, args.estimator, axes, fixed,
                                                args.init, args.scheduler,
                                                progress=not args.quiet)
            prepared = result.files
        else:
            prepared, left_out = [], []
            for path in files:
                try:
                    prepared.append(tunable(prepare(_load(path, args),
                                                    declination_deg=args.declination_deg,
                                                    aid=args.aid or "auto"), path))
                except (ReplayInputError, ValueError, OSError) as exc:
                    left_out.append(unusable(str(path), exc))
            if not prepared:
                raise ReplayInputError(no_log_left(left_out))
        for reason in left_out:  # a corpus goes on without its unusable logs, saying so
            print(f"attitude-bridge tune: left out {reason}", file=sys.stderr)
        if args.cross_validate and left_out:
            check_groups([str(f) for f in prepared], args.group_by)
        if not args.scheduler:
            result = sweep(prepared, args.estimator, axes, fixed, jobs=args.jobs,
                           init=args.init, progress=not args.quiet)
        dead = result.unscored_files()
        if dead:  # a log the estimator never ran on, at any grid point
            why = (f"{args.estimator} never ran on a scored sample at any grid point (no "
                   f"usable gyro or accelerometer where the reference is)")
            if len(dead) == len(result.files):
                raise ReplayInputError(f"{', '.join(dead)}: {why}")
            result = result.without(dead)
            left_out += [f"{f}: {why}" for f in dead]
            for f in dead:
                print(f"attitude-bridge tune: left out {f}: {why}", file=sys.stderr)
            if args.cross_validate:
                check_groups(list(result.files), args.group_by)
        done = int(result.done.sum())
        if result.interrupted:
            print(f"interrupted: {done} of {len(result.points)} parameter sets done",
                  file=sys.stderr)
        best = result.best if done else None
        cv = cross_validate(result, args.group_by) if args.cross_validate and done else None
    except KeyboardInterrupt:  # while loading, before any point was scored
        print("attitude-bridge tune: interrupted before any parameter set was scored",
              file=sys.stderr)
        return INTERRUPTED
    except (ReplayInputError, ValueError) as exc:
        return _fail("tune", exc)
    print(f"{done} parameter sets x {len(result.files)} file(s) in {result.seconds:.1f} s"
          + (f" ({len(left_out)} left out: see above)" if left_out else ""))
    if best is not None:
        i = result.best_index
        print(f"best {args.estimator}: " + ", ".join(f"{k}={v:.6g}" for k, v in best.items())
              + f"  mean total {result.mean_total[i]:.3f} deg (heading "
              f"{result.heading[i].mean():.3f}, inclination {result.inclination[i].mean():.3f})"
              + ("  [6D: minimised inclination]" if result.objective == "inclination" else ""))
        for k, (path, total) in enumerate(zip(result.files, result.total[i], strict=True)):
            print(f"  {Path(path).name}: total {total:.3f} deg")
            if not args.quiet:  # what the log lost: its score is on what is left
                for note in result.notes_of(k):
                    print(f"    note: {note}")
    if cv is not None:
        print("\n".join(cv.lines()))
    try:
        if args.out and args.out.suffix.lower() == ".json":
            result.write_json(args.out, {"left_out": left_out,
                                         **({"cross_validation": cv.as_json()} if cv else {})})
            print(f"sweep: {args.out}")
        elif args.out:
            result.write_csv(args.out)
            print(f"sweep: {args.out}")
        if args.heatmap and done:
            from .figures import save_png, sweep_figure

            save_png(sweep_figure(result), args.heatmap)
            print(f"heatmap: {args.heatmap}")
    except OSError as exc:
        return _fail("tune", f"cannot write output: {exc}")
    return INTERRUPTED if result.interrupted else 0
