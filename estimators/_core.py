"""Compiled building blocks shared by every estimator.

Each estimator writes one numba function, its ``step``::

    step(state, params, gx, gy, gz, ax, ay, az, mx, my, mz, acc_ok, mag_ok, dt) -> None

that advances ``state`` by one sample *after* the common checks done here: sample
validation, ``dt`` checks, initialisation from the first usable sample, counting, and
output in the requested world frame. ``make_kernels(step)`` closes over it and returns
``update_one`` (one sample on a packed workspace, called by ``Estimator.update``) and
``run_batch`` (a compiled loop, called by ``batch``). Both run the very same code per
sample, which is why ``batch`` equals ``update`` bit for bit.

Velocity aiding (optional, per sample): the vehicle's world-frame velocity, NaN where no
new measurement arrives, with its age (how long before this sample it was valid). The
driver turns it into the internal frame. For an ordinary step it differentiates
consecutive measurements into a linear acceleration (as PX4's attitude_estimator_q does)
and removes it from the specific force before the step sees the accelerometer, so that
every estimator that takes the accelerometer for gravity is aided alike. A step built
with ``make_kernels(step, takes_velocity=True)`` instead receives the velocity itself,
``step(..., dt, vx, vy, vz, v_age)``, and models it (eskf).

Internally every estimator works in NED (gravity reference ``[0, 0, -1]`` for the
accelerometer's specific force direction, magnetic north along +x); ENU is a fixed
left-multiplication applied on output.
"""

from __future__ import annotations

import hashlib
import inspect
import math
from pathlib import Path

import numpy as np
from numba import njit, types
from numba.core.caching import FunctionCache


def _package_digest() -> str:
    """Digest of every source file of this package.

    numba's own cache check looks only at the file that defines a function, but the
    compiled code freezes globals read from other modules (``_core.PRIVATE`` inside an
    estimator's step, say). After an update that changes ``_core`` but not the estimator's
    file, a cached step would silently run with the old layout. Every cache key here
    includes this digest, so any change to the package recompiles everything once.
    """
    h = hashlib.sha256()
    for f in sorted(Path(__file__).parent.glob("*.py")):
        h.update(f.name.encode() + f.read_bytes())
    return h.hexdigest()


PACKAGE_DIGEST = _package_digest()


class _PackageKeyedCache(FunctionCache):
    """numba's disk cache with :data:`PACKAGE_DIGEST` in every key."""

    def _index_key(self, sig, codegen):
        return (*super()._index_key(sig, codegen), PACKAGE_DIGEST)


def kernel(fn=None, **options):
    """``njit(cache=True, **options)`` whose cache entries are keyed by the package digest
    (use instead of ``njit(cache=True)`` for every compiled function of the package)."""
    def wrap(f):
        dispatcher = njit(cache=True, **options)(f)
        dispatcher._cache = _PackageKeyedCache(dispatcher.py_func)
        return dispatcher
    return wrap if fn is None else wrap(fn)

# --- state vector layout (float64), shared by all estimators -------------------
Q0, Q1, Q2, Q3 = 0, 1, 2, 3  # attitude, body -> NED
B0 = 4  # gyro bias estimate [rad/s] in state[4:7] (zeros when not estimated)
INIT = 7  # 1.0 once initialised
ACC_REJ = 8  # 1.0 when the last sample's accelerometer was rejected as disturbed
MAG_REJ = 9  # 1.0 when the last sample's magnetometer was rejected as disturbed
# Velocity aiding, kept by the driver (internal frame: magnetic NED):
AID_V = 10  # 3: last velocity measurement per axis [m/s]
AID_VT = 13  # 3: when it was valid, on the RUN_T clock [s] (-inf: none yet)
AID_A = 16  # 3: linear acceleration from the last two measurements per axis [m/s^2]
RUN_T = 19  # run clock: sum of the steps of the samples processed [s]
#: What the vehicle says it is doing (``Estimator.set_flight_state``): FLIGHT_AIRBORNE,
#: FLIGHT_GROUND or FLIGHT_UNKNOWN (an estimator with a flight-only model then decides
#: from the data). Estimators without such a model ignore it.
FLIGHT = 20
AIR_MODEL = 21  # 1.0 while the estimator runs its in-flight model (reported per sample)
PRIVATE = 22  # first index an estimator may use for its own state
FLIGHT_UNKNOWN, FLIGHT_GROUND, FLIGHT_AIRBORNE = -1.0, 0.0, 1.0

