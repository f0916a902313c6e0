"""``attitude-bridge replay PATH...`` with several logs: the corpus replay.

Each log is one task (``replay.corpus_task``) run on this machine's cores (``--jobs``)
or on a Dask cluster (``--scheduler``), the largest files first (a long log started
last would leave the other workers idle at the end); a log that cannot be read or scored
is reported with its one-line reason and the batch goes on. One summary
(``replay.corpus_summary``) goes to stdout, and to ``--json`` / ``--csv`` /
``--report``. Exit code 0 when at least one log was scored, 2 when none was (or the
input was at fault before any work), 130 after Ctrl-C (the summary then covers the logs
done).

Options of the single-file replay that describe one log's time series have no corpus
meaning and are refused (``SINGLE_FILE_ONLY``); ``--json``, ``--csv`` and ``--report``
take the corpus meaning (the summary, the per-log table, the summary page).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from bridge.app.config_checks import check_outputs
from estimators.spec import EstimatorSpec

from .cli import INTERRUPTED, compared_references, require_module
from .corpus_summary import CorpusSummary, summarise
from .corpus_task import FAILED, ReplayOptions, absolute, crashed, replay_log, warm
from .dataset import ReplayInputError
from .logpaths import expand
from .parallel import run
from .progress import Progress
from .references import reference_labels

#: option -> why it does not apply to several logs
SINGLE_FILE_ONLY = {"png": "--png writes one replay's figures"}


def _fail(exc: Exception | str) -> int:
    print(f"attitude-bridge replay: error: {exc}", file=sys.stderr)
    return 2


def check_options(args: argparse.Namespace) -> None:
    """Refuse what has no meaning for several logs, and bad outputs, before any work."""
    for name, why in SINGLE_FILE_ONLY.items():
        if getattr(args, name, None):
            raise ReplayInputError(f"{why}: give one log, not several (for several: "
                                   f"--json, --csv or --report)")
    check_outputs(((args.report, "--report"), (args.json, "--json"), (args.csv, "--csv")),
                  expand(args.paths))
    if args.report:
        require_module("bokeh", "--report")
    if args.scheduler:
        from .cluster import check_address, require_dask

        require_dask()
        check_address(args.scheduler)


def options_from(args: argparse.Namespace) -> ReplayOptions:
    """The workers' options; the estimators checked here (a typo is one error, not one
    failure per log) and named explicitly, so every worker runs the same list."""
    import estimators

    from .evaluate import default_specs

    specs = [EstimatorSpec.parse(s) for s in args.estimator] or default_specs()
    for spec in specs:  # unknown names and parameters fail here
        estimators.estimator_class(spec.name).make_params(**spec.params)
    return ReplayOptions(tuple(specs), args.board, args.imu, args.reference, args.init,
                         args.declination_deg, args.aid or "auto", args.smooth,
                         compared_references(args))


def _size(path: Path) -> int:
    """Bytes on disk: a log's work is about proportional to it (0 when unreadable)."""
    try:
        return path.stat().st_size
    except OSError:
        return 0


def replay_corpus(args: argparse.Namespace) -> int:
    try:
        check_options(args)
        options = options_from(args)
        logs = expand(args.paths)
    except (ReplayInputError, ValueError) as exc:
        return _fail(exc)
    tasks = [(str(p), absolute(p), options) for p in logs]
    sizes = [_size(p) for p in logs]
    largest_first = sorted(range(len(logs)), key=lambda i: (-sizes[i], i))
    bar = None if args.quiet else Progress(len(tasks), count_failed=True)
    began = time.perf_counter()

    def done(_: int, entry: dict) -> None:
        if bar is not None:
            bar.advance(failed=entry["status"] == FAILED)

    try:
        outcome = run(replay_log, tasks, on_crash=lambda task, why: crashed(task[0], why),
                      jobs=args.jobs, scheduler=args.scheduler, on_done=done,
                      warm=lambda: warm(options.specs, options.smooth),
                      order=largest_first, weights=sizes)
    except (ReplayInputError, ValueError) as exc:  # the cluster: no Dask, no scheduler
        return _fail(exc)
    seconds = time.perf_counter() - began
    if outcome.interrupted and bar is not None:
        bar.interrupt()
    summary = summarise([r for r in outcome.results if r is not None],
                        [s.label for s in options.specs] + reference_labels(options.compare))
    for line in summary.lines():
        print(line)
    if outcome.interrupted:
        print(f"interrupted: {outcome.done} of {len(tasks)} logs done", file=sys.stderr)
    elif not args.quiet:
        where = f"on {args.scheduler}" if args.scheduler else f"--jobs {args.jobs or 'all'}"
        print(f"{len(tasks)} logs in {seconds:.1f} s ({len(tasks) / seconds:.2f} logs/s, "
              f"{where})", file=sys.stderr)
    try:
        _write_outputs(args, summary)
    except OSError as exc:  # disk full, permissions changed meanwhile
        return _fail(f"cannot write output: {exc}")
    if outcome.interrupted:
        return INTERRUPTED
    if not summary.scored:
        return _fail(f"no log was scored ({len(summary.with_status(FAILED))} failed, "
                     f"{len(summary.logs) - len(summary.with_status(FAILED))} not scored)")
    return 0


def _write_outputs(args: argparse.Namespace, summary: CorpusSummary) -> None:
    import json

    if args.json:
        args.json.write_text(json.dumps(summary.as_json(), indent=1), encoding="utf-8")
        print(f"json: {args.json}")
    if args.csv:
        summary.write_csv(args.csv)
        print(f"csv: {args.csv}")
    if args.report:
        from .corpus_report import write_report

        write_report(summary, args.report)
        print(f"report: {args.report}")
