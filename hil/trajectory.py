"""Smooth motions with exact derivatives up to jerk, the raw material of a multirotor flight.

A multirotor's attitude follows its thrust direction, which depends on the acceleration;
its body rates therefore depend on the *jerk*. To get exact, continuous body rates the
position must be C³ with analytic derivatives. The building block here is a
"move": go from rest to rest by ``delta`` at a cruise ``speed``, accelerating and braking
at ``accel`` with the acceleration itself switched on and off along a quintic smoothstep
in ``rise`` seconds (so acceleration and jerk are continuous, and the acceleration is
*held* for ``speed/accel - rise`` seconds, as a real vehicle holds its tilt while it
speeds up). A scalar ``Axis`` is a sum of moves; a ``Circle`` turns one move of an angle
into a planar circle with sustained centripetal acceleration.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Antiderivatives of the quintic smoothstep S(u) = 10u³ - 15u⁴ + 6u⁵ at u = 1.
_I1_AT_1 = 0.5
_I2_AT_1 = 1.0 / 7.0


def _step(tau: np.ndarray, rise: float, amount: float) -> tuple[np.ndarray, ...]:
    """An acceleration step of ``amount`` starting at tau = 0: value, v, a, jerk.

    The acceleration follows amount·S(tau/rise); velocity and value are its exact first
    and second integrals (zero before the step).
    """
    u = np.clip(tau / rise, 0.0, 1.0)
    u2 = u * u
    u3 = u2 * u
    s = u3 * (10.0 - 15.0 * u + 6.0 * u2)
    ds = 30.0 * u2 * (1.0 - u) ** 2
    i1 = u2 * u2 * (2.5 - 3.0 * u + u2)
    i2 = u3 * u2 * (0.5 - 0.5 * u + u2 / 7.0)
    after = tau >= rise
    late = tau - rise
    x = np.where(after, rise * rise * _I2_AT_1 + rise * _I1_AT_1 * late + 0.5 * late * late,
                 rise * rise * i2)
    v = np.where(after, rise * _I1_AT_1 + late, rise * i1)
    return amount * x, amount * v, amount * s, amount * ds / rise


@dataclass(frozen=True)
class Move:
    """From rest at ``start`` to rest ``delta`` further, at most ``speed``, with ``accel``.

    The cruise phase is what is left after speeding up and braking; a distance too
    short for the speed is an error (pick a lower speed), so the shape stays as asked.
    """

    start: float
    delta: float
    speed: float
    accel: float
    rise: float = 0.3

    def __post_init__(self) -> None:
        if not (self.speed > 0 and self.accel > 0 and self.rise > 0):
            raise ValueError("speed, accel and rise must be > 0")
        if self.speed / self.accel < self.rise:
            raise ValueError("speed/accel must be at least the rise time")
        if self.cruise < -1e-9:
            raise ValueError(f"move of {self.delta} is too short for speed {self.speed}")

    @property
    def ramp(self) -> float:
        """Duration of speeding up (and of braking): accel time plus one rise."""
        return self.speed / self.accel + self.rise

    @property
    def cruise(self) -> float:
        return abs(self.delta) / self.speed - self.ramp

    @property
    def duration(self) -> float:
        return 2.0 * self.ramp + max(0.0, self.cruise)

    @property
    def end(self) -> float:
        return self.start + self.duration

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, ...]:
        """Value, velocity, acceleration, jerk at t (0 before, delta after the move)."""
        sign = 1.0 if self.delta >= 0 else -1.0
        a = sign * self.accel
        hold = self.speed / self.accel
        brake = self.start + self.ramp + max(0.0, self.cruise)
        out = [np.zeros_like(t) for _ in range(4)]
        for t0, amount in ((self.start, a), (self.start + hold, -a),
                           (brake, -a), (brake + hold, a)):
            for acc, part in zip(out, _step(t - t0, self.rise, amount), strict=True):
                acc += part  # zero before the step starts
        done = t >= self.end
        out[0] = np.where(done, self.delta, out[0])
        for k in (1, 2, 3):
            out[k] = np.where(done, 0.0, out[k])
        return tuple(out)


@dataclass
class Axis:
    """One scalar (a coordinate, an angle): initial value plus moves, with 3 derivatives."""

    initial: float = 0.0
    moves: list[Move] = field(default_factory=list)

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Value, first, second and third derivative at times t."""
        t = np.asarray(t, dtype=float)
        x = np.full(t.shape, float(self.initial))
        v, a, j = np.zeros(t.shape), np.zeros(t.shape), np.zeros(t.shape)
        if t.size == 0:
            return x, v, a, j
        lo, hi = float(t.min()), float(t.max())
        for m in self.moves:
            if m.end <= lo:
                x += m.delta
            elif m.start < hi:
                dx, dv, da, dj = m.evaluate(t)
                x += dx
                v += dv
                a += da
                j += dj
        return x, v, a, j


@dataclass(frozen=True)
class Circle:
    """A circle in the north-east plane driven by the angle ``angle`` (a Move).

    Position relative to where the circle starts: ``R (e^{iθ} - e^{iθ0})`` with north
    the real and east the imaginary part; θ increasing turns right (clockwise seen from
    above) and the velocity points to heading θ + 90°.
    """

    radius: float
    theta0: float
    angle: Move

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, ...]:
        """(north, east) offsets as 4 complex arrays: position, velocity, accel, jerk."""
        th, w, dw, ddw = Axis(self.theta0, [self.angle]).evaluate(t)
        z = self.radius * np.exp(1j * th)
        moving = (t > self.angle.start) & (t < self.angle.end)
        p = z - self.radius * np.exp(1j * self.theta0)
        v = 1j * w * z
        a = (1j * dw - w * w) * z
        j = (1j * ddw - 3.0 * w * dw - 1j * w**3) * z
        return p, np.where(moving, v, 0.0), np.where(moving, a, 0.0), np.where(moving, j, 0.0)