# --- counters (float64 slots of the workspace: whole numbers, exact below 2**53) ------
C_SAMPLES = 0  # samples offered
C_SKIPPED = 1  # samples not used at all (gyro non-finite or impossible, or bad dt)
C_BAD_DT = 2  # of those: dt non-finite, <= 0 or > max_dt
C_ACC_UNUSABLE = 3  # accelerometer NaN/inf, zero-norm or saturated (gyro still used)
C_MAG_UNUSABLE = 4  # magnetometer given but NaN/inf or zero-norm
C_ACC_REJECTED = 5  # usable but rejected by the estimator as non-gravitational
C_MAG_REJECTED = 6  # usable but rejected by the estimator as disturbed
C_GYR_SATURATED = 7  # gyro at full scale (integrated clipped to it: the best we have)
N_COUNTERS = 8
COUNTER_NAMES = (
    "samples", "skipped", "bad_dt", "acc_unusable", "mag_unusable",
    "acc_rejected", "mag_rejected", "gyr_saturated",
)

# --- common parameter vector (float64) --------------------------------------------
P_ACC_RANGE = 0  # full scale [m/s^2]: an axis at >= 99.9 % of it is saturated
P_GYR_RANGE = 1  # full scale [rad/s]
P_MAX_DT = 2  # longest usable step [s]
P_OUT = 3  # common[3:7]: output rotation W, out = W ⊗ q (NED -> ENU and/or declination)
P_AID_TIMEOUT = 7  # longest gap between velocity measurements that still aids [s]
N_COMMON = 8

# --- per-estimator workspace (float64) for update_one ------------------------------
# ws = [header | state | params | common | counters | out(4)]; the header holds where
# each section ends, so one compiled driver serves every estimator's sizes. Packing the
# per-call arrays into one buffer keeps a Python -> numba call at three array arguments:
# argument unboxing, not the filter arithmetic, is most of the per-sample cost.
W_STATE_END, W_PARAMS_END, W_COMMON_END, W_COUNTERS_END = 0, 1, 2, 3
W_HEADER = 4
W_OUT = 4  # output quaternion length at the end

# --- per-sample flags written by run_batch (bit field, uint8) -----------------------
F_INITIALISED = 1
F_ACC_REJECTED = 2
F_MAG_REJECTED = 4
F_SKIPPED = 8
F_ACC_UNUSABLE = 16
F_AIR_MODEL = 32  # the estimator's in-flight model (eskf: rotor drag) was on

_SAT_FRACTION = 0.999
#: A gyro axis beyond this many times its full scale is no saturated reading (a sensor
#: cannot report it) but a corrupt one: the sample is skipped, not clipped and integrated.
GYR_CORRUPT_FACTOR = 2.0
_ACC_MIN_NORM = 1e-3  # m/s^2: below this the direction of gravity is meaningless


@kernel(inline="always")
def finite3(x: float, y: float, z: float) -> bool:
    return math.isfinite(x) and math.isfinite(y) and math.isfinite(z)


@kernel(inline="always")
def quat_multiply(a0: float, a1: float, a2: float, a3: float, b0: float, b1: float,
                  b2: float, b3: float) -> tuple:
    """Hamilton product a ⊗ b of two quaternions given by their components (the compiled
    kernels' form of ``estimators.quat.multiply``)."""
    return (a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
            a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
            a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
            a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0)


@kernel(inline="always")
def quat_normalized(w: float, x: float, y: float, z: float) -> tuple:
    """The quaternion (w, x, y, z) scaled to unit norm."""
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    return w / norm, x / norm, y / norm, z / norm


@kernel(inline="always")
def quat_exp(x: float, y: float, z: float) -> tuple:
    """Quaternion of the rotation vector (x, y, z) [rad] (the compiled kernels' form of
    ``estimators.quat.from_rotvec``)."""
    angle = math.sqrt(x * x + y * y + z * z)
    if angle < 1e-12:
        return 1.0, 0.5 * x, 0.5 * y, 0.5 * z
    s = math.sin(0.5 * angle) / angle
    return math.cos(0.5 * angle), x * s, y * s, z * s


