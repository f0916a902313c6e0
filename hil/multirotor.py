"""A quadrotor in flight: the attitude is whatever points the thrust where it must go.

Dynamics (NED world, FRD body, rotation R body -> world, body z axis z_b = R e3):

* A multirotor can only push along its body -z axis (thrust T per unit mass). Its
  rotors also brake the air flowing across them ("rotor drag"): a force opposite the
  *body-frame horizontal* velocity, linear in it. So the specific force, which is what
  the accelerometer measures, is in the body frame

      f_b = ( -mu v_bx, -mu v_by, -T ),       and Newton gives  a = g + R f_b.

* Solving for the attitude: R f_b = -mu (v - (v·z_b) z_b) - T z_b, hence
  ``a - g + mu v = (mu v·z_b - T) z_b``: the body z axis is exactly
  ``z_b = -w/|w|`` with ``w = a - g + mu v`` (the drag along body z just changes the
  thrust needed). This is the differential flatness of a quadrotor with isotropic rotor
  drag (Faessler et al., RA-L 2018), specialised to equal x/y drag.
* The yaw schedule fixes the rotation about z_b: x_b lies in the vertical plane of the
  heading ψ (so ψ is the Z-Y-X Euler yaw), ``x_b ∝ y_c × z_b`` with
  ``y_c = (-sin ψ, cos ψ, 0)``, and ``y_b = z_b × x_b``.
* Body rates come from the exact time derivatives of that frame (which need the jerk
  and ψ'): ``p = z_b·ẏ_b``, ``q = x_b·ż_b``, ``r = y_b·ẋ_b``.

The truth's specific force is ``R^T (a - g)`` as for every profile; with this attitude
its body x/y components are exactly ``-mu`` times the body velocity. At constant
velocity the vehicle tilts into the wind of its own motion (tan tilt = mu |v_h| / g)
and the accelerometer reads gravity in that tilted body, as on a real quadrotor.
``mu`` (``drag_per_s``, 1/s) is 0.3-0.6 on real quads; PX4's SIH model uses 1.0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .environment import GRAVITY_NED
from .trajectory import Axis, Circle, Move
from .truth import Profile, Truth

DEFAULT_DRAG_PER_S = 0.4


@dataclass
class Track:
    """Position (NED) and yaw as sums of moves and circles, with exact derivatives."""

    north: Axis = field(default_factory=Axis)
    east: Axis = field(default_factory=Axis)
    down: Axis = field(default_factory=Axis)
    yaw: Axis = field(default_factory=Axis)
    circles: list[Circle] = field(default_factory=list)

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, ...]:
        """Position, velocity, acceleration, jerk (N, 3) and yaw, yaw rate (N,)."""
        axes = [c.evaluate(t) for c in (self.north, self.east, self.down)]
        p, v, a, j = (np.stack([ax[k] for ax in axes], axis=-1) for k in range(4))
        for circle in self.circles:
            if circle.angle.start >= float(np.max(t, initial=-np.inf)):
                continue
            for out, z in zip((p, v, a, j), circle.evaluate(t), strict=True):
                out[:, 0] += z.real
                out[:, 1] += z.imag
        psi, dpsi, _, _ = self.yaw.evaluate(t)
        return p, v, a, j, psi, dpsi

    @property
    def end(self) -> float:
        moves = [m for ax in (self.north, self.east, self.down, self.yaw) for m in ax.moves]
        moves += [c.angle for c in self.circles]
        return max((m.end for m in moves), default=0.0)


class TrackBuilder:
    """Lays out manoeuvres one after another (a cursor in seconds)."""

    def __init__(self, start: float = 0.0):
        self.t = start
        self.track = Track()

    def hover(self, seconds: float) -> TrackBuilder:
        self.t += seconds
        return self

    def leg(self, north: float, east: float, down: float = 0.0, *, speed: float,
            accel: float, rise: float = 0.3) -> TrackBuilder:
        """A straight line from rest to rest (every axis on the same time line)."""
        dist = math.sqrt(north * north + east * east + down * down)
        end = self.t
        for axis, delta in ((self.track.north, north), (self.track.east, east),
                            (self.track.down, down)):
            if delta != 0.0:
                share = abs(delta) / dist
                move = Move(self.t, delta, speed * share, accel * share, rise)
                axis.moves.append(move)
                end = move.end
        self.t = end
        return self

    def yaw_turn(self, delta_deg: float, rate_dps: float, accel_dps2: float, *,
                 after: float | None = None, rise: float = 0.2) -> TrackBuilder:
        """Turn by delta; with ``after`` it starts that long after the cursor and runs in
        parallel with whatever comes next (the cursor stays)."""
        start = self.t + (after or 0.0)
        move = Move(start, math.radians(delta_deg), math.radians(rate_dps),
                    math.radians(accel_dps2), rise)
        self.track.yaw.moves.append(move)
        if after is None:
            self.t = move.end
        return self

    def circle(self, radius: float, speed: float, laps: int, accel: float, *,
               theta0: float, rise: float = 0.3) -> TrackBuilder:
        """Whole laps of a circle entered and left at rest; the nose turns with it."""
        angle = Move(self.t, 2.0 * math.pi * laps, speed / radius, accel / radius, rise)
        self.track.circles.append(Circle(radius, theta0, angle))
        self.track.yaw.moves.append(angle)
        self.t = angle.end
        return self


class MultirotorProfile(Profile):
    """Attitude and specific force of a quadrotor following a flight plan.

    The plan is a prologue (ground, take-off), a cycle repeated ``cycles`` times from
    ``cycle_start`` (it starts and ends hovering at the same place, at rest, with the
    same heading modulo 360°) and an epilogue (landing) after the cycles.
    """

    def __init__(self, name: str, prologue: Track, cycle: Track, cycle_start: float,
                 cycle_length: float, cycles: int, epilogue: Track,
                 drag_per_s: float = DEFAULT_DRAG_PER_S):
        if not (math.isfinite(drag_per_s) and 0.0 <= drag_per_s <= 5.0):
            raise ValueError(f"rotor drag must be 0..5 1/s, got {drag_per_s}")
        self.name = name
        self.prologue, self.cycle, self.epilogue = prologue, cycle, epilogue
        self.cycle_start = cycle_start
        self.cycle_length = cycle_length
        self.cycles = cycles
        self.land_start = cycle_start + cycles * cycle_length
        self.drag_per_s = drag_per_s

    def plan(self, t: np.ndarray) -> tuple[np.ndarray, ...]:
        """Position, velocity, acceleration, jerk (N, 3), yaw and yaw rate (N,)."""
        t = np.asarray(t, dtype=float)
        out = list(self.prologue.evaluate(t))
        in_cycle = (t >= self.cycle_start) & (t < self.land_start)
        if np.any(in_cycle):
            local = np.where(in_cycle, (t - self.cycle_start) % self.cycle_length, -1.0)
            for k, part in enumerate(self.cycle.evaluate(local)):
                out[k] = out[k] + part
        if np.any(t >= self.land_start):
            for k, part in enumerate(self.epilogue.evaluate(t - self.land_start)):
                out[k] = out[k] + part
        return tuple(out)

    def truth(self, t: np.ndarray) -> Truth:
        t = np.asarray(t, dtype=float)
        p, v, a, j, psi, dpsi = self.plan(t)
        q, rates = attitude_from_thrust(a, v, j, psi, dpsi, self.drag_per_s)
        return Truth(t=t, q=q, rates=rates, accel_ned=a, velocity_ned=v, position_ned=p)


def attitude_from_thrust(a: np.ndarray, v: np.ndarray, jerk: np.ndarray, yaw: np.ndarray,
                         yaw_rate: np.ndarray, drag_per_s: float
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Quaternions body -> NED and FRD body rates of a quadrotor with rotor drag."""
    w = a - GRAVITY_NED + drag_per_s * v
    dw = jerk + drag_per_s * a
    nw = np.linalg.norm(w, axis=-1, keepdims=True)
    z = -w / nw
    dz = -(dw - _dot(dw, z) * z) / nw
    zero = np.zeros_like(yaw)
    yc = np.stack([-np.sin(yaw), np.cos(yaw), zero], axis=-1)
    dyc = -yaw_rate[:, None] * np.stack([np.cos(yaw), np.sin(yaw), zero], axis=-1)
    u = np.cross(yc, z)
    du = np.cross(dyc, z) + np.cross(yc, dz)
    nu = np.linalg.norm(u, axis=-1, keepdims=True)
    x = u / nu
    dx = (du - _dot(du, x) * x) / nu
    y = np.cross(z, x)
    dy = np.cross(dz, x) + np.cross(z, dx)
    rates = np.stack([_dot(z, dy)[:, 0], _dot(x, dz)[:, 0], _dot(y, dx)[:, 0]], axis=-1)
    return quat_from_frame(x, y, z), rates


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sum(a * b, axis=-1, keepdims=True)


