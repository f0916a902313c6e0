"""Name -> estimator class. Estimator modules register themselves on import."""

from __future__ import annotations

import importlib

from .base import Estimator

_REGISTRY: dict[str, type[Estimator]] = {}
# Modules that define estimators; imported on first use so `import estimators` stays cheap.
_MODULES = ("euler", "dcm", "quaternion", "mahony", "madgwick", "kalman", "eskf")


def register(cls: type[Estimator]) -> type[Estimator]:
    """Class decorator: make ``cls`` available under ``cls.name``."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    _REGISTRY[cls.name] = cls
    return cls


def _load_all() -> None:
    for module in _MODULES:
        try:
            importlib.import_module(f"{__package__}.{module}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{__package__}.{module}":
                raise


def names() -> list[str]:
    """Every registered estimator name."""
    _load_all()
    return list(_REGISTRY)


def estimator_class(name: str) -> type[Estimator]:
    """The class registered under ``name``; ValueError listing valid names otherwise."""
    _load_all()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown estimator {name!r}; valid: {sorted(_REGISTRY)}") from None
