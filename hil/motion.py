"""Trajectories with exact truth: attitude, body rates, specific force, field.

Every profile is built from smooth analytic pieces, so its derivatives are exact:

* attitude from Z-Y-X Euler angles ``(roll, pitch, yaw)(t)`` — unbounded, so a flip is
  just pitch going through 2π — with body rates from the Euler kinematics
  ``p = φ' - ψ' sinθ``, ``q = θ' cosφ + ψ' sinφ cosθ``, ``r = -θ' sinφ + ψ' cosφ cosθ``;
* position (NED) with its analytic second derivative, the linear acceleration.

``flight`` is different: a quadrotor's dynamics (``hil.multirotor``), where the attitude
follows from the thrust the planned acceleration needs. The older Euler-angle flight, whose
attitude and translation are laid out independently, lives on as ``gentle``.
``handheld_flight`` joins the two: a vehicle carried by hand, set down, then flown
twice with the quadrotor's dynamics (``HandheldThenFlight``).

Each profile also says its flight state (``Profile.flight_state``: armed, and
MAV_LANDED_STATE), what a flight controller would report. The Euler-angle profiles move
the body kinematically, as a hand does (no thrust: the accelerometer sees gravity plus
the motion's own acceleration), so they are never armed and always ON_GROUND; the
multirotor flights derive theirs from their flight plan (``hil.multirotor``).

Integrating the body rates therefore reproduces the attitude (tests check it).
Specific force in the body frame is ``R^T (a_ned - g_ned)``: level and at rest the
FRD accelerometer reads ``[0, 0, -g]``.

``file:PATH`` replays a recorded attitude: a CSV with a header row
``time_s,qw,qx,qy,qz`` (quaternion FRD body -> NED, any sign, need not be exactly unit),
strictly increasing time; ``#`` comment lines allowed. Between rows the body rotates at
the constant rate that joins the two attitudes (so the truth rates are exact for the
replayed motion); after the last row it holds still. Position stays fixed.
"""

from __future__ import annotations

import csv
import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estimators import quat

from .multirotor import (
    DEFAULT_DRAG_PER_S,
    DISARM_AFTER_TOUCHDOWN_S,
    MultirotorProfile,
    bench_flights,
)
from .multirotor import flight as multirotor_flight
from .truth import Profile, Truth

PROFILE_NAMES = ("static", "tilt", "flight", "gentle", "aggressive", "calibration",
                 "handheld_flight")
TILT_ROLL_DEG = 15.9  # the seed paper's static test
TILT_PITCH_DEG = 9.2


# ---- smooth building blocks -------------------------------------------------------

@dataclass(frozen=True)
class Ramp:
    """Change by ``delta`` between start and start+duration along a quintic smoothstep.

    The quintic 10u³-15u⁴+6u⁵ has zero first and second derivative at both ends, so
    rates and accelerations are continuous.
    """

    start: float
    duration: float
    delta: float


@dataclass(frozen=True)
class Wobble:
    """``amplitude * (1 - cos(2π f τ)) / 2`` for whole cycles from start to stop.

    Starting and stopping where value and derivative are both zero keeps the body
    rates continuous.
    """

    amplitude: float
    frequency_hz: float
    start: float
    cycles: int


