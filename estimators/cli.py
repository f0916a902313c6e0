"""``attitude-bridge estimators``: list estimators and their parameters."""

from __future__ import annotations

import argparse

from .registry import estimator_class, names


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("estimators", help="list estimators and their parameters")
    p.add_argument("name", nargs="?", help="show this estimator's parameters")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    for name in [args.name] if args.name else names():
        cls = estimator_class(name)
        print(f"{name}: {(cls.__doc__ or '').strip().splitlines()[0]}")
        if args.name:
            for key, doc in cls.param_docs().items():
                print(f"    {key} = {doc}")
    return 0
