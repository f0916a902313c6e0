"""The ``attitude-bridge`` command: one sub-command per job, one error boundary for all.

Each sub-command lives with the code it drives and exposes
``register(subparsers) -> None``, which adds its parser and sets ``func`` (called
with the parsed arguments, returns the exit code).

Whatever a user can get wrong — a file that is not there, a port in use, a host that
does not resolve, a bad value in a settings file — raises ``ValueError`` or ``OSError``
with a message that names the culprit. :func:`main` turns those into one line on
stderr and exit code 2, whichever sub-command raised them, so no expected failure ever
ends in a traceback. Anything else is a bug: one line saying so (exit code 1), and the
traceback with ``ATTITUDE_BRIDGE_DEBUG=1``.
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import sys
from collections.abc import Sequence
from typing import NoReturn

#: Each sub-command and the module that registers it, in the order `--help` lists them.
#: Only the module of the command given is imported: together they load numpy, numba,
#: pymavlink and every estimator (most of a second of CPU), which ``health``, the
#: container's HEALTHCHECK run every 30 s beside the bridge, does not need.
SUBCOMMANDS: dict[str, str] = {
    "estimators": "estimators.cli",
    "hil": "hil.cli",
    "run": "bridge.app.run_cli",
    "demo": "bridge.app.run_cli",
    "calibrate": "bridge.app.calibrate_cli",
    "replay": "replay.cli",
    "tune": "replay.cli",
    "warmup": "bridge.app.warmup",
    "health": "bridge.app.health",
}

EXIT_USAGE = 2  # bad input: the user can fix it (argparse uses 2 too)
EXIT_BUG = 1
EXIT_INTERRUPTED = 130  # as a shell reports SIGINT
DEBUG_ENV = "ATTITUDE_BRIDGE_DEBUG"


def version_text() -> str:
    """The installed version, with the versions that matter for a bug report."""
    from importlib import metadata

    def v(dist: str) -> str:
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return "not installed"

    return (f"attitude-bridge {v('attitude-bridge')} (python {sys.version.split()[0]}, "
            f"numpy {v('numpy')}, numba {v('numba')}, pymavlink {v('pymavlink')})")


class _Version(argparse.Action):
    """``--version``: print on one line (argparse's own action wraps it) and exit."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS,
                 **kwargs: object) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS,
                         help="print the version (and those of its main libraries) and exit")

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        print(version_text())
        parser.exit()


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are one line, like every other input error.

    argparse prints the whole usage before the message: dozens of lines for ``run``,
    which bury the one that says what is wrong. Sub-command parsers inherit the class.
    """

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def seconds(text: str) -> float:
    """argparse type of a duration, timeout or age: finite seconds, >= 0.

    ``float`` alone takes "nan", "inf" and "-5": ``hil --duration nan`` then streamed
    for ever (NaN > 0 is false, which reads as "no limit") and ``health --max-age nan``
    called any status file fresh. Whether 0 is allowed is the option's own business.
    """
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") \
            from None
    if not math.isfinite(value) or value < 0.0:
        raise argparse.ArgumentTypeError(
            f"must be a finite number of seconds >= 0, got {text!r}")
    return value


def command_in(argv: Sequence[str]) -> str | None:
    """The sub-command ``argv`` starts with; None when it starts with an option (``-h``
    and ``--version`` answer for every command, ``-h run`` included)."""
    return argv[0] if argv and not argv[0].startswith("-") else None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser for ``command`` alone when it is one (see ``SUBCOMMANDS``), else for
    every command (``--help``, ``--version``, a misspelt command's error)."""
    parser = OneLineParser(
        prog="attitude-bridge",
        description="MAVLink companion and HIL bridge for quadrotor attitude estimation.")
    parser.add_argument("--version", action=_Version)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules = ([SUBCOMMANDS[command]] if command in SUBCOMMANDS
               else dict.fromkeys(SUBCOMMANDS.values()))
    for module in modules:
        importlib.import_module(module).register(sub)
    return parser


def describe_error(exc: BaseException) -> str:
    """One line for an expected failure: what, and which file or address."""
    if isinstance(exc, OSError) and exc.strerror:
        name = exc.filename if exc.filename is not None else ""
        return f"{name}: {exc.strerror}" if name else exc.strerror
    text = str(exc).strip() or type(exc).__name__
    return " ".join(text.split())  # never more than one line


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    try:  # imports the command's module: Ctrl-C can come this early
        parser = build_parser(command_in(argv))
    except KeyboardInterrupt:
        print("attitude-bridge: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    prog = f"attitude-bridge {args.command}"
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (ValueError, OSError) as exc:
        if os.environ.get(DEBUG_ENV):
            raise
        print(f"{prog}: error: {describe_error(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except Exception as exc:
        if os.environ.get(DEBUG_ENV):
            raise
        print(f"{prog}: internal error ({type(exc).__name__}: {describe_error(exc)}); "
              f"this is a bug: {DEBUG_ENV}=1 shows the traceback", file=sys.stderr)
        return EXIT_BUG


if __name__ == "__main__":
    sys.exit(main())