@dataclass
class Channel:
    """One scalar of a trajectory: initial value + ramps + wobbles, with derivatives."""

    initial: float = 0.0
    ramps: list[Ramp] = field(default_factory=list)
    wobbles: list[Wobble] = field(default_factory=list)

    def ramp(self, start: float, duration: float, delta: float) -> Channel:
        self.ramps.append(Ramp(start, duration, delta))
        return self

    def _ramp_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if getattr(self, "_cache_len", -1) != len(self.ramps):
            self._cache = (np.array([r.start for r in self.ramps], dtype=float),
                           np.array([r.start + r.duration for r in self.ramps], dtype=float),
                           np.array([r.delta for r in self.ramps], dtype=float))
            self._cache_len = len(self.ramps)
        return self._cache

    def _wobble_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        if getattr(self, "_wobble_len", -1) != len(self.wobbles):
            starts = np.array([w.start for w in self.wobbles], dtype=float)
            ends = starts + np.array([w.cycles / w.frequency_hz for w in self.wobbles])
            self._wobble_cache = (starts, ends)
            self._wobble_len = len(self.wobbles)
        return self._wobble_cache

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Value, first and second derivative at times t.

        Only pieces overlapping [min t, max t] are evaluated; finished ramps just add
        their delta, so long (hours) profiles stay cheap per chunk.
        """
        t = np.asarray(t, dtype=float)
        v = np.full(t.shape, float(self.initial))
        d1 = np.zeros(t.shape)
        d2 = np.zeros(t.shape)
        if t.size == 0:
            return v, d1, d2
        lo, hi = float(t.min()), float(t.max())
        starts, ends, deltas = self._ramp_arrays()
        done = ends <= lo
        v += deltas[done].sum()
        for i in np.flatnonzero(~done & (starts < hi)):
            r = self.ramps[i]
            u = np.clip((t - r.start) / r.duration, 0.0, 1.0)
            inside = (u > 0.0) & (u < 1.0)
            v += r.delta * u**3 * (10.0 - 15.0 * u + 6.0 * u**2)
            d1 += np.where(inside, r.delta / r.duration * 30.0 * u**2 * (1.0 - u) ** 2, 0.0)
            d2 += np.where(inside, r.delta / r.duration**2 * 60.0 * u * (1.0 - u) * (1.0 - 2.0 * u),
                           0.0)
        w_starts, w_ends = self._wobble_arrays()
        for i in np.flatnonzero((w_ends > lo) & (w_starts < hi)):
            s = self.wobbles[i]
            end = w_ends[i]
            w = 2.0 * math.pi * s.frequency_hz
            tau = t - s.start
            on = (tau >= 0.0) & (t < end)
            half = 0.5 * s.amplitude
            v += np.where(on, half * (1.0 - np.cos(w * tau)), 0.0)
            d1 += np.where(on, half * w * np.sin(w * tau), 0.0)
            d2 += np.where(on, half * w * w * np.cos(w * tau), 0.0)
        return v, d1, d2


class EulerProfile(Profile):
    """Attitude from Euler-angle channels [rad], position from NED channels [m]."""

    def __init__(self, name: str, roll: Channel, pitch: Channel, yaw: Channel,
                 north: Channel | None = None, east: Channel | None = None,
                 down: Channel | None = None):
        self.name = name
        self.euler = (roll, pitch, yaw)
        self.position = (north or Channel(), east or Channel(), down or Channel())

    def truth(self, t: np.ndarray) -> Truth:
        t = np.asarray(t, dtype=float)
        (phi, dphi, _), (theta, dtheta, _), (psi, dpsi, _) = (c.evaluate(t) for c in self.euler)
        rates = np.stack([
            dphi - dpsi * np.sin(theta),
            dtheta * np.cos(phi) + dpsi * np.sin(phi) * np.cos(theta),
            -dtheta * np.sin(phi) + dpsi * np.cos(phi) * np.cos(theta),
        ], axis=-1)
        pos = [c.evaluate(t) for c in self.position]
        return Truth(
            t=t,
            q=quat.canonical(quat.from_euler(phi, theta, psi)),
            rates=rates,
            position_ned=np.stack([p[0] for p in pos], axis=-1),
            velocity_ned=np.stack([p[1] for p in pos], axis=-1),
            accel_ned=np.stack([p[2] for p in pos], axis=-1),
        )


def _deg(x: float) -> float:
    return math.radians(x)


def static() -> Profile:
    """Level, facing north, at rest."""
    return EulerProfile("static", Channel(), Channel(), Channel())


def tilt() -> Profile:
    """The seed paper's static attitude: roll 15.9°, pitch 9.2°, at rest."""
    return EulerProfile("tilt", Channel(_deg(TILT_ROLL_DEG)), Channel(_deg(TILT_PITCH_DEG)),
                        Channel())


GENTLE_GROUND_S = 5.0
GENTLE_TAKEOFF_S = GENTLE_GROUND_S + 6.0
GENTLE_CYCLE_S = 24.0