@kernel(inline="always")
def acc_usable(ax: float, ay: float, az: float, acc_range: float) -> bool:
    """Finite, not ~zero, and no axis clipped at full scale."""
    if not finite3(ax, ay, az):
        return False
    lim = _SAT_FRACTION * acc_range
    if abs(ax) >= lim or abs(ay) >= lim or abs(az) >= lim:
        return False
    return ax * ax + ay * ay + az * az > _ACC_MIN_NORM * _ACC_MIN_NORM


@kernel(inline="always")
def mag_usable(mx: float, my: float, mz: float) -> bool:
    """Finite and non-zero (units are free, only the direction matters)."""
    return finite3(mx, my, mz) and mx * mx + my * my + mz * mz > 1e-24


@kernel
def normalize_q(state: np.ndarray) -> None:
    """Renormalise state[0:4]; an unrecoverable quaternion resets to identity."""
    n = math.sqrt(state[0] ** 2 + state[1] ** 2 + state[2] ** 2 + state[3] ** 2)
    if n > 1e-12 and math.isfinite(n):
        state[0] /= n
        state[1] /= n
        state[2] /= n
        state[3] /= n
    else:
        state[0], state[1], state[2], state[3] = 1.0, 0.0, 0.0, 0.0


@kernel
def integrate_first_order(state: np.ndarray, wx: float, wy: float, wz: float,
                          dt: float) -> None:
    """q += 0.5 · q ⊗ [0, w] · dt, then normalise (the seeds' first-order Runge-Kutta)."""
    h = 0.5 * dt
    w, x, y, z = state[0], state[1], state[2], state[3]
    state[0] = w + (-x * wx - y * wy - z * wz) * h
    state[1] = x + (w * wx + y * wz - z * wy) * h
    state[2] = y + (w * wy - x * wz + z * wx) * h
    state[3] = z + (w * wz + x * wy - y * wx) * h
    normalize_q(state)


@kernel
def integrate_exact(state: np.ndarray, wx: float, wy: float, wz: float, dt: float) -> None:
    """q ← q ⊗ exp(w·dt/2): exact for a rate constant over the step, then normalise."""
    angle = math.sqrt(wx * wx + wy * wy + wz * wz) * dt
    half = 0.5 * angle
    if angle < 1e-6:
        k = 0.5 * dt * (1.0 - angle * angle / 24.0)
        c = 1.0 - half * half / 2.0
    else:
        k = math.sin(half) / angle * dt
        c = math.cos(half)
    dx, dy, dz = wx * k, wy * k, wz * k
    w, x, y, z = state[0], state[1], state[2], state[3]
    state[0] = w * c - x * dx - y * dy - z * dz
    state[1] = w * dx + x * c + y * dz - z * dy
    state[2] = w * dy - x * dz + y * c + z * dx
    state[3] = w * dz + x * dy - y * dx + z * c
    normalize_q(state)


@kernel
def body_to_world(state: np.ndarray, vx: float, vy: float, vz: float) -> tuple:
    """R(q) · v for the attitude in state[0:4]."""
    w, x, y, z = state[0], state[1], state[2], state[3]
    return (
        (1 - 2 * (y * y + z * z)) * vx + 2 * (x * y - w * z) * vy + 2 * (x * z + w * y) * vz,
        2 * (x * y + w * z) * vx + (1 - 2 * (x * x + z * z)) * vy + 2 * (y * z - w * x) * vz,
        2 * (x * z - w * y) * vx + 2 * (y * z + w * x) * vy + (1 - 2 * (x * x + y * y)) * vz,
    )


@kernel
def world_to_body(state: np.ndarray, vx: float, vy: float, vz: float) -> tuple:
    """R(q)ᵀ · v for the attitude in state[0:4]."""
    w, x, y, z = state[0], state[1], state[2], state[3]
    return (
        (1 - 2 * (y * y + z * z)) * vx + 2 * (x * y + w * z) * vy + 2 * (x * z - w * y) * vz,
        2 * (x * y - w * z) * vx + (1 - 2 * (x * x + z * z)) * vy + 2 * (y * z + w * x) * vz,
        2 * (x * z + w * y) * vx + 2 * (y * z - w * x) * vy + (1 - 2 * (x * x + y * y)) * vz,
    )


