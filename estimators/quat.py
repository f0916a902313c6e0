"""Quaternion algebra and attitude conversions (numpy, vectorised).

Conventions (SPEC): Hamilton product, scalar first ``[w, x, y, z]``, and a quaternion
``q`` rotates *body* vectors into the *world* frame: ``v_world = q ⊗ v_body ⊗ q*``.
Euler angles are aerospace Z-Y-X: ``R = Rz(yaw) · Ry(pitch) · Rx(roll)``.

Every function accepts a single quaternion ``(4,)`` or a stack ``(N, 4)`` and returns
the same leading shape, so the same code serves per-sample and offline work.
"""

from __future__ import annotations

import math

import numpy as np

from ._core import kernel

# Below this |cos(pitch)| the yaw/roll split is undefined (gimbal lock); see to_euler.
GIMBAL_LOCK_COS = 1e-6

_SQRT_HALF = float(np.sqrt(0.5))
#: NED <-> ENU world swap (x<->y, z flipped). A proper rotation, its own inverse.
Q_NED_ENU = np.array([0.0, _SQRT_HALF, _SQRT_HALF, 0.0])
#: FRD <-> RFU body swap (the seeds' X-right/Y-forward/Z-up board). Same matrix as above.
Q_FRD_RFU = Q_NED_ENU


def identity(n: int | None = None) -> np.ndarray:
    """The identity quaternion, or ``n`` of them."""
    if n is None:
        return np.array([1.0, 0.0, 0.0, 0.0])
    q = np.zeros((n, 4))
    q[:, 0] = 1.0
    return q


def multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p ⊗ q`` (broadcasts over leading dimensions)."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def conjugate(q: np.ndarray) -> np.ndarray:
    """``q*``: the inverse rotation for a unit quaternion."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def normalize(q: np.ndarray) -> np.ndarray:
    """Unit-norm copy of ``q``."""
    q = np.asarray(q, dtype=float)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def canonical(q: np.ndarray) -> np.ndarray:
    """Sign-fixed copy with ``w >= 0`` (q and -q are the same rotation)."""
    q = np.asarray(q, dtype=float)
    return np.where(q[..., :1] < 0.0, -q, q)


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate body vector(s) ``v`` into the world frame: ``q ⊗ v ⊗ q*``."""
    return np.einsum("...ij,...j->...i", to_dcm(q), np.asarray(v, dtype=float))