def gentle(duration_s: float) -> Profile:
    """On the ground, take-off to 10 m, hover, then cycles of manoeuvres, yaw turns, climbs.

    Not a multirotor's dynamics: the attitude is laid out on its own and the translation
    is only a gentle repositioning (the accelerometer sees mostly gravity). Kept for
    what it was made for, an easy hover-and-manoeuvre case; ``flight`` is the real one.
    Kinematically it is a body moved by hand (no thrust, no rotor drag), and its flight
    state says so: disarmed, ON_GROUND, whatever its height.

    The first 5 s the vehicle stands still on the ground (boot and arming, when a real
    board's estimator learns its gyro bias). Each 24 s cycle: roll and pitch manoeuvres
    (±20-25°) with the horizontal motion they cause (2-3 m repositioning, peak ≈ 1 m/s²,
    a hover-and-manoeuvre flight rather than a race), a 90° and a -180° yaw turn, a 5 m
    climb and descent, and a gentle 0.4 Hz roll wobble; every cycle ends level at hover
    height, so any duration works.
    """
    roll, pitch, yaw = Channel(), Channel(), Channel()
    north, east, down = Channel(), Channel(), Channel()
    down.ramp(GENTLE_GROUND_S, 5.0, -10.0)  # take-off
    cycles = max(1, math.ceil((duration_s - GENTLE_TAKEOFF_S) / GENTLE_CYCLE_S))
    for k in range(cycles):
        c = GENTLE_TAKEOFF_S + k * GENTLE_CYCLE_S
        roll.ramp(c + 0.0, 1.0, _deg(20)).ramp(c + 2.0, 1.0, _deg(-20))
        east.ramp(c + 0.5, 4.0, 2.0)
        pitch.ramp(c + 3.5, 1.0, _deg(-15)).ramp(c + 5.5, 1.0, _deg(15))
        north.ramp(c + 4.0, 4.0, 3.0)
        yaw.ramp(c + 7.0, 3.0, _deg(90))
        down.ramp(c + 10.0, 4.0, -5.0)
        roll.ramp(c + 12.0, 0.8, _deg(-25)).ramp(c + 13.6, 0.8, _deg(25))
        yaw.ramp(c + 15.0, 4.0, _deg(-180))
        down.ramp(c + 16.0, 4.0, 5.0)
        pitch.ramp(c + 20.0, 1.0, _deg(20)).ramp(c + 22.0, 1.0, _deg(-20))
        north.ramp(c + 19.5, 4.0, -3.0)
        east.ramp(c + 19.5, 4.0, -2.0)
        roll.wobbles.append(Wobble(_deg(4.0), 0.4, c, 9))
    return EulerProfile("gentle", roll, pitch, yaw, north, east, down)


AGGRESSIVE_CYCLE_S = 12.0


def aggressive(duration_s: float) -> Profile:
    """Flips: full pitch loops through +90° and -90°, roll rolls, and a fast yaw spin.

    One loop takes 1 s (peak rate ≈ 675 °/s, inside the ±2000 °/s gyro range); each
    12 s cycle returns to level. A tumble of the board in place (the accelerometer reads
    gravity through the loops, which a multirotor's thrust would not): a hand-held
    motion, disarmed and ON_GROUND.
    """
    roll, pitch, yaw = Channel(), Channel(), Channel()
    down = Channel().ramp(0.5, 2.0, -5.0)
    cycles = max(1, math.ceil(duration_s / AGGRESSIVE_CYCLE_S))
    for k in range(cycles):
        c = 1.0 + k * AGGRESSIVE_CYCLE_S
        pitch.ramp(c + 1.0, 1.0, 2.0 * math.pi)  # forward loop: through +90°
        pitch.ramp(c + 3.0, 1.0, -2.0 * math.pi)  # backward loop: through -90°
        roll.ramp(c + 5.0, 1.0, 2.0 * math.pi)
        pitch.ramp(c + 7.0, 0.6, _deg(80)).ramp(c + 8.0, 0.6, _deg(-80))  # near vertical
        yaw.ramp(c + 9.0, 1.5, 2.0 * math.pi)
        roll.ramp(c + 9.2, 0.5, _deg(30)).ramp(c + 10.2, 0.5, _deg(-30))
    return EulerProfile("aggressive", roll, pitch, yaw, down=down)