@kernel
def set_q_from_dcm(state: np.ndarray, r00: float, r01: float, r02: float, r10: float,
                   r11: float, r12: float, r20: float, r21: float, r22: float) -> None:
    """state[0:4] ← quaternion of the rotation matrix R (Shepperd's method)."""
    tr = r00 + r11 + r22
    if tr >= r00 and tr >= r11 and tr >= r22:
        s = 2.0 * math.sqrt(1.0 + tr)
        state[0], state[1] = 0.25 * s, (r21 - r12) / s
        state[2], state[3] = (r02 - r20) / s, (r10 - r01) / s
    elif r00 >= r11 and r00 >= r22:
        s = 2.0 * math.sqrt(1.0 + r00 - r11 - r22)
        state[0], state[1] = (r21 - r12) / s, 0.25 * s
        state[2], state[3] = (r01 + r10) / s, (r02 + r20) / s
    elif r11 >= r22:
        s = 2.0 * math.sqrt(1.0 + r11 - r00 - r22)
        state[0], state[1] = (r02 - r20) / s, (r01 + r10) / s
        state[2], state[3] = 0.25 * s, (r12 + r21) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r22 - r00 - r11)
        state[0], state[1] = (r10 - r01) / s, (r02 + r20) / s
        state[2], state[3] = (r12 + r21) / s, 0.25 * s
    if state[0] < 0.0:
        for i in range(4):
            state[i] = -state[i]
    normalize_q(state)


@kernel
def init_from_acc_mag(state: np.ndarray, ax: float, ay: float, az: float, mx: float,
                      my: float, mz: float, use_mag: bool) -> None:
    """Attitude from one sample: down = -acc; north from the magnetometer, else yaw 0."""
    na = math.sqrt(ax * ax + ay * ay + az * az)
    dx, dy, dz = -ax / na, -ay / na, -az / na
    rx, ry, rz = (mx, my, mz) if use_mag else (1.0, 0.0, 0.0)
    ex, ey, ez = dy * rz - dz * ry, dz * rx - dx * rz, dx * ry - dy * rx
    ne = math.sqrt(ex * ex + ey * ey + ez * ez)
    if ne < 1e-6 * math.sqrt(rx * rx + ry * ry + rz * rz):
        # Reference parallel to gravity: take the heading from body y instead.
        ex, ey, ez = -dz, 0.0, dx
        ne = math.sqrt(ex * ex + ez * ez)
    ex, ey, ez = ex / ne, ey / ne, ez / ne
    nx, ny, nz = ey * dz - ez * dy, ez * dx - ex * dz, ex * dy - ey * dx
    # Rows of R_world<-body are the world axes (north, east, down) in body coordinates.
    set_q_from_dcm(state, nx, ny, nz, ex, ey, ez, dx, dy, dz)


@kernel(inline="always")
def rotate_output(state: np.ndarray, common: np.ndarray) -> tuple:
    """W ⊗ q: the attitude relative to the requested world frame (magnetic NED inside).

    W (from ``output_rotation``) is the identity, the NED -> ENU swap, a rotation about
    the vertical by the magnetic declination, or both.
    """
    w, x, y, z = state[0], state[1], state[2], state[3]
    pw, px = common[P_OUT], common[P_OUT + 1]
    py, pz = common[P_OUT + 2], common[P_OUT + 3]
    return (pw * w - px * x - py * y - pz * z,
            pw * x + px * w + py * z - pz * y,
            pw * y - px * z + py * w + pz * x,
            pw * z + px * y - py * x + pz * w)


@kernel
def write_output(state: np.ndarray, common: np.ndarray, out: np.ndarray) -> None:
    """out ← attitude in the requested world frame."""
    out[0], out[1], out[2], out[3] = rotate_output(state, common)


