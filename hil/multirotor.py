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

The flight state (armed, MAV_LANDED_STATE) comes from the same plan: a flight begins
where a vertical move leaves the ground (altitude 0) and ends where one reaches it
again. ``TAKEOFF`` is that first climb, ``LANDING`` the last descent, ``IN_AIR`` the
rest; the vehicle arms ``ARM_BEFORE_LIFTOFF_S`` before lift-off and disarms
``DISARM_AFTER_TOUCHDOWN_S`` after touchdown (PX4's COM_DISARM_LAND default), unless the
next flight arms it first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .environment import GRAVITY_NED
from .trajectory import Axis, Circle, Move
from .truth import LANDED_IN_AIR, LANDED_LANDING, LANDED_ON_GROUND, LANDED_TAKEOFF, Profile, Truth

DEFAULT_DRAG_PER_S = 0.4
#: Armed this long before lift-off (the pilot arms, the motors spin up, it takes off).
ARM_BEFORE_LIFTOFF_S = 1.5
#: Disarmed this long after touchdown (PX4's COM_DISARM_LAND default).
DISARM_AFTER_TOUCHDOWN_S = 2.0
#: Altitude [m] below which the plan counts as on the ground (the plans sum to exact 0).
GROUND_TOLERANCE_M = 1e-6


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


@dataclass(frozen=True)
class Airborne:
    """One flight of a plan [s]: the climb that leaves the ground runs from ``liftoff``
    to ``climbed`` (vertical speed back to 0 at its altitude), the descent that reaches
    the ground from ``descent`` to ``touchdown`` (inf: still flying when the plan ends)."""

    liftoff: float
    climbed: float
    descent: float
    touchdown: float


def airborne_spans(moves: list[Move], initial_down: float = 0.0) -> list[Airborne]:
    """The flights of a sequence of vertical (down-axis) moves in absolute time, the
    ground being at down = 0; ValueError if moves overlap or go below the ground."""
    flights: list[Airborne] = []
    down = initial_down
    lifted: tuple[float, float] | None = None
    if down < -GROUND_TOLERANCE_M:
        lifted = (-math.inf, -math.inf)  # the plan starts in the air
    elif down > GROUND_TOLERANCE_M:
        raise ValueError("the plan starts below the ground")
    last_end = -math.inf
    for m in sorted(moves, key=lambda m: m.start):
        if m.start < last_end - 1e-9:
            raise ValueError("vertical moves overlap: the flight state needs them in turn")
        last_end = m.end
        after = down + m.delta
        if after > GROUND_TOLERANCE_M:
            raise ValueError(f"a vertical move at {m.start:g} s goes below the ground")
        grounded, lands = down > -GROUND_TOLERANCE_M, after > -GROUND_TOLERANCE_M
        if grounded and not lands:
            lifted = (m.start, m.end)
        elif lands and not grounded and lifted is not None:
            flights.append(Airborne(lifted[0], lifted[1], m.start, m.end))
            lifted = None
        down = after
    if lifted is not None:
        flights.append(Airborne(lifted[0], lifted[1], math.inf, math.inf))
    return flights


def flight_state_of(flights: list[Airborne], t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(armed, landed_state) at times t for a list of flights (on the ground outside)."""
    t = np.asarray(t, dtype=float)
    landed = np.full(t.shape, LANDED_ON_GROUND, dtype=np.uint8)
    armed = np.zeros(t.shape, dtype=bool)
    for f in flights:
        landed[(t >= f.liftoff) & (t < f.climbed)] = LANDED_TAKEOFF
        landed[(t >= f.climbed) & (t < f.descent)] = LANDED_IN_AIR
        landed[(t >= f.descent) & (t < f.touchdown)] = LANDED_LANDING
        armed |= (t >= f.liftoff - ARM_BEFORE_LIFTOFF_S) & (t < f.touchdown
                                                             + DISARM_AFTER_TOUCHDOWN_S)
    return armed, landed


class MultirotorProfile(Profile):
    """Attitude and specific force of a quadrotor following a flight plan.

    The plan is a prologue (ground, take-off), a cycle repeated ``cycles`` times from
    ``cycle_start`` (it starts and ends hovering at the same place, at rest, with the
    same heading modulo 360°) and an epilogue (landing) after the cycles. A plan laid
    out whole has no cycles (``cycles=0``, an empty cycle and epilogue).
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
        self.flights = airborne_spans(self._vertical_moves(), prologue.down.initial)

    def _vertical_moves(self) -> list[Move]:
        """Every down-axis move of the plan in absolute time (cycles unrolled)."""
        moves = list(self.prologue.down.moves)
        for k in range(self.cycles):
            offset = self.cycle_start + k * self.cycle_length
            moves += [replace(m, start=m.start + offset) for m in self.cycle.down.moves]
        moves += [replace(m, start=m.start + self.land_start) for m in self.epilogue.down.moves]
        return moves

    def flight_state(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Armed and MAV_LANDED_STATE from the plan's flights (``self.flights``)."""
        return flight_state_of(self.flights, t)

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


# ---- the flights of `handheld_flight` ------------------------------------------------

BENCH_GROUND_S = 4.0  # set down level, then still on the ground until lift-off (arming)
BENCH_REST_S = 10.0  # on the ground between the two flights


def bench_flights(start_s: float, yaw0: float,
                  drag_per_s: float = DEFAULT_DRAG_PER_S) -> MultirotorProfile:
    """Two short flights from where a hand set the vehicle down at ``start_s``, at rest,
    level, facing ``yaw0`` [rad] (the plan starts exactly there, so the attitude joins).

    After ``BENCH_GROUND_S`` on the ground: take-off to 8 m, 25 m north at 5 m/s
    (4.5 m/s²), a 90° yaw turn, 20 m east (4 m/s²), home along the diagonal at 5 m/s
    (5 m/s²) while turning back, landing. ``BENCH_REST_S`` on the ground (landed,
    disarmed after 2 s, armed again 1.5 s before lift-off), then take-off to 6 m, one lap
    of a 6 m circle at 5 m/s (4.2 m/s² centripetal, nose along the track), a 180° yaw
    turn, 20 m out and back (4.5 and 5 m/s²), landing at home. Then on the ground for
    ever.
    """
    b = TrackBuilder(start_s)
    b.track.yaw.initial = yaw0
    b.hover(BENCH_GROUND_S)
    # first flight
    b.leg(0.0, 0.0, -8.0, speed=2.0, accel=2.0).hover(1.0)
    b.leg(25.0, 0.0, speed=5.0, accel=4.5).hover(1.0)
    b.yaw_turn(90.0, 90.0, 180.0).hover(0.5)
    b.leg(0.0, 20.0, speed=5.0, accel=4.0).hover(1.0)
    b.yaw_turn(-90.0, 45.0, 90.0, after=1.0)
    b.leg(-25.0, -20.0, speed=5.0, accel=5.0).hover(1.5)
    b.leg(0.0, 0.0, 8.0, speed=1.5, accel=1.5)
    b.hover(BENCH_REST_S)
    # second flight
    b.leg(0.0, 0.0, -6.0, speed=2.0, accel=2.0).hover(1.0)
    heading = float(b.track.yaw.evaluate(np.array([b.t]))[0][0])
    b.circle(6.0, 5.0, 1, 3.0, theta0=heading - 0.5 * math.pi).hover(1.0)
    b.yaw_turn(180.0, 120.0, 240.0).hover(0.5)
    b.leg(-20.0, 0.0, speed=5.0, accel=4.5).hover(1.0)
    b.leg(20.0, 0.0, speed=5.0, accel=5.0).hover(1.5)
    b.leg(0.0, 0.0, 6.0, speed=1.5, accel=1.5)
    return MultirotorProfile("bench flights", b.track, Track(), b.t, 1.0, 0, Track(),
                             drag_per_s)