#: (roll, pitch, yaw) [deg] of the `calibration` profile's static poses: gravity along
#: ±x, ±y, ±z and eight diagonals, each at another heading, so the accelerometer sees
#: 14 directions and the magnetometer the whole sphere.
CALIBRATION_POSES_DEG = (
    (0, 0, 0), (0, 0, 120), (180, 0, 60), (90, 0, 200), (-90, 0, 300), (0, 90, 30),
    (0, -90, 150), (45, 45, 250), (-45, 45, 340), (45, -45, 80), (-45, -45, 190),
    (135, 30, 280), (-135, 30, 20), (135, -30, 110), (-135, -30, 230),
)
CALIBRATION_HOLD_S = 2.0
CALIBRATION_MOVE_S = 1.5


def calibration() -> Profile:
    """A board turned by hand through 15 orientations and held still in each.

    The still stretches give the gyro offset and the accelerometer's static poses; the
    turns in between (and the varied headings) spread the magnetometer over the sphere.
    The first pose (level, north) is held first; the last one is held for ever.
    """
    channels = [Channel(_deg(v)) for v in CALIBRATION_POSES_DEG[0]]
    t = CALIBRATION_HOLD_S
    for prev, pose in itertools.pairwise(CALIBRATION_POSES_DEG):
        for ch, a, b in zip(channels, prev, pose, strict=True):
            if a != b:
                ch.ramp(t, CALIBRATION_MOVE_S, _deg(b - a))
        t += CALIBRATION_MOVE_S + CALIBRATION_HOLD_S
    return EulerProfile("calibration", *channels)


def calibration_duration_s() -> float:
    """Time to go through every pose of the `calibration` profile."""
    n = len(CALIBRATION_POSES_DEG)
    return n * CALIBRATION_HOLD_S + (n - 1) * CALIBRATION_MOVE_S


# ---- handheld_flight ------------------------------------------------------------------

#: The hand lifts the vehicle this much off the bench [m] while turning it.
HANDHELD_LIFT_M = 0.25
#: Largest jump of any truth quantity where the hand-held part hands over to the flight.
JOIN_TOLERANCE = 1e-6


def handheld() -> EulerProfile:
    """The hand-held part of ``handheld_flight``: 12.5 s on the bench by hand.

    Still for 1 s, lifted 25 cm, rolled 24° and pitched -19° together (30° tilt), moved
    30 cm north and 20 cm west, turned 90° right, rocked (8° roll at 0.8 Hz, three
    times), pitched up 15°, turned 60° back and moved back, then set down level where it
    started, facing 30°. The hand's accelerations stay below 0.7 m/s², so the
    accelerometer reads gravity plus a little.
    """
    roll, pitch, yaw = Channel(), Channel(), Channel()
    north, east, down = Channel(), Channel(), Channel()
    down.ramp(1.0, 1.5, -HANDHELD_LIFT_M)
    roll.ramp(2.0, 1.2, _deg(24)).ramp(3.6, 1.2, _deg(-24))
    pitch.ramp(2.4, 1.2, _deg(-19)).ramp(3.8, 1.2, _deg(19))
    north.ramp(2.5, 2.0, 0.3)
    east.ramp(3.0, 2.0, -0.2)
    yaw.ramp(6.0, 2.0, _deg(90))
    roll.wobbles.append(Wobble(_deg(8.0), 0.8, 6.5, 3))
    pitch.ramp(8.0, 1.0, _deg(15)).ramp(9.2, 1.0, _deg(-15))
    yaw.ramp(9.0, 1.5, _deg(-60))
    north.ramp(8.5, 2.0, -0.3)
    east.ramp(9.0, 2.0, 0.2)
    down.ramp(11.0, 1.5, HANDHELD_LIFT_M)  # set down on the bench
    return EulerProfile("handheld", roll, pitch, yaw, north, east, down)


def channel_end(ch: Channel) -> float:
    """When a channel's last ramp or wobble is over (from then on it is constant)."""
    ends = [r.start + r.duration for r in ch.ramps]
    ends += [w.start + w.cycles / w.frequency_hz for w in ch.wobbles]
    return max(ends, default=0.0)