def to_dcm(q: np.ndarray) -> np.ndarray:
    """Rotation matrix ``R`` with ``v_world = R @ v_body`` (the seeds' R_b^n)."""
    q = normalize(q)
    w, x, y, z = np.moveaxis(q, -1, 0)
    r = np.empty((*q.shape[:-1], 3, 3))
    r[..., 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    r[..., 0, 1] = 2.0 * (x * y - w * z)
    r[..., 0, 2] = 2.0 * (x * z + w * y)
    r[..., 1, 0] = 2.0 * (x * y + w * z)
    r[..., 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    r[..., 1, 2] = 2.0 * (y * z - w * x)
    r[..., 2, 0] = 2.0 * (x * z - w * y)
    r[..., 2, 1] = 2.0 * (y * z + w * x)
    r[..., 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return r


def from_dcm(r: np.ndarray) -> np.ndarray:
    """Quaternion of a rotation matrix (Shepperd's method: stable for every angle)."""
    r = np.asarray(r, dtype=float)
    lead = r.shape[:-2]
    r = r.reshape(-1, 3, 3)
    tr = np.trace(r, axis1=1, axis2=2)
    diag = np.stack([tr, r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], axis=1)
    pick = np.argmax(diag, axis=1)
    q = np.empty((r.shape[0], 4))
    for i in range(r.shape[0]):
        m = r[i]
        k = pick[i]
        if k == 0:
            s = 2.0 * np.sqrt(1.0 + tr[i])
            q[i] = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s,
                    (m[1, 0] - m[0, 1]) / s]
        elif k == 1:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q[i] = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s,
                    (m[0, 2] + m[2, 0]) / s]
        elif k == 2:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            q[i] = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s,
                    (m[1, 2] + m[2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            q[i] = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s,
                    (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    return canonical(normalize(q)).reshape(*lead, 4)


def to_euler(q: np.ndarray) -> np.ndarray:
    """Z-Y-X Euler angles ``[roll, pitch, yaw]`` in radians, yaw in (-pi, pi].

    Gimbal-lock safe: when ``|cos(pitch)| < GIMBAL_LOCK_COS`` only ``yaw ∓ roll`` is
    observable, so roll is set to 0 and the whole heading goes into yaw, instead of
    dividing two vanishing numbers.

    The package's one Euler conversion (replay, the bridge's ATTITUDE, MQTT and table,
    the emulator). Compiled rather than numpy: on the bridge's per-sample output path
    one quaternion costs about 1 µs instead of numpy's ~25 µs of per-call overhead.
    """
    q = np.asarray(q, dtype=float)
    rows = np.ascontiguousarray(q.reshape(-1, 4))
    out = np.empty((rows.shape[0], 3))
    _euler_rows(rows, out)
    return out.reshape((*q.shape[:-1], 3))


@kernel(error_model="numpy")  # a zero or NaN quaternion gives NaN angles, not an exception
def _euler_rows(q: np.ndarray, out: np.ndarray) -> None:
    """:func:`to_euler` of each row of ``q`` (N, 4) into ``out`` (N, 3), from the
    elements of the rotation matrix (see :func:`to_dcm`)."""
    for i in range(q.shape[0]):
        w, x, y, z = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
        scale = 1.0 / math.sqrt(w * w + x * x + y * y + z * z)
        w, x, y, z = w * scale, x * scale, y * scale, z * scale
        r00 = 1.0 - 2.0 * (y * y + z * z)
        r10 = 2.0 * (x * y + w * z)
        sin_pitch = 2.0 * (w * y - x * z)  # -r20
        if sin_pitch > 1.0:  # rounding; a NaN passes through
            sin_pitch = 1.0
        elif sin_pitch < -1.0:
            sin_pitch = -1.0
        if math.hypot(r00, r10) < GIMBAL_LOCK_COS:  # |cos(pitch)|
            roll = 0.0
            yaw = math.atan2(2.0 * (w * z - x * y), 1.0 - 2.0 * (x * x + z * z))  # -r01, r11
        else:
            roll = math.atan2(2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))  # r21, r22
            yaw = math.atan2(r10, r00)
        out[i, 0] = roll
        out[i, 1] = math.asin(sin_pitch)
        out[i, 2] = yaw + 2.0 * math.pi if yaw <= -math.pi else yaw


def from_euler(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Quaternion of Z-Y-X Euler angles (radians): ``qz(yaw) ⊗ qy(pitch) ⊗ qx(roll)``."""
    cr, sr = np.cos(np.asarray(roll) / 2.0), np.sin(np.asarray(roll) / 2.0)
    cp, sp = np.cos(np.asarray(pitch) / 2.0), np.sin(np.asarray(pitch) / 2.0)
    cy, sy = np.cos(np.asarray(yaw) / 2.0), np.sin(np.asarray(yaw) / 2.0)
    return np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )


def from_rotvec(v: np.ndarray) -> np.ndarray:
    """Quaternion of a rotation vector (axis · angle, radians); exact for any angle."""
    v = np.asarray(v, dtype=float)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(a/2)/a -> 1/2 as a -> 0; the series keeps full precision for tiny angles.
    small = angle < 1e-6
    k = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    return np.concatenate([np.cos(half), v * k], axis=-1)


def to_rotvec(q: np.ndarray) -> np.ndarray:
    """Rotation vector (axis · angle, angle in [0, pi]) of a quaternion."""
    q = canonical(normalize(q))
    vec = q[..., 1:]
    s = np.linalg.norm(vec, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    small = s < 1e-9
    k = np.where(small, 2.0 / np.maximum(q[..., :1], 1e-300), angle / np.where(small, 1.0, s))
    return vec * k


def bracket(t_src: np.ndarray, t: np.ndarray, max_gap: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each time in ``t``, into sorted ``t_src`` (2 samples at least): the index of
    the sample at or before it, the fraction (0..1) of the way to the next one, and
    whether it lies within ``t_src``'s span between two samples at most ``max_gap``
    apart or on a sample itself (elsewhere the other two are meaningless). On a sample
    nothing is interpolated, so a gap after it does not matter: a truth placed at the
    time of the IMU sample read before it is paired with that sample's estimate even
    when the stream pauses next."""
    i0 = np.clip(np.searchsorted(t_src, t, side="right") - 1, 0, len(t_src) - 2)
    t0, t1 = t_src[i0], t_src[i0 + 1]
    inside = (t >= t_src[0]) & (t <= t_src[-1]) & ((t1 - t0 <= max_gap) | (t == t0)
                                                   | (t == t1))
    frac = np.clip((t - t0) / np.maximum(t1 - t0, 1e-12), 0.0, 1.0)
    return i0, frac, inside


def slerp(q0: np.ndarray, q1: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """The attitude ``frac`` (0..1) of the way from ``q0`` to ``q1``, row by row:
    ``q0 ⊗ exp(frac · log(q0* ⊗ q1))``, the shortest rotation at a constant rate."""
    step = canonical(multiply(conjugate(q0), q1))
    return multiply(q0, from_rotvec(np.asarray(frac, dtype=float)[..., None] * to_rotvec(step)))


def from_axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Quaternion of a rotation by ``angle`` (radians) about ``axis`` (any length > 0)."""
    axis = np.asarray(axis, dtype=float)
    unit = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    return from_rotvec(unit * np.asarray(angle, dtype=float)[..., None])


def to_axis_angle(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(unit axis, angle)``; the axis is +x for the identity, where it is undefined."""
    v = to_rotvec(q)
    angle = np.linalg.norm(v, axis=-1)
    safe = np.where(angle[..., None] > 0.0, v / np.where(angle > 0, angle, 1.0)[..., None],
                    np.array([1.0, 0.0, 0.0]))
    return safe, angle


def angle_between(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Smallest rotation angle (radians) taking ``q`` to ``p``."""
    err = multiply(normalize(p), conjugate(normalize(q)))
    # atan2 keeps full precision near zero, where arccos(|w|) loses half the digits.
    return 2.0 * np.arctan2(np.linalg.norm(err[..., 1:], axis=-1), np.abs(err[..., 0]))


def ned_to_enu(q: np.ndarray) -> np.ndarray:
    """Re-express a body->NED attitude as body->ENU (same body frame)."""
    return multiply(Q_NED_ENU, q)


def enu_to_ned(q: np.ndarray) -> np.ndarray:
    """Re-express a body->ENU attitude as body->NED (same body frame)."""
    return multiply(Q_NED_ENU, q)


def rfu_to_frd_body(q: np.ndarray) -> np.ndarray:
    """Attitude of an RFU board (the seeds' X-right/Y-forward/Z-up) as the FRD body's."""
    return multiply(q, Q_FRD_RFU)


def frd_to_rfu_body(q: np.ndarray) -> np.ndarray:
    """Attitude of an FRD body as the RFU board's (inverse of ``rfu_to_frd_body``)."""
    return multiply(q, Q_FRD_RFU)


def rfu_to_frd_vector(v: np.ndarray) -> np.ndarray:
    """Sensor vector(s) from RFU board axes to FRD (also NED<->ENU for world vectors)."""
    v = np.asarray(v, dtype=float)
    return np.stack([v[..., 1], v[..., 0], -v[..., 2]], axis=-1)


frd_to_rfu_vector = rfu_to_frd_vector
enu_to_ned_vector = rfu_to_frd_vector
ned_to_enu_vector = rfu_to_frd_vector


def from_acc_mag(acc: np.ndarray, mag: np.ndarray | None = None,
                 world: str = "NED") -> np.ndarray:
    """Attitude from one accelerometer (specific force) and optional magnetometer sample.

    At rest the accelerometer measures +g *upward*, so ``-acc`` points down. Without a
    magnetometer the heading is chosen so that the body x axis points north (yaw 0).
    """
    acc = np.asarray(acc, dtype=float)
    down = -acc / np.linalg.norm(acc, axis=-1, keepdims=True)
    if mag is None:
        ref = np.broadcast_to(np.array([1.0, 0.0, 0.0]), down.shape)
        # If body x is (anti)parallel to down, use body y to define the heading.
        parallel = np.abs(np.sum(ref * down, axis=-1, keepdims=True)) > 0.999
        ref = np.where(parallel, np.array([0.0, 1.0, 0.0]), ref)
        east = np.cross(down, ref)
    else:
        east = np.cross(down, np.asarray(mag, dtype=float))
    east = east / np.linalg.norm(east, axis=-1, keepdims=True)
    north = np.cross(east, down)
    # Rows are the world axes expressed in the body frame: R_world<-body.
    r = np.stack([north, east, down], axis=-2)
    q = from_dcm(r)
    return ned_to_enu(q) if world_is_enu(world) else q


def world_is_enu(world: str) -> bool:
    """Validate a world-frame name and say whether it is ENU."""
    w = world.upper()
    if w not in ("NED", "ENU"):
        raise ValueError(f"world must be 'NED' or 'ENU', got {world!r}")
    return w == "ENU"
