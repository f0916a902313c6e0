"""``NAME[:key=value,...]``: how the CLI, config files and reports name an estimator
with parameter overrides (``mahony:kp=0.5,ki=0.01``, ``mahony:mag_mode=full``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .base import Estimator
from .registry import estimator_class

ParamValue = float | bool | str


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
                                 f"(valid keys for {name}: {est_cls.param_names()})")
            params[key.strip()] = _parse_value(value)
        spec = cls(name, params)
        spec.validate()
        return spec

    @property
    def label(self) -> str:
        """Unique display/topic name: the name, plus the overrides if any."""
        if not self.params:
            return self.name
        return self.name + ":" + ",".join(
            f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
            for k, v in self.params.items())

    def validate(self) -> None:
        """ValueError for an unknown name or a bad parameter, before any work is done."""
        estimator_class(self.name).make_params(**self.params)

    def create(self, rate_hz: float = 1000.0, world: str = "NED",
               q0: np.ndarray | None = None, **defaults: ParamValue) -> Estimator:
        """A fresh instance; ``defaults`` (e.g. a site-wide declination) yield to the
        spec's own overrides."""
        return estimator_class(self.name)(rate_hz=rate_hz, world=world, q0=q0,
                                          **{**defaults, **self.params})