class HandheldThenFlight(Profile):
    """A hand-held motion until ``switch_s``, then a multirotor's flight plan.

    The hand-held part ends at rest, level, on the ground (altitude 0), and the flight
    plan starts there at rest with the same heading, so attitude, rates, specific force,
    velocity and position are continuous at the switch (velocity and acceleration are
    zero there on both sides; the construction checks it). Flight state: the hand-held
    part is disarmed on the ground, the flight plan's is its own
    (``MultirotorProfile.flight_state``).
    """

    def __init__(self, name: str, hand: EulerProfile, flight: MultirotorProfile,
                 switch_s: float):
        self.name = name
        self.hand, self.flight, self.switch_s = hand, flight, switch_s
        self.flights = flight.flights
        self.drag_per_s = flight.drag_per_s
        if self.flights and self.flights[0].liftoff < switch_s:
            raise ValueError("the flight plan must not lift off before the hand lets go")
        self._check_join()

    def _check_join(self) -> None:
        """ValueError unless the two parts meet: a jump in attitude, rate, velocity or
        specific force would be a physical impossibility every estimator trips over."""
        at = np.array([self.switch_s])
        a, b = self.hand.truth(at), self.flight.truth(at)
        dq = min(np.abs(a.q - b.q).max(), np.abs(a.q + b.q).max())
        gaps = {"attitude": dq, "rates": np.abs(a.rates - b.rates).max(),
                "velocity": np.abs(a.velocity_ned - b.velocity_ned).max(),
                "position": np.abs(a.position_ned - b.position_ned).max(),
                "specific force": np.abs(a.specific_force() - b.specific_force()).max()}
        bad = {k: float(v) for k, v in gaps.items() if not v < JOIN_TOLERANCE}
        if bad:
            raise ValueError(f"hand-held and flight parts do not join at {self.switch_s:g} s: "
                             f"{bad}")

    @property
    def end_s(self) -> float:
        """When the last flight is over: landed and disarmed."""
        return self.flights[-1].touchdown + DISARM_AFTER_TOUCHDOWN_S

    def truth(self, t: np.ndarray) -> Truth:
        t = np.asarray(t, dtype=float)
        by_hand = t < self.switch_s
        if by_hand.all():
            return self.hand.truth(t)
        if not by_hand.any():
            return self.flight.truth(t)
        a, b = self.hand.truth(t[by_hand]), self.flight.truth(t[~by_hand])
        merged = {}
        for name in ("q", "rates", "accel_ned", "velocity_ned", "position_ned"):
            out = np.empty((len(t), *getattr(a, name).shape[1:]))
            out[by_hand], out[~by_hand] = getattr(a, name), getattr(b, name)
            merged[name] = out
        return Truth(t=t, **merged)

    def flight_state(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Disarmed and ON_GROUND in the hand (however high it is lifted), then the
        flight plan's state."""
        t = np.asarray(t, dtype=float)
        armed, landed = self.flight.flight_state(t)
        hand_armed, hand_landed = self.hand.flight_state(t)
        by_hand = t < self.switch_s
        return (np.where(by_hand, hand_armed, armed),
                np.where(by_hand, hand_landed, landed).astype(np.uint8))


def handheld_flight(drag_per_s: float = DEFAULT_DRAG_PER_S) -> HandheldThenFlight:
    """Carried by hand on the bench (disarmed), set down, then two multirotor flights
    with a rest on the ground between them (``hil.multirotor.bench_flights``).

    A companion must tell a device in the hand from a vehicle that flies, and a landed
    vehicle from one in the air, on the same board in one session; this profile has
    all of it. Times [s] (``flights`` has the exact ones):

    * 0-12.5 in the hand (``handheld``), disarmed, ON_GROUND although lifted 25 cm;
      set down level facing 30° at 12.5, still on the ground until lift-off;
    * armed at 15.0, TAKEOFF 16.5-21.8 (to 8 m), IN_AIR, LANDING 48.2-54.8,
      touchdown 54.8, disarmed at 56.8;
    * 10 s on the ground between the flights, disarmed from 56.8 to 63.3 (not armed
      idle: PX4 disarms 2 s after landing, ``DISARM_AFTER_TOUCHDOWN_S``), armed again
      at 63.3;
    * TAKEOFF 64.8-69.1 (to 6 m), IN_AIR, LANDING 96.5-101.8, touchdown 101.8,
      disarmed at 103.8 (``end_s``); on the ground, disarmed, after that whatever
      the duration.
    """
    hand = handheld()
    switch = max(channel_end(c) for c in (*hand.euler, *hand.position))
    yaw0 = float(hand.euler[2].evaluate(np.array([switch]))[0][0])
    return HandheldThenFlight("handheld_flight", hand, bench_flights(switch, yaw0, drag_per_s),
                              switch)


class FileProfile(Profile):
    """Replay of a recorded attitude (see the module docstring for the CSV format)."""

    def __init__(self, path: str | Path):
        self.name = f"file:{path}"
        self.times, self.q = load_attitude_csv(path)
        dt = np.diff(self.times)
        step = quat.multiply(quat.conjugate(self.q[:-1]), self.q[1:])
        self.rates = quat.to_rotvec(step) / dt[:, None]  # constant body rate per interval

    def truth(self, t: np.ndarray) -> Truth:
        t = np.asarray(t, dtype=float)
        last = len(self.times) - 1
        i = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, last)
        seg = np.minimum(i, last - 1)
        moving = (t >= self.times[0]) & (t < self.times[-1])
        tau = np.clip(t - self.times[seg], 0.0, None)
        rates = np.where(moving[:, None], self.rates[seg], 0.0)
        base = np.where(moving[:, None], self.q[seg], self.q[i])
        q = quat.canonical(quat.multiply(base, quat.from_rotvec(rates * tau[:, None])))
        zeros = np.zeros((len(t), 3))
        return Truth(t=t, q=q, rates=rates, accel_ned=zeros, velocity_ned=zeros,
                     position_ned=zeros)