@kernel(inline="always")
def user_to_internal(common: np.ndarray, vx: float, vy: float, vz: float) -> tuple:
    """R(W)ᵀ·v: a vector in the user's world frame (true north, NED or ENU) expressed in
    the estimators' internal magnetic NED (W from ``output_rotation``).

    A missing component stays missing without spoiling the others (GPS_RAW_INT has no
    vertical speed): W keeps the vertical vertical, so the horizontal pair maps to the
    horizontal pair and the vertical to the vertical. Without this, 0·NaN in the
    product would turn a horizontal-only velocity into no velocity at all.
    """
    w, x = common[P_OUT], common[P_OUT + 1]
    y, z = common[P_OUT + 2], common[P_OUT + 3]
    horizontal = math.isfinite(vx) and math.isfinite(vy)
    vertical = math.isfinite(vz)
    hx, hy = (vx, vy) if horizontal else (0.0, 0.0)
    hz = vz if vertical else 0.0
    ix = (1 - 2 * (y * y + z * z)) * hx + 2 * (x * y + w * z) * hy + 2 * (x * z - w * y) * hz
    iy = 2 * (x * y - w * z) * hx + (1 - 2 * (x * x + z * z)) * hy + 2 * (y * z + w * x) * hz
    iz = 2 * (x * z + w * y) * hx + 2 * (y * z - w * x) * hy + (1 - 2 * (x * x + y * y)) * hz
    if not horizontal:
        ix = iy = math.nan
    if not vertical:
        iz = math.nan
    return ix, iy, iz


@kernel(inline="always")
def _track_axis(state: np.ndarray, i: int, v: float, t_valid: float, timeout: float) -> None:
    if not math.isfinite(v):
        return
    gap = t_valid - state[AID_VT + i]
    if gap <= 0.0:  # not newer than what we have: a repeat or reordered
        return
    state[AID_A + i] = (v - state[AID_V + i]) / gap if gap <= timeout else 0.0
    state[AID_V + i] = v
    state[AID_VT + i] = t_valid


@kernel(inline="always")
def track_velocity(state: np.ndarray, common: np.ndarray, vx: float, vy: float,
                   vz: float, v_age: float) -> None:
    """Differentiate velocity measurements (internal frame) into a linear acceleration.

    Each axis on its own (GPS_RAW_INT has no vertical speed): the difference of two
    measurements no further apart than the aiding timeout, divided by their time apart;
    after a longer gap the acceleration is unknown (0) rather than averaged over the gap.
    """
    t_valid = state[RUN_T] - v_age
    timeout = common[P_AID_TIMEOUT]
    _track_axis(state, 0, vx, t_valid, timeout)
    _track_axis(state, 1, vy, t_valid, timeout)
    _track_axis(state, 2, vz, t_valid, timeout)


@kernel(inline="always")
def _aid_axis(state: np.ndarray, i: int, timeout: float) -> float:
    return state[AID_A + i] if state[RUN_T] - state[AID_VT + i] <= timeout else 0.0


@kernel(inline="always")
def remove_linear_acceleration(state: np.ndarray, common: np.ndarray, ax: float, ay: float,
                               az: float) -> tuple:
    """``f − R(q)ᵀ·a_lin``: what gravity alone makes the accelerometer read, given the
    linear acceleration from the velocity measurements. Axes not measured within the
    aiding timeout contribute nothing."""
    timeout = common[P_AID_TIMEOUT]
    lx = _aid_axis(state, 0, timeout)
    ly = _aid_axis(state, 1, timeout)
    lz = _aid_axis(state, 2, timeout)
    if lx == 0.0 and ly == 0.0 and lz == 0.0:
        return ax, ay, az
    bx, by, bz = world_to_body(state, lx, ly, lz)
    return ax - bx, ay - by, az - bz


_VEC = types.float64[::1]
# update_one's only signatures (see prepare_update): anything else (lists, other
# dtypes, strided views) raises TypeError; Estimator.update then converts and retries.
_UPDATE_SIGNATURES = [
    types.int64(_VEC, _VEC, _VEC, types.none, types.float64, _VEC, types.float64),
    types.int64(_VEC, _VEC, _VEC, _VEC, types.float64, _VEC, types.float64)]


def make_workspace(state_size: int, params: np.ndarray, common: np.ndarray) -> np.ndarray:
    """A zeroed workspace for update_one with ``params`` and ``common`` filled in."""
    s_end = W_HEADER + state_size
    p_end = s_end + params.shape[0]
    c_end = p_end + common.shape[0]
    n_end = c_end + N_COUNTERS
    ws = np.zeros(n_end + W_OUT)
    ws[W_STATE_END], ws[W_PARAMS_END], ws[W_COMMON_END], ws[W_COUNTERS_END] = (
        s_end, p_end, c_end, n_end)
    ws[s_end:p_end] = params
    ws[p_end:c_end] = common
    return ws


