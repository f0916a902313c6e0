"""``NAME[:key=value,...]``: how the CLI, config files and reports name an estimator
with parameter overrides (``mahony:kp=0.5,ki=0.01``, ``mahony:mag_mode=full``).

Angles at the user surface are in degrees (SPEC, conventions), the library works in
radians: every parameter documented in ``[rad]`` also answers to ``<name>_deg`` and
every one in ``[rad/s]`` to ``<name>_dps`` (``eskf:declination_deg=3.5``,
``mahony:bias_limit_dps=20``); they are converted when parsed, and labels and listings
show them that way.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from .base import DEGREE_UNITS, DOC_UNIT, Estimator, doc_unit
from .registry import estimator_class

ParamValue = float | bool | str


def angle_params(est_cls: type[Estimator]) -> dict[str, str]:
    """Parameter name -> its degree alias (``declination`` -> ``declination_deg``) for
    every parameter whose documented unit is ``[rad]`` or ``[rad/s]``."""
    out = {}
    for f in dataclasses.fields(est_cls.Params):
        degrees = DEGREE_UNITS.get(doc_unit(f) or "")
        if degrees is not None:
            out[f.name] = f.name + degrees[0]
    return out


def user_param(est_cls: type[Estimator], name: str, value: ParamValue
               ) -> tuple[str, ParamValue]:
    """(name, value) as the user surface shows it: angles in degrees under their alias."""
    alias = angle_params(est_cls).get(name)
    if alias is None or isinstance(value, bool) or not isinstance(value, int | float):
        return name, value
    return alias, math.degrees(float(value))


def user_param_docs(est_cls: type[Estimator]) -> dict[str, str]:
    """Like ``param_docs`` with angles in degrees, and the range a value must lie in:
    ``beta_dps`` -> '5.72958 (0..572.958); ...[deg/s]...'."""
    aliases = angle_params(est_cls)
    out = {}
    for f in dataclasses.fields(est_cls.Params):
        doc = f.metadata.get("doc", "")
        bounds = est_cls.Params.BOUNDS.get(f.name)
        if f.name in aliases:
            unit = DEGREE_UNITS[doc_unit(f) or ""][1]
            doc = DOC_UNIT.sub(f"[{unit}]", doc, count=1)
            shown = f"{math.degrees(f.default):.6g}"
            if bounds is not None:
                shown += f" ({math.degrees(bounds[0]):.6g}..{math.degrees(bounds[1]):.6g})"
            out[aliases[f.name]] = f"{shown}; {doc}"
        else:
            shown = repr(f.default)
            if bounds is not None:
                shown += f" ({bounds[0]:g}..{bounds[1]:g})"
            out[f.name] = f"{shown}; {doc}"
    return out


def _parse_value(text: str) -> ParamValue:
    """Numbers and booleans as such; anything else stays text for the estimator to judge."""
    low = text.strip().lower()
    if low in ("true", "yes", "on"):
        return True
    if low in ("false", "no", "off"):
        return False
    try:
        return float(text)
    except ValueError:
        return text.strip()


@dataclass(frozen=True)
class EstimatorSpec:
    """An estimator name with parameter overrides, checked when parsed."""

    name: str
    params: dict[str, ParamValue] = field(default_factory=dict)

    @classmethod
    def parse(cls, text: str) -> EstimatorSpec:
        """``"mahony:kp=0.5"`` -> spec; ValueError naming what is valid when it is wrong."""
        name, _, rest = text.strip().partition(":")
        name = name.strip()
        est_cls = estimator_class(name)  # ValueError listing the valid names
        params: dict[str, ParamValue] = {}
        for item in filter(None, (p.strip() for p in rest.split(","))):
            key, sep, value = item.partition("=")
            if not sep or not key.strip():
                raise ValueError(f"bad estimator parameter {item!r} in {text!r}; use k=v "
                                 f"(valid keys for {name}: {user_param_names(est_cls)})")
            key, parsed = to_internal(est_cls, key.strip(), _parse_value(value))
            if key in params:
                raise ValueError(f"estimator parameter {key!r} given twice in {text!r}")
            params[key] = parsed
        spec = cls(name, params)
        spec.validate()
        return spec

    @property
    def label(self) -> str:
        """Unique display name: the name, plus the overrides if any (angles in degrees,
        ``eskf:declination_deg=3.5``)."""
        if not self.params:
            return self.name
        return self.name + ":" + ",".join(
            f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
            for k, v in self.user_params().items())

    def user_params(self) -> dict[str, ParamValue]:
        """The overrides as the user surface shows them (angles in degrees)."""
        est_cls = estimator_class(self.name)
        return dict(user_param(est_cls, k, v) for k, v in self.params.items())

    def validate(self) -> None:
        """ValueError for an unknown name, a bad parameter or a missing package, before
        any work is done."""
        est_cls = estimator_class(self.name)
        est_cls.make_params(**self.params)
        est_cls.check_available()

    def create(self, rate_hz: float = 1000.0, world: str = "NED",
               q0: np.ndarray | None = None, **defaults: ParamValue) -> Estimator:
        """A fresh instance; ``defaults`` (e.g. a site-wide declination) yield to the
        spec's own overrides."""
        return estimator_class(self.name)(rate_hz=rate_hz, world=world, q0=q0,
                                          **{**defaults, **self.params})


def user_param_names(est_cls: type[Estimator]) -> list[str]:
    """Every name a parameter answers to at the user surface (degree aliases included)."""
    aliases = angle_params(est_cls)
    return [n for name in est_cls.param_names()
            for n in ((name, aliases[name]) if name in aliases else (name,))]


def to_internal(est_cls: type[Estimator], key: str, value: ParamValue
              ) -> tuple[str, ParamValue]:
    """A user-surface parameter -> (library name, value in radians)."""
    for name, alias in angle_params(est_cls).items():
        if key == alias:
            if isinstance(value, bool) or not isinstance(value, float):
                raise ValueError(f"parameter {key!r} must be a number of degrees, "
                                 f"got {value!r}")
            return name, math.radians(value)
    if key not in est_cls.param_names():
        raise ValueError(f"unknown parameter {key!r} for estimator {est_cls.name!r}; "
                         f"valid: {user_param_names(est_cls)}")
    return key, value
