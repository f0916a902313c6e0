"""``attitude-bridge estimators``: list estimators and their parameters."""

from __future__ import annotations

import argparse

from .registry import estimator_class, names, reference_names
from .spec import user_param_docs


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("estimators", help="list estimators and their parameters",
                       description="List the estimators, or one estimator's parameters "
                                   "with defaults and units (angles in degrees: "
                                   "NAME_deg, rates NAME_dps, as -e NAME:k=v takes them).")
    p.add_argument("name", nargs="?", help="show this estimator's parameters")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    for name in [args.name] if args.name else names() + reference_names():
        cls = estimator_class(name)  # ValueError listing the valid names
        print(f"{name}: {(cls.__doc__ or '').strip().splitlines()[0]}")
        if args.name:
            for key, doc in user_param_docs(cls).items():
                print(f"    {key} = {doc}")
    return 0