def quat_from_frame(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Quaternion (w >= 0) of the rotation whose columns are the body axes x, y, z in the
    world frame; Shepperd's method, vectorised (the truth is needed at 8 kHz)."""
    r00, r10, r20 = x[:, 0], x[:, 1], x[:, 2]
    r01, r11, r21 = y[:, 0], y[:, 1], y[:, 2]
    r02, r12, r22 = z[:, 0], z[:, 1], z[:, 2]
    cands = np.stack([
        [1.0 + r00 + r11 + r22, r21 - r12, r02 - r20, r10 - r01],
        [r21 - r12, 1.0 + r00 - r11 - r22, r01 + r10, r02 + r20],
        [r02 - r20, r01 + r10, 1.0 - r00 + r11 - r22, r12 + r21],
        [r10 - r01, r02 + r20, r12 + r21, 1.0 - r00 - r11 + r22],
    ])  # (4 cases, 4 components, N): case k has 4 q_k q_i in row i
    diag = np.stack([cands[k, k] for k in range(4)])
    best = np.argmax(diag, axis=0)
    n = np.arange(x.shape[0])
    q = cands[best, :, n]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[:, :1] < 0.0, -q, q)


# ---- the `flight` profile ---------------------------------------------------------

FLIGHT_GROUND_S = 5.0
FLIGHT_ALTITUDE_M = 10.0


