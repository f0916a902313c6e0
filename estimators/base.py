"""The one small interface every estimator implements.

A concrete estimator supplies:

* ``name`` (the registry key) and ``Params``, a frozen dataclass deriving from
  :class:`CommonParams` whose fields are the tunable parameters with their defaults
  (each field's ``metadata["doc"]`` says its unit and meaning);
* ``_pack_params(p) -> np.ndarray``: the parameters as a float64 vector for the kernel;
* ``_state_size`` and optionally ``_init_private(state, p)``;
* ``_update_one`` / ``_run_batch``: the pair returned by ``_core.make_kernels(step)``.

Everything else (argument checking, sample validation, counting, initialisation,
world frame, batch) lives here and in ``_core`` so that all estimators behave alike.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import re
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from . import _core
from . import quat as Q

G = 9.80665
_NO_VELOCITY = np.full(3, np.nan)  # update()'s vel when none is given (never written)
#: Longest imu_delay taken [s]: a 2-pole low-pass at 2 Hz delays by 0.11 s; a longer delay
#: is no filter a flight controller runs, and turning forward by it would amplify noise.
MAX_IMU_DELAY_S = 0.1


def turned_forward(q: np.ndarray, gyr: np.ndarray, bias: np.ndarray, delay: float
                   ) -> np.ndarray:
    """``q ⊗ exp((ω − b)·delay)``: attitudes (N, 4) integrated from IMU samples that are
    ``delay`` seconds old (a sender's low-pass filter), carried forward to now at the body
    rate each sample measured. A body rotation multiplies on the right, so this holds in
    any output world frame. A sample without a finite rate is left as it is."""
    if delay <= 0.0:
        return q
    rate = np.nan_to_num(np.asarray(gyr, dtype=float) - bias, nan=0.0, posinf=0.0,
                         neginf=0.0)
    return Q.multiply(q, Q.from_rotvec(rate * delay))


def param(default: float | bool | str, doc: str) -> Any:
    """A dataclass field for an estimator parameter, with its unit/meaning in ``doc``."""
    return field(default=default, metadata={"doc": doc})


#: Unit (the doc's first bracket) -> (suffix of its degree alias, unit in degrees).
DEGREE_UNITS = {"rad": ("_deg", "deg"), "rad/s": ("_dps", "deg/s")}
#: The first bracket of a parameter doc: its unit.
DOC_UNIT = re.compile(r"\[([^\]]*)\]")


def doc_unit(f: dataclasses.Field) -> str | None:
    """The unit a parameter's doc gives first (``[rad/s]`` -> ``rad/s``), if any."""
    unit = DOC_UNIT.search(f.metadata.get("doc", ""))
    return None if unit is None else unit.group(1).strip()


def _shown(f: dataclasses.Field, value: float) -> str:
    """A value as the user typed it: angles also in degrees, under their alias."""
    degrees = DEGREE_UNITS.get(doc_unit(f) or "")
    if degrees is None or not math.isfinite(value):
        return f"{value:g}"
    return f"{value:g} ({math.degrees(value):g} {degrees[1]}, as {f.name}{degrees[0]})"


def check_param_value(f: dataclasses.Field, value: Any,
                      bounds: tuple[float, float] | None) -> None:
    """ValueError (one line, naming the parameter in the user's units) for a value outside
    the parameter's kind: a flag that is not 0/1, a number outside ``bounds``."""
    if isinstance(f.default, bool):
        if not (isinstance(value, bool) or value in (0, 1)):
            raise ValueError(f"parameter {f.name!r} is a flag: 0/1 or true/false, "
                             f"got {value!r}")
        return
    if bounds is None or isinstance(value, str) or not isinstance(f.default, int | float):
        return
    lo, hi = bounds
    if not lo <= float(value) <= hi:
        unit = doc_unit(f) or ""
        span = f"{lo:g}..{hi:g}" + (f" {unit}" if unit else "")
        degrees = DEGREE_UNITS.get(unit)
        if degrees is not None:
            span += f" ({math.degrees(lo):g}..{math.degrees(hi):g} {degrees[1]})"
        raise ValueError(f"parameter {f.name!r} must be within {span}, "
                         f"got {_shown(f, float(value))}")


@dataclass(frozen=True)
class CommonParams:
    """Sensor limits shared by every estimator (samples beyond them are not trusted).

    ``BOUNDS`` (a subclass extends it): parameter -> the inclusive range, in its doc's
    unit, of values that still mean something. The ranges are wide — a user may set a
    poor value, not an absurd one — and exist because past them the filters'
    arithmetic breaks without a word: a noise of 1e-200 squares to zero and is divided
    by, one of 1e308 squares to infinity and every later sample is rejected, so the
    estimate is garbage and nothing says so."""

    BOUNDS: ClassVar[dict[str, tuple[float, float]]] = {}

    acc_range: float = param(16 * G, "accelerometer full scale [m/s^2]; an axis at it is "
                                     "saturated and the sample's accelerometer is unused")
    gyr_range: float = param(math.radians(2000.0), "gyro full scale [rad/s]; saturation is "
                                                   "counted (the rate, clipped to it, still "
                                                   "integrates); beyond twice it a sample is "
                                                   "corrupt and skipped")
    max_dt: float = param(0.5, "longest usable time step [s]; longer gaps are skipped")
    declination: float = param(0.0, "magnetic declination [rad], east positive: the output "
                                    "heading is relative to true north (magnetic + "
                                    "declination) instead of magnetic north")
    aid_timeout: float = param(0.5, "velocity aiding: longest gap [s] between two velocity "
                                    "measurements (and longest age of one) that still aids")
    imu_delay: float = param(0.0, "how much older [s] each IMU sample is than its stamp: "
                                  "the group delay of a low-pass filter the sender applied "
                                  "(ArduPilot's INS_GYRO_FILTER, imu.filter_delay); the "
                                  "output is turned forward by the body rate times it")


def _check_common(p: CommonParams) -> None:
    """ValueError for common parameters no estimator can work with (an infinite
    declination makes NaN quaternions, a negative max_dt skips every sample)."""
    fields = {f.name: f for f in dataclasses.fields(p)}

    def shown(name: str) -> str:
        return _shown(fields[name], float(getattr(p, name)))

    for name in ("acc_range", "gyr_range", "max_dt", "declination", "aid_timeout",
                 "imu_delay"):
        if not math.isfinite(float(getattr(p, name))):
            raise ValueError(f"parameter {name!r} must be finite, got {shown(name)}")
    for name in ("acc_range", "gyr_range", "max_dt", "aid_timeout"):
        if not float(getattr(p, name)) > 0.0:
            raise ValueError(f"parameter {name!r} must be positive, got {shown(name)}")
    if not 0.0 <= float(p.imu_delay) <= MAX_IMU_DELAY_S:
        raise ValueError(f"parameter 'imu_delay' must be within 0..{MAX_IMU_DELAY_S} s, "
                         f"got {shown('imu_delay')}")
    if abs(float(p.declination)) > math.pi:
        raise ValueError(f"parameter 'declination' must be within ±pi rad (±180 deg), "
                         f"got {shown('declination')}")


@dataclass(frozen=True)
class SampleCounters:
    """How many samples were offered, and what was skipped, unusable or rejected."""

    samples: int = 0
    skipped: int = 0
    bad_dt: int = 0
    acc_unusable: int = 0
    mag_unusable: int = 0
    acc_rejected: int = 0
    mag_rejected: int = 0
    gyr_saturated: int = 0


@dataclass(frozen=True)
class EstimatorStatus:
    """A snapshot of an estimator's internal state, for telemetry and debugging."""

    q: np.ndarray  # [w, x, y, z], body -> requested world frame
    bias: np.ndarray  # gyro bias estimate [rad/s] (zeros if the estimator has none)
    initialising: bool  # True until the first usable accelerometer sample
    acc_rejected: bool  # last sample's accelerometer judged non-gravitational
    mag_rejected: bool  # last sample's magnetometer judged disturbed
    counters: SampleCounters


@dataclass(frozen=True)
class BatchResult:
    """Per-sample output of a batch run."""

    q: np.ndarray  # (N, 4)
    bias: np.ndarray  # (N, 3)
    flags: np.ndarray  # (N,) uint8, bits _core.F_*

    @property
    def initialised(self) -> np.ndarray:
        return (self.flags & _core.F_INITIALISED) != 0

    @property
    def acc_rejected(self) -> np.ndarray:
        return (self.flags & _core.F_ACC_REJECTED) != 0

    @property
    def mag_rejected(self) -> np.ndarray:
        return (self.flags & _core.F_MAG_REJECTED) != 0

    @property
    def skipped(self) -> np.ndarray:
        return (self.flags & _core.F_SKIPPED) != 0

    @property
    def air_model(self) -> np.ndarray:
        """Samples on which the estimator ran its in-flight model (eskf: rotor drag)."""
        return (self.flags & _core.F_AIR_MODEL) != 0


class Estimator:
    """Base class: attitude from gyro + accelerometer (+ magnetometer) samples."""

    name: ClassVar[str] = ""
    #: Someone else's published filter wrapped for comparison (``estimators.vqf_online``):
    #: run only when named, never by default.
    reference: ClassVar[bool] = False
    Params: ClassVar[type[CommonParams]] = CommonParams
    _state_size: ClassVar[int] = _core.PRIVATE
    # Set by subclasses from _core.make_kernels(step); staticmethod-wrapped.
    _update_one: ClassVar[Any]
    _run_batch: ClassVar[Any]

    def __init__(self, rate_hz: float = 1000.0, world: str = "NED",
                 q0: np.ndarray | None = None, **params: float) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"rate_hz must be a positive number, got {rate_hz!r}")
        self.rate_hz = float(rate_hz)
        self.world = "ENU" if Q.world_is_enu(world) else "NED"
        self.params = self.make_params(**params)
        self._dt = 1.0 / self.rate_hz
        # One buffer holds state, parameters, counters and output (see
        # _core.make_workspace); the attributes below are views into it.
        self._ws = _core.make_workspace(
            self._state_size,
            np.ascontiguousarray(self._pack_params(self.params), dtype=float).ravel(),
            np.array([self.params.acc_range, self.params.gyr_range, self.params.max_dt,
                      *self.output_rotation, self.params.aid_timeout]))
        (self._state, self._params_vec, self._common, self._counters,
         self._out) = _core.workspace_views(self._ws)
        self._q0 = None if q0 is None else np.array(q0, dtype=float)
        self._flight = _core.FLIGHT_UNKNOWN
        _core.prepare_update(type(self)._update_one)
        self._kernel = type(self)._update_one  # bound once: update() is per sample
        self.reset()

    # --- parameters ----------------------------------------------------------------
    @classmethod
    def check_available(cls) -> None:
        """ValueError when something the estimator needs is not installed (a reference's
        package): said when its spec is parsed, not when the first sample comes."""

    @classmethod
    def param_names(cls) -> list[str]:
        return [f.name for f in dataclasses.fields(cls.Params)]

    @classmethod
    def param_docs(cls) -> dict[str, str]:
        """Parameter name -> 'default; doc' (for CLI help and the README)."""
        return {f.name: f"{f.default!r}; {f.metadata.get('doc', '')}"
                for f in dataclasses.fields(cls.Params)}

    @classmethod
    def make_params(cls, **params: float) -> CommonParams:
        unknown = sorted(set(params) - set(cls.param_names()))
        if unknown:
            raise ValueError(f"unknown parameter(s) {unknown} for estimator {cls.name!r}; "
                             f"valid: {cls.param_names()}")
        for key, value in params.items():
            if not isinstance(value, int | float | bool | np.number) or (
                    isinstance(value, float) and math.isnan(value)):
                raise ValueError(f"parameter {key!r} must be a number, got {value!r}")
        made = cls.Params(**params)
        _check_common(made)
        for f in dataclasses.fields(made):
            check_param_value(f, getattr(made, f.name), made.BOUNDS.get(f.name))
        return made

    @property
    def output_rotation(self) -> np.ndarray:
        """W with ``q_world = W ⊗ q_internal``: estimators work in magnetic NED; the
        declination turns magnetic into true north, then NED becomes ENU if asked."""
        w = Q.from_axis_angle(np.array([0.0, 0.0, 1.0]), self.params.declination)
        return Q.ned_to_enu(w) if self.world == "ENU" else w

    def set_declination(self, declination: float) -> None:
        """Report true north with another declination [rad] from the next output on.

        The estimate lives in magnetic north (the magnetometer's reference), so only
        the output rotation changes and nothing re-converges: for a live source whose
        declination becomes known after it started (an autopilot parameter, the first
        position fix). Velocities given later are taken in the new true north.
        """
        params = dataclasses.replace(self.params, declination=float(declination))
        _check_common(params)
        self.params = params
        self._common[_core.P_OUT:_core.P_OUT + 4] = self.output_rotation

    def set_imu_delay(self, delay_s: float) -> None:
        """Carry the output forward by another ``imu_delay`` [s] from the next output on
        (for a live source whose filter setting becomes known after it started: an
        autopilot parameter). Only the output changes; nothing re-converges."""
        params = dataclasses.replace(self.params, imu_delay=float(delay_s))
        _check_common(params)
        self._params_vec[:] = np.ascontiguousarray(self._pack_params(params),
                                                   dtype=float).ravel()
        self.params = params

    def set_flight_state(self, airborne: bool | None) -> None:
        """What the vehicle says it is doing from the next sample on: True in the air
        (taking off, flying, landing), False on the ground (disarmed, landed, carried by
        hand), None when nothing says (the estimator then decides from the data).

        Only estimators with a model that holds in flight alone use it (eskf's rotor
        drag); it survives ``reset``, since a reboot of the estimator is not a landing.
        """
        self._flight = (_core.FLIGHT_UNKNOWN if airborne is None else
                        _core.FLIGHT_AIRBORNE if airborne else _core.FLIGHT_GROUND)
        self._state[_core.FLIGHT] = self._flight
        if airborne is False:  # off from this sample on, not from the next filter step
            self._state[_core.AIR_MODEL] = 0.0

    @property
    def air_model(self) -> bool:
        """Whether the last sample ran the in-flight model (eskf: rotor drag)."""
        return bool(self._state[_core.AIR_MODEL] > 0.0)

    def _pack_params(self, p: CommonParams) -> np.ndarray:
        return np.zeros(1)

    def _init_private(self, state: np.ndarray, p: CommonParams) -> None:
        """Initialise state[PRIVATE:] (covariances, integrators)."""

    # --- state -----------------------------------------------------------------------
    def reset(self, q0: np.ndarray | None = None) -> None:
        """Forget everything; start from ``q0`` (world frame) or the next usable sample."""
        if q0 is not None:
            self._q0 = np.array(q0, dtype=float)
        state = np.zeros(self._state_size)
        state[0] = 1.0
        state[_core.AID_VT:_core.AID_VT + 3] = -math.inf  # no velocity measurement yet
        if self._q0 is not None:
            q = Q.normalize(self._q0)
            if q.shape != (4,) or not np.all(np.isfinite(q)):
                raise ValueError(f"q0 must be a finite non-zero quaternion, got {self._q0!r}")
            state[0:4] = Q.multiply(Q.conjugate(self.output_rotation), q)
            state[_core.INIT] = 1.0
        state[_core.FLIGHT] = self._flight
        self._init_private(state, self.params)
        self._state[:] = state
        self._counters[:] = 0.0
        self._last_flags = 0
        self._last_gyr: Any = np.zeros(3)  # the last sample's gyro, for imu_delay

    @property
    def q(self) -> np.ndarray:
        """Current attitude [w, x, y, z], body -> world."""
        type(self)._write_output(self._state, self._common, self._out)
        if self.params.imu_delay > 0.0:  # (a gyro kept by reference is made an array now)
            self._last_gyr = np.ascontiguousarray(self._last_gyr, dtype=np.float64)
        return self._turned_forward(self._out.copy())

    @property
    def bias(self) -> np.ndarray:
        """Current gyro-bias estimate [rad/s] (zeros if the estimator has none)."""
        return self._state[_core.B0:_core.B0 + 3].copy()

    @property
    def counters(self) -> SampleCounters:
        return SampleCounters(*(int(c) for c in self._counters))

    @property
    def status(self) -> EstimatorStatus:
        return EstimatorStatus(
            q=self.q, bias=self.bias,
            initialising=self._state[_core.INIT] <= 0.0,
            acc_rejected=bool(self._last_flags & _core.F_ACC_REJECTED),
            mag_rejected=bool(self._last_flags & _core.F_MAG_REJECTED),
            counters=self.counters,
        )

    # --- estimation --------------------------------------------------------------------
    def update(self, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None = None,
               dt: float | None = None, *, vel: np.ndarray | None = None,
               vel_age: float = 0.0) -> np.ndarray:
        """Advance by one sample and return the attitude [w, x, y, z] (a new array).

        ``gyr`` rad/s, ``acc`` m/s^2 (specific force), ``mag`` any unit or None, ``dt``
        seconds since the previous sample (default ``1/rate_hz``). Bad samples are counted
        in ``counters``, never raised: a sensor stream must not crash the caller.

        ``vel`` (optional aiding): the vehicle's velocity [m/s] in the output world frame
        (NED or ENU, true north when ``declination`` is set), measured ``vel_age``
        seconds before this sample; None or NaN components when no new measurement
        arrived with this sample. Estimators that use the accelerometer as a gravity
        reference then remove the vehicle's acceleration from it.
        """
        step_dt = self._dt if dt is None else dt
        v = _NO_VELOCITY if vel is None else vel
        try:
            # Fast path: contiguous float64 (3,) arrays go straight to the kernel.
            flags = self._kernel(self._ws, gyr, acc, mag, step_dt, v, vel_age)
        except TypeError:
            flags = -1
        if flags < 0:
            flags = self._update_converted(gyr, acc, mag, step_dt, v, vel_age)
        self._last_flags = flags
        if self.params.imu_delay > 0.0:
            self._last_gyr = np.array(gyr, dtype=np.float64)  # a copy: callers reuse buffers
            return self._turned_forward(self._out.copy())
        self._last_gyr = gyr  # (copied only when it is used: per-sample cost)
        return self._out.copy()

    def _turned_forward(self, q: np.ndarray) -> np.ndarray:
        """One output (a fresh array) carried forward by ``imu_delay`` at the last
        sample's rate, in place."""
        if self.params.imu_delay > 0.0:
            _core.turn_forward(q, self._last_gyr, self._state, self.params.imu_delay)
        return q

    def _update_converted(self, gyr: object, acc: object, mag: object, dt: object,
                          vel: object, vel_age: object) -> int:
        """update() for inputs the kernel does not take as they are: convert or raise."""
        g = np.ascontiguousarray(gyr, dtype=np.float64)
        a = np.ascontiguousarray(acc, dtype=np.float64)
        if g.shape != (3,) or a.shape != (3,):
            raise ValueError(f"gyr and acc must have shape (3,), got {g.shape} and {a.shape}")
        m = None
        if mag is not None:
            m = np.ascontiguousarray(mag, dtype=np.float64)
            if m.shape != (3,):
                raise ValueError(f"mag must have shape (3,), got {m.shape}")
        v = np.ascontiguousarray(vel, dtype=np.float64)
        if v.shape != (3,):
            raise ValueError(f"vel must have shape (3,), got {v.shape}")
        try:
            step_dt = float(dt)  # type: ignore[arg-type]
            age = float(vel_age)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise ValueError(f"dt and vel_age must be numbers of seconds, got {dt!r} and "
                             f"{vel_age!r}") from None
        return type(self)._update_one(self._ws, g, a, m, step_dt, v, age)

    def run(self, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None = None,
            dt: float | np.ndarray | None = None, *, vel: np.ndarray | None = None,
            vel_age: float | np.ndarray | None = None,
            airborne: np.ndarray | None = None) -> BatchResult:
        """Process (N, 3) arrays in a compiled loop, continuing from the current state.

        ``dt`` is a scalar, an (N,) array of per-sample steps, or None for ``1/rate_hz``.
        ``vel`` (N, 3) and ``vel_age`` (scalar or (N,), default 0) as in ``update``, NaN
        rows where no velocity measurement arrives. ``airborne`` (N,): the vehicle's
        flight state per sample as in ``set_flight_state`` (1 in the air, 0 on the
        ground, NaN unknown); the last one stays set after the run. Gives the same
        quaternions as calling ``update`` (and ``set_flight_state``) N times.
        """
        if airborne is not None:
            return self._run_by_flight_state(gyr, acc, mag, dt, vel, vel_age, airborne)
        G_ = np.ascontiguousarray(gyr, dtype=np.float64)
        A_ = np.ascontiguousarray(acc, dtype=np.float64)
        n = G_.shape[0]
        if G_.ndim != 2 or G_.shape[1] != 3 or A_.shape != G_.shape:
            raise ValueError(f"gyr and acc must both be (N, 3), got {G_.shape} and {A_.shape}")
        if mag is None:
            M_, has_mag = np.zeros((1, 3)), False
        else:
            M_ = np.ascontiguousarray(mag, dtype=np.float64)
            if M_.shape != G_.shape:
                raise ValueError(f"mag must be (N, 3) like gyr, got {M_.shape}")
            has_mag = True
        dts = self._per_sample("dt", 1.0 / self.rate_hz if dt is None else dt, n)
        if vel is None:
            V_ = _NO_VELOCITY.reshape(1, 3)
        else:
            V_ = np.ascontiguousarray(vel, dtype=np.float64)
            if V_.shape != G_.shape:
                raise ValueError(f"vel must be (N, 3) like gyr, got {V_.shape}")
        ages = self._per_sample("vel_age", 0.0 if vel_age is None else vel_age, n)
        q_out = np.empty((n, 4))
        b_out = np.empty((n, 3))
        f_out = np.zeros(n, dtype=np.uint8)
        if n:
            type(self)._run_batch(self._state, self._params_vec, self._common, G_, A_, M_,
                                  has_mag, dts, self._counters, q_out, b_out, f_out, V_, ages)
            self._last_flags = int(f_out[-1])
            self._last_gyr = G_[-1].copy()
            if self.params.imu_delay > 0.0:
                q_out = turned_forward(q_out, G_, b_out, self.params.imu_delay)
        return BatchResult(q=q_out, bias=b_out, flags=f_out)

    def _run_by_flight_state(self, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None,
                             dt: float | np.ndarray | None, vel: np.ndarray | None,
                             vel_age: float | np.ndarray | None,
                             airborne: np.ndarray) -> BatchResult:
        """``run`` in pieces of constant flight state (it changes a few times a flight)."""
        n = np.asarray(gyr).shape[0]
        state = np.asarray(airborne, dtype=np.float64)
        if state.shape != (n,):
            raise ValueError(f"airborne must have shape ({n},), got {state.shape}")
        code = np.where(np.isnan(state), 2, state != 0.0).astype(np.int8)
        cuts = [0, *(np.flatnonzero(np.diff(code)) + 1).tolist(), n]

        def piece(x: object, a: int, b: int) -> object:
            arr = np.asarray(x) if x is not None else None
            return arr[a:b] if arr is not None and arr.ndim >= 1 and arr.shape[0] == n else x

        parts = []
        for a, b in itertools.pairwise(cuts):
            if b <= a:
                continue
            self.set_flight_state(None if code[a] == 2 else bool(code[a]))
            parts.append(self.run(piece(gyr, a, b), piece(acc, a, b), piece(mag, a, b),
                                  piece(dt, a, b), vel=piece(vel, a, b),
                                  vel_age=piece(vel_age, a, b)))
        if not parts:
            return self.run(gyr, acc, mag, dt, vel=vel, vel_age=vel_age)
        return BatchResult(q=np.concatenate([p.q for p in parts]),
                           bias=np.concatenate([p.bias for p in parts]),
                           flags=np.concatenate([p.flags for p in parts]))

    @staticmethod
    def _per_sample(name: str, value: float | np.ndarray, n: int) -> np.ndarray:
        """A scalar or (N,) input as a contiguous float64 array of shape (1,) or (N,)."""
        arr = np.ascontiguousarray(np.atleast_1d(np.asarray(value, dtype=np.float64)))
        if arr.shape not in ((1,), (n,)):
            raise ValueError(f"{name} must be a scalar or shape ({n},), got {arr.shape}")
        return arr

    _write_output = staticmethod(_core.write_output)
