"""The ``attitude-bridge`` command: one sub-command per job.

Each sub-command lives with the code it drives and exposes
``register(subparsers) -> None``, which adds its parser and sets ``func`` (called
with the parsed arguments, returns the exit code).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

# Modules providing sub-commands, in the order `--help` lists them.
SUBCOMMAND_MODULES: tuple[str, ...] = (
    "estimators.cli",
    "hil.cli",
    "bridge.run_cli",
    "bridge.calibrate_cli",
    "replay.cli",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="attitude-bridge",
        description="MAVLink companion and HIL bridge for quadrotor attitude estimation.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in SUBCOMMAND_MODULES:
        importlib.import_module(module).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