def flight(duration_s: float, drag_per_s: float = DEFAULT_DRAG_PER_S) -> MultirotorProfile:
    """A quadrotor flight like PX4's SIH box flights, built from the real dynamics.

    5 s on the ground (boot, arming: the estimators learn the gyro bias), take-off to
    10 m, then cycles of: a 30 m leg north at 5 m/s (4.5 m/s² held ~1 s, ~34° tilt while
    speeding up), a 90° yaw turn, 30 m east (4 m/s²), back home along the diagonal at
    5 m/s with 5.5 m/s² (~37° tilt) while yawing 135°, two right-hand laps of a 7 m
    circle at 6 m/s (5.1 m/s² centripetal for ~11 s, 30° tilt, nose along the track), a
    5 m climb and descent, and a 450° yaw spin. Each cycle ends hovering over home, so
    any duration works; when the duration leaves room after whole cycles, it lands.
    Cruising, the vehicle leans into its rotor drag (12° at 5 m/s with mu = 0.4).
    """
    pro = TrackBuilder().hover(FLIGHT_GROUND_S)
    pro.leg(0.0, 0.0, -FLIGHT_ALTITUDE_M, speed=2.5, accel=2.5).hover(1.0)
    cyc = TrackBuilder()
    cyc.hover(2.0).leg(30.0, 0.0, speed=5.0, accel=4.5).hover(1.5)
    cyc.yaw_turn(90.0, 90.0, 180.0).hover(0.5)
    cyc.leg(0.0, 30.0, speed=5.0, accel=4.0).hover(1.0)
    cyc.yaw_turn(135.0, 60.0, 120.0, after=1.5)
    cyc.leg(-30.0, -30.0, speed=5.0, accel=5.5).hover(1.0)
    cyc.yaw_turn(45.0, 60.0, 120.0).hover(0.5)
    cyc.circle(7.0, 6.0, 2, 3.5, theta0=math.pi).hover(1.0)  # heading 270° at its start
    cyc.leg(0.0, 0.0, -5.0, speed=2.0, accel=2.0).hover(1.0)
    cyc.yaw_turn(450.0, 150.0, 300.0).hover(0.5)
    cyc.leg(0.0, 0.0, 5.0, speed=1.5, accel=1.5).hover(2.0)
    land = TrackBuilder().leg(0.0, 0.0, FLIGHT_ALTITUDE_M, speed=1.5, accel=1.5)
    cycle_length = cyc.t
    cycles = max(1, math.floor((duration_s - pro.t - land.t) / cycle_length))
    return MultirotorProfile("flight", pro.track, cyc.track, pro.t, cycle_length, cycles,
                             land.track, drag_per_s)