def workspace_views(ws: np.ndarray) -> tuple:
    """(state, params, common, counters, out): views sharing the workspace's memory."""
    s_end, p_end, c_end, n_end = (int(ws[i]) for i in (W_STATE_END, W_PARAMS_END,
                                                        W_COMMON_END, W_COUNTERS_END))
    return (ws[W_HEADER:s_end], ws[s_end:p_end], ws[p_end:c_end], ws[c_end:n_end],
            ws[n_end:n_end + W_OUT])


@kernel
def turn_forward(out: np.ndarray, gyr: np.ndarray, state: np.ndarray, delay: float) -> None:
    """out ← out ⊗ exp((ω − b)·delay), in place: one output carried forward by the
    sender's filter delay at the sample's bias-corrected rate (``Estimator.update``'s
    per-sample path; ``base.turned_forward`` is the same for arrays). A rate that is not
    finite leaves it unchanged."""
    wx, wy, wz = gyr[0] - state[B0], gyr[1] - state[B0 + 1], gyr[2] - state[B0 + 2]
    if finite3(wx, wy, wz):
        integrate_exact(out, wx, wy, wz, delay)


@kernel(inline="always")
def write_output_row(state: np.ndarray, common: np.ndarray, Q: np.ndarray, i: int) -> None:
    """Q[i] ← write_output, without a row view (whose reference counting costs more
    than the arithmetic in a batch loop)."""
    Q[i, 0], Q[i, 1], Q[i, 2], Q[i, 3] = rotate_output(state, common)


def make_kernels(step, takes_velocity: bool = False):
    """Build the compiled single-sample and batch drivers around an estimator's step.

    ``step(state, params, gx, gy, gz, ax, ay, az, mx, my, mz, acc_ok, mag_ok, dt)``
    takes scalars: array views would cost a reference-count round trip per sample. With
    ``takes_velocity`` it also takes ``vx, vy, vz, v_age`` (internal frame, NaN when no
    measurement) and the driver leaves the accelerometer as it is; otherwise the driver
    removes the linear acceleration derived from the velocities (see module docstring).

    The step is inlined into the drivers (numba IR inlining): a call passing two arrays
    and twelve scalars per sample cost more than most filters' arithmetic. The drivers
    are cached on disk keyed by the step's source file (see _StepKeyedCache).
    """
    process = _make_process(step, takes_velocity)
    return _make_drivers(process, step, takes_velocity)


