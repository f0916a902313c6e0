"""Name -> estimator class. Estimator modules register themselves on import.

Two kinds: our estimators (:func:`names`, every one of them keeps the SPEC's contracts
and runs by default where "all" are run) and references, other people's published
filters wrapped for comparison (:func:`reference_names`, ``Estimator.reference``), which
run only when named (``-e vqf``) and are not held to contracts they were not built for
(a starting attitude, velocity aiding)."""

from __future__ import annotations

import importlib

from .base import Estimator

_REGISTRY: dict[str, type[Estimator]] = {}
_REFERENCES: dict[str, type[Estimator]] = {}
# Modules that define estimators; imported on first use so `import estimators` stays cheap.
_MODULES = ("euler", "dcm", "quaternion", "mahony", "madgwick", "kalman", "eskf",
            "vqf_online")


def register(cls: type[Estimator]) -> type[Estimator]:
    """Class decorator: make ``cls`` available under ``cls.name``."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    (_REFERENCES if cls.reference else _REGISTRY)[cls.name] = cls
    return cls


def _load_all() -> None:
    for module in _MODULES:
        try:
            importlib.import_module(f"{__package__}.{module}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{__package__}.{module}":
                raise


def names() -> list[str]:
    """Every registered estimator name (ours; the references are listed apart)."""
    _load_all()
    return list(_REGISTRY)


def reference_names() -> list[str]:
    """The reference estimators, run only when named (``-e vqf``)."""
    _load_all()
    return list(_REFERENCES)


def estimator_class(name: str) -> type[Estimator]:
    """The class registered under ``name`` (an estimator or a reference); ValueError
    listing the valid names otherwise."""
    _load_all()
    found = _REGISTRY.get(name) or _REFERENCES.get(name)
    if found is None:
        raise ValueError(f"unknown estimator {name!r}; valid: {sorted(_REGISTRY)} "
                         f"(references: {sorted(_REFERENCES)})")
    return found