def load_attitude_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(times from 0, unit quaternions with a continuous sign) from a truth CSV."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"cannot read motion file {path}: {exc}") from exc
    numbered = [(n, line) for n, line in enumerate(text.splitlines(), start=1)
                if line.strip() and not line.startswith("#")]
    reader = csv.DictReader([line for _, line in numbered])
    need = ["time_s", "qw", "qx", "qy", "qz"]
    if reader.fieldnames is None or any(k not in reader.fieldnames for k in need):
        raise ValueError(f"{path}: header must contain {','.join(need)}")
    try:
        data = np.array([[float(r[k]) for k in need] for r in reader])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: non-numeric value ({exc})") from exc
    if len(data) and not np.all(np.isfinite(data)):
        k = int(np.flatnonzero(~np.all(np.isfinite(data), axis=1))[0])
        line_no = numbered[k + 1][0]  # +1: the header  # one CSV record per line
        raise ValueError(f"{path}: line {line_no}: not a finite number "
                         f"({','.join(f'{v:g}' for v in data[k])})")
    if len(data) < 2:
        raise ValueError(f"{path}: need at least 2 rows of finite numbers")
    times = data[:, 0] - data[0, 0]
    if np.any(np.diff(times) <= 0.0):
        raise ValueError(f"{path}: time_s must be strictly increasing")
    norms = np.linalg.norm(data[:, 1:], axis=1)
    if np.any(norms < 1e-6):
        raise ValueError(f"{path}: zero-length quaternion")
    q = data[:, 1:] / norms[:, None]
    for k in range(1, len(q)):  # shortest path between rows
        if np.dot(q[k], q[k - 1]) < 0.0:
            q[k] = -q[k]
    return times, q


def make_profile(name: str, duration_s: float = 60.0,
                 drag_per_s: float = DEFAULT_DRAG_PER_S) -> Profile:
    """A profile by name (``static``, ``tilt``, ``flight``, ``gentle``, ``aggressive``,
    ``calibration``, ``handheld_flight``, ``file:PATH``); ``drag_per_s`` is the rotor
    drag of ``flight`` and ``handheld_flight``."""
    if name.startswith("file:"):
        return FileProfile(name[len("file:"):])
    builders = {"static": lambda: static(), "tilt": lambda: tilt(),
                "flight": lambda: multirotor_flight(duration_s, drag_per_s),
                "gentle": lambda: gentle(duration_s), "aggressive": lambda: aggressive(duration_s),
                "calibration": calibration,
                "handheld_flight": lambda: handheld_flight(drag_per_s)}
    if name not in builders:
        raise ValueError(f"unknown profile {name!r}; valid: {', '.join(PROFILE_NAMES)}, file:PATH")
    return builders[name]()