def _make_process(step, takes_velocity: bool):
    """The per-sample driver around ``step`` (inlined into the batch drivers)."""
    step = njit(inline="always")(getattr(step, "py_func", step))

    @njit(inline="always")
    def process(state, params, common, gx, gy, gz, ax, ay, az, mx, my, mz, has_mag, dt,
                counters, ux, uy, uz, v_age) -> int:
        """One sample with the common checks; returns the F_* flags of this sample."""
        counters[C_SAMPLES] += 1
        initialised = F_INITIALISED if state[INIT] > 0.0 else 0
        grange = common[P_GYR_RANGE]
        corrupt = GYR_CORRUPT_FACTOR * grange
        if not finite3(gx, gy, gz) or abs(gx) > corrupt or abs(gy) > corrupt \
                or abs(gz) > corrupt:
            counters[C_SKIPPED] += 1
            return F_SKIPPED | initialised
        if not (dt > 0.0 and dt <= common[P_MAX_DT]):
            counters[C_SKIPPED] += 1
            counters[C_BAD_DT] += 1
            return F_SKIPPED | initialised
        state[RUN_T] += dt
        vx, vy, vz = user_to_internal(common, ux, uy, uz)
        if not (v_age >= 0.0 and v_age <= common[P_AID_TIMEOUT]):
            vx, vy, vz = math.nan, math.nan, math.nan  # too old (or no age): no aiding
        flags = 0
        acc_ok = acc_usable(ax, ay, az, common[P_ACC_RANGE])
        if not acc_ok:
            counters[C_ACC_UNUSABLE] += 1
            flags |= F_ACC_UNUSABLE
        mag_ok = False
        if has_mag:
            mag_ok = mag_usable(mx, my, mz)
            if not mag_ok:
                counters[C_MAG_UNUSABLE] += 1
        glim = _SAT_FRACTION * grange
        if abs(gx) >= glim or abs(gy) >= glim or abs(gz) >= glim:
            counters[C_GYR_SATURATED] += 1
            gx = min(max(gx, -grange), grange)
            gy = min(max(gy, -grange), grange)
            gz = min(max(gz, -grange), grange)
        if not takes_velocity:
            track_velocity(state, common, vx, vy, vz, v_age)
        if not initialised:
            if not acc_ok:
                return flags  # nothing to anchor the attitude to yet
            init_from_acc_mag(state, ax, ay, az, mx, my, mz, mag_ok)
            state[INIT] = 1.0
            return flags | F_INITIALISED
        if takes_velocity:
            step(state, params, gx, gy, gz, ax, ay, az, mx, my, mz, acc_ok, mag_ok, dt,
                 vx, vy, vz, v_age)
        else:
            if acc_ok:
                ax, ay, az = remove_linear_acceleration(state, common, ax, ay, az)
            step(state, params, gx, gy, gz, ax, ay, az, mx, my, mz, acc_ok, mag_ok, dt)
        if state[ACC_REJ] > 0.0:
            counters[C_ACC_REJECTED] += 1
            flags |= F_ACC_REJECTED
        if state[MAG_REJ] > 0.0:
            counters[C_MAG_REJECTED] += 1
            flags |= F_MAG_REJECTED
        if state[AIR_MODEL] > 0.0:
            flags |= F_AIR_MODEL
        return flags | F_INITIALISED

    return process


def _make_batch_loop(process, tap_at: int = 0, tap_size: int = 0):
    """The batch loop around ``process``: row ``i`` of Q, B and F per sample; a one-row
    ``dts``, ``M`` (no magnetometer), ``V`` (no velocity) or ``V_AGE`` holds for every
    sample. With ``tap_size`` (see make_tapped_driver) it also copies out the tap block;
    without, that code is not compiled (``tap_size`` is a compile-time constant).

    One loop for both drivers, not a per-sample body inlined into two loops: the arrays
    handed to an inlined function are reference-counted at every sample, which slowed
    the cheap filters' batches measurably (mahony's most)."""

    @njit
    def batch_loop(state, params, common, G, A, M, has_mag, dts, counters,
                   Q, B, F, V, V_AGE, TAP, AT, n, offset) -> int:
        single_dt = dts.shape[0] == 1
        has_vel = V.shape[0] == G.shape[0]
        single_age = V_AGE.shape[0] == 1
        for i in range(G.shape[0]):
            dt = dts[0] if single_dt else dts[i]
            j = i if has_mag else 0
            k = i if has_vel else 0
            age = V_AGE[0] if single_age else V_AGE[i]
            F[i] = process(state, params, common, G[i, 0], G[i, 1], G[i, 2],
                           A[i, 0], A[i, 1], A[i, 2], M[j, 0], M[j, 1], M[j, 2],
                           has_mag, dt, counters, V[k, 0], V[k, 1], V[k, 2], age)
            write_output_row(state, common, Q, i)
            B[i, 0], B[i, 1], B[i, 2] = state[B0], state[B0 + 1], state[B0 + 2]
            if tap_size > 0 and state[tap_at] > 0.0:
                if n < TAP.shape[0]:
                    for c in range(tap_size):
                        TAP[n, c] = state[tap_at + c]
                    AT[n] = offset + i
                n += 1
                state[tap_at] = 0.0
                state[tap_at + 1] = 0.0
        return n

    return batch_loop


def _make_drivers(process, step, takes_velocity: bool):
    """(update_one, run_batch) around one estimator's ``process``."""

    def update_one(ws, g, a, m, dt, v, v_age) -> int:
        """One sample on a workspace (see make_workspace); -1 if a vector is not (3,)."""
        if g.shape[0] != 3 or a.shape[0] != 3 or v.shape[0] != 3:
            return -1
        s_end, p_end = int(ws[W_STATE_END]), int(ws[W_PARAMS_END])
        c_end, n_end = int(ws[W_COMMON_END]), int(ws[W_COUNTERS_END])
        state, params, common = ws[W_HEADER:s_end], ws[s_end:p_end], ws[p_end:c_end]
        counters = ws[c_end:n_end]
        if m is None:
            flags = process(state, params, common, g[0], g[1], g[2], a[0], a[1], a[2],
                            0.0, 0.0, 0.0, False, dt, counters, v[0], v[1], v[2], v_age)
        else:
            if m.shape[0] != 3:
                return -1
            flags = process(state, params, common, g[0], g[1], g[2], a[0], a[1], a[2],
                            m[0], m[1], m[2], True, dt, counters, v[0], v[1], v[2], v_age)
        write_output(state, common, ws[n_end:n_end + W_OUT])
        return flags

    batch_loop = _make_batch_loop(process)

    def run_batch(state, params, common, G, A, M, has_mag, dts, counters,
                  Q, B, F, V, V_AGE) -> None:
        batch_loop(state, params, common, G, A, M, has_mag, dts, counters,
                   Q, B, F, V, V_AGE, np.empty((0, 0)), np.empty(0, np.int64), 0, 0)

    variant = f"takes_velocity={takes_velocity}"
    return (_cached_njit(update_one, step, variant), _cached_njit(run_batch, step, variant))


def make_tapped_driver(step, tap_at: int, tap_size: int):
    """run_batch that also copies out a block of the state the step writes at chosen
    moments (an offline pass over the recording needs what the online filter knew then,
    e.g. a Kalman filter's prior and posterior for a smoother).

    ``state[tap_at:tap_at + tap_size]`` is the block; its first element is set by the
    step when the block is fresh and the second may flag a break (both cleared here
    after each copy). ``run_tapped(..., TAP, AT, n)`` copies block k into ``TAP[n + k]``
    and the sample index into ``AT[n + k]`` and returns the new count, which goes past
    ``TAP.shape[0]`` (without copying) when TAP is too small.
    """
    run_tapped = _make_batch_loop(_make_process(step, True), tap_at, tap_size)
    return _cached_njit(run_tapped.py_func, step, f"tapped={tap_at},{tap_size}")


class _StepKeyedCache(FunctionCache):
    """Disk cache for a driver built around one estimator's step.

    numba keys a closure's cache entry on its pickled closure cells; a dispatcher
    pickles with a random per-process id, so the default key never matched and every
    process recompiled every estimator's drivers. This key uses the driver's bytecode
    plus the step's qualified name and the text of the file defining it instead (an
    edit there recompiles), and the package digest (see :func:`_package_digest`).
    """

    def __init__(self, py_func, step, variant: str = "") -> None:
        super().__init__(py_func)
        fn = getattr(step, "py_func", step)
        try:
            source = Path(inspect.getsourcefile(fn) or "").read_bytes()
        except (OSError, TypeError):
            source = fn.__code__.co_code
        self._step_digest = hashlib.sha256(
            fn.__module__.encode() + fn.__qualname__.encode() + variant.encode()
            + source).hexdigest()

    def _index_key(self, sig, codegen):
        code = hashlib.sha256(self._py_func.__code__.co_code).hexdigest()
        return (sig, codegen.magic_tuple(), (code, self._step_digest), PACKAGE_DIGEST)


def _cached_njit(fn, step, variant: str = ""):
    """njit(fn) with the step-keyed disk cache (compiled lazily); ``variant`` names
    closure settings that change the compiled code without changing any source."""
    dispatcher = njit(fn)
    dispatcher._cache = _StepKeyedCache(dispatcher.py_func, step, variant)
    return dispatcher


def prepare_update(update_one) -> None:
    """Compile ``update_one`` for its two signatures (6D, 9D) and freeze it, so any other
    argument types raise TypeError at the call instead of compiling a specialisation.
    Called when an estimator is created: importing stays cheap, and an estimator
    nobody uses is never compiled."""
    if len(update_one.signatures) < len(_UPDATE_SIGNATURES):
        for sig in _UPDATE_SIGNATURES:
            update_one.compile(sig)
        update_one.disable_compile()
    if not turn_forward.signatures:  # (imu_delay's per-sample path, shared by all)
        turn_forward.compile(types.none(_VEC, _VEC, _VEC, types.float64))
