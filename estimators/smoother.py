"""The best attitude a whole recording allows: the eskf run forward, then smoothed back.

    from estimators import smooth
    res = smooth("eskf", gyr, acc, mag, rate_hz=400.0, world="NED", vel=v, airborne=a)
    res.q          # smoothed (N, 4), same frames and conventions as the online filter
    res.online     # the online eskf of the same run

An online filter answers "what is the attitude now, from what came so far"; after a
flight the question is "what was it", and every sample after a moment says something
about it too: the heading the magnetometer settles on a minute later, the gyro bias
measured at the next rest, the velocity that shows where the tilt was wrong. A
Rauch-Tung-Striebel smoother uses all of it, for the same model and noise as the online
filter (nothing here is tuned on its own).

Forward: the online eskf itself (the same compiled step, so bias, velocity, rotor drag,
aiding and the flight state behave exactly as online), through a driver that copies out
each Kalman step's predicted and updated state and covariance (the "tap",
``estimators.eskf.TAP_*``). Memory: one tap row (237 floats) per Kalman step (100 per
second), linear in the recording.

Backward, on the error state δx = [δθ (world), δb, δv, δλ = δ ln μ]: with the step-k posterior
x̂ₖ⁺, Pₖ⁺, the step-(k+1) prediction x̂ₖ₊₁⁻, Pₖ₊₁⁻ and its transition Fₖ (rebuilt from the
tap: δθ ← δθ − R·T·δb, δv ← δv − [ΔV]×·δθ),

    eₖ₊₁ = x̂ˢₖ₊₁ ⊖ x̂ₖ₊₁⁻              (the smoothed state, against the prediction)
    Cₖ = Pₖ⁺·Fₖᵀ·(Pₖ₊₁⁻)⁻¹,  δˢₖ = Cₖ·eₖ₊₁,  x̂ˢₖ = x̂ₖ⁺ ⊕ δˢₖ

(⊕ on the attitude: exp(δθ) ⊗ q, a world-frame rotation as in the filter). Where the
filter re-anchored a state outside its Kalman update (a velocity re-anchored after a
knock, a heading reset after a gyro-bias step; ``TAP_BREAK``) the step before starts the
backward pass afresh: the reset says the filter's past was wrong in a way its model
does not describe. Between Kalman steps each sample gets the correction interpolated in
time between δˢₖ and eₖ₊₁. Samples before the first Kalman step (initialising) and after
the last one are the online ones.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from . import _core, eskf
from ._core import quat_exp, quat_multiply
from .base import BatchResult, SampleCounters, turned_forward

_NX = 10
_N = eskf.TAP_NOMINAL
_PRI, _POST, _BREAK = eskf.TAP_PRIOR, eskf.TAP_POST, eskf.TAP_BREAK
_T, _R, _DV = eskf.TAP_T, eskf.TAP_R, eskf.TAP_DV


@dataclass(frozen=True)
class SmoothResult:
    """Smoothed and online attitude of one recording."""

    q: np.ndarray  # (N, 4) smoothed, in the estimator's output frame
    bias: np.ndarray  # (N, 3) smoothed gyro bias [rad/s]
    online: BatchResult  # the forward (online) pass
    counters: SampleCounters  # the forward pass's sample counts
    steps: int  # Kalman steps smoothed
    breaks: int  # steps where the filter re-anchored a state (no smoothing across)


_tapped = None


def _tapped_driver():
    """The eskf's tapped batch driver (compiled on first use, cached on disk)."""
    global _tapped
    if _tapped is None:
        _tapped = _core.make_tapped_driver(eskf._step, eskf.TAP, eskf.TAP_SIZE)
    return _tapped


def smooth(name: str, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None = None,
           rate_hz: float = 1000.0, world: str = "NED", q0: np.ndarray | None = None,
           dt: float | np.ndarray | None = None, *, vel: np.ndarray | None = None,
           vel_age: float | np.ndarray | None = None, airborne: np.ndarray | None = None,
           **params: float) -> SmoothResult:
    """Smooth a recording with estimator ``name`` (the arguments of ``estimators.run``).

    Only ``eskf`` has a smoother: the others carry no covariance to smooth with."""
    if name != "eskf":
        raise ValueError(f"no smoother for {name!r}: only 'eskf' (a Kalman filter) has one")
    from . import create

    G = np.ascontiguousarray(gyr, dtype=np.float64)
    A = np.ascontiguousarray(acc, dtype=np.float64)
    n = G.shape[0]
    if G.ndim != 2 or G.shape[1] != 3 or A.shape != G.shape:
        raise ValueError(f"gyr and acc must both be (N, 3), got {G.shape} and {A.shape}")
    M = np.zeros((1, 3)) if mag is None else np.ascontiguousarray(mag, dtype=np.float64)
    if mag is not None and M.shape != G.shape:
        raise ValueError(f"mag must be (N, 3) like gyr, got {M.shape}")
    V = np.full((1, 3), np.nan) if vel is None else np.ascontiguousarray(vel, dtype=np.float64)
    if vel is not None and V.shape != G.shape:
        raise ValueError(f"vel must be (N, 3) like gyr, got {V.shape}")
    est = create(name, rate_hz=rate_hz, world=world, q0=q0, **params)
    dts = est._per_sample("dt", 1.0 / rate_hz if dt is None else dt, n)
    ages = est._per_sample("vel_age", 0.0 if vel_age is None else vel_age, n)
    code = np.full(n, 2, dtype=np.int8)
    if airborne is not None:
        air = np.asarray(airborne, dtype=np.float64)
        if air.shape != (n,):
            raise ValueError(f"airborne must have shape ({n},), got {air.shape}")
        code = np.where(np.isnan(air), 2, air != 0.0).astype(np.int8)
    cuts = [0, *(np.flatnonzero(np.diff(code)) + 1).tolist(), n] if n else [0]
    total_s = float(np.sum(dts) if dts.shape[0] == n else dts[0] * n)
    capacity = min(n, int(total_s / est.params.update_period * 1.02) + 16)
    while True:
        q, b, f = np.empty((n, 4)), np.empty((n, 3)), np.zeros(n, dtype=np.uint8)
        tap = np.empty((capacity, eskf.TAP_SIZE))
        at = np.empty(capacity, dtype=np.int64)
        k = _forward(est, cuts, code, G, A, M, mag is not None, dts, V, ages, q, b, f, tap, at)
        if k <= capacity:
            break
        capacity = k  # more Kalman steps than the time says (uneven steps): once more
        est = create(name, rate_hz=rate_hz, world=world, q0=q0, **params)
    if n:
        est._last_flags = int(f[-1])
    delay = est.params.imu_delay  # both outputs are carried forward like Estimator.run's
    online = BatchResult(q=turned_forward(q, G, b, delay), bias=b, flags=f)
    tap, at = tap[:k], at[:k]
    if k < 2:
        return SmoothResult(q=online.q.copy(), bias=b.copy(), online=online,
                            counters=est.counters, steps=k, breaks=0)
    d, e = _backward(tap)
    t = np.cumsum(dts) if dts.shape[0] == n else dts[0] * np.arange(1, n + 1)
    w = est._common[_core.P_OUT:_core.P_OUT + 4].copy()
    qs, bs = _apply(q, b, at, d, e, t, w)
    return SmoothResult(q=turned_forward(qs, G, bs, delay), bias=bs, online=online,
                        counters=est.counters, steps=k,
                        breaks=int((tap[:, eskf.TAP_BREAK] > 0.0).sum()))


def _forward(est, cuts: list[int], code: np.ndarray, G: np.ndarray, A: np.ndarray,
             M: np.ndarray, has_mag: bool, dts: np.ndarray, V: np.ndarray, ages: np.ndarray,
             q: np.ndarray, b: np.ndarray, f: np.ndarray, tap: np.ndarray,
             at: np.ndarray) -> int:
    """The online eskf over pieces of constant flight state (as ``Estimator.run``), the
    tap copied out; returns the number of Kalman steps."""
    n_all = G.shape[0]

    def piece(x: np.ndarray, a: int, z: int) -> np.ndarray:
        return x[a:z] if x.shape[0] == n_all else x

    driver = _tapped_driver()
    k = 0
    for a, z in itertools.pairwise(cuts):
        if z <= a:
            continue
        est.set_flight_state(None if code[a] == 2 else bool(code[a]))
        k = driver(est._state, est._params_vec, est._common, G[a:z], A[a:z], piece(M, a, z),
                   has_mag, piece(dts, a, z), est._counters, q[a:z], b[a:z], f[a:z],
                   piece(V, a, z), piece(ages, a, z), tap, at, k, a)
    return k


@njit(cache=True)
def _backward(tap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RTS over the tap rows: (δˢ against each posterior, e against each prediction)."""
    K = tap.shape[0]
    pri, post = _PRI, _POST
    d = np.zeros((K, _NX))
    e = np.zeros((K, _NX))
    F = np.eye(_NX)
    for k in range(K - 2, -1, -1):
        j = k + 1
        # e_j = (x̂_j⁺ ⊕ δˢ_j) ⊖ x̂_j⁻
        qs = quat_exp(d[j, 0], d[j, 1], d[j, 2])
        qs = quat_multiply(qs[0], qs[1], qs[2], qs[3], tap[j, post], tap[j, post + 1],
                           tap[j, post + 2], tap[j, post + 3])
        dq = quat_multiply(qs[0], qs[1], qs[2], qs[3], tap[j, pri], -tap[j, pri + 1],
                           -tap[j, pri + 2], -tap[j, pri + 3])
        sgn = 1.0 if dq[0] >= 0.0 else -1.0
        vn = math.sqrt(dq[1] ** 2 + dq[2] ** 2 + dq[3] ** 2)
        scale = 2.0 * math.atan2(vn, sgn * dq[0]) / vn * sgn if vn > 1e-12 else 2.0 * sgn
        for c in range(3):
            e[j, c] = scale * dq[1 + c]
        for c in range(3, _NX - 1):  # b, v: plain differences (tap columns 4..9)
            e[j, c] = d[j, c] + tap[j, post + c + 1] - tap[j, pri + c + 1]
        # μ: the filter's error state is δ ln μ (0 while the drag model is off, μ = 0)
        mu_post, mu_pri = tap[j, post + _NX], tap[j, pri + _NX]
        log_ratio = math.log(mu_post / mu_pri) if mu_post > 0.0 and mu_pri > 0.0 else 0.0
        e[j, _NX - 1] = d[j, _NX - 1] + log_ratio
        if tap[j, _BREAK] > 0.0:
            continue  # d[k] stays 0: nothing carried across a re-anchoring
        T = tap[j, _T]
        r = tap[j, _R:_R + 9]
        dv = tap[j, _DV:_DV + 3]
        for a in range(3):
            for c in range(3):
                F[a, 3 + c] = -T * r[3 * a + c]
        F[6, 1], F[6, 2] = dv[2], -dv[1]  # −[ΔV]×
        F[7, 0], F[7, 2] = -dv[2], dv[0]
        F[8, 0], F[8, 1] = dv[1], -dv[0]
        p_post = tap[k, post + _N:post + _N + _NX * _NX].copy().reshape(_NX, _NX)
        p_prior = tap[j, pri + _N:pri + _N + _NX * _NX].copy().reshape(_NX, _NX)
        for c in range(_NX):  # a state the filter does not run (μ without the drag
            if p_prior[c, c] <= 0.0:  # model): its rows are zero, it gets no correction
                p_prior[c, c] = 1.0
        # Cₖᵀ = (Pₖ₊₁⁻)⁻¹·Fₖ·Pₖ⁺ (P symmetric)
        ct = np.linalg.solve(p_prior, F @ p_post)
        d[k] = ct.T @ e[j]
    return d, e


@njit(cache=True)
def _apply(q: np.ndarray, b: np.ndarray, at: np.ndarray, d: np.ndarray, e: np.ndarray,
           t: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each sample's correction, interpolated between Kalman steps, onto the online
    output (which is W ⊗ q inside: a world-frame error δθ is R(W)·δθ outside)."""
    K = at.shape[0]
    qs, bs = q.copy(), b.copy()
    w0, w1, w2, w3 = w[0], w[1], w[2], w[3]
    rw = np.array([[1 - 2 * (w2 * w2 + w3 * w3), 2 * (w1 * w2 - w0 * w3),
                    2 * (w1 * w3 + w0 * w2)],
                   [2 * (w1 * w2 + w0 * w3), 1 - 2 * (w1 * w1 + w3 * w3),
                    2 * (w2 * w3 - w0 * w1)],
                   [2 * (w1 * w3 - w0 * w2), 2 * (w2 * w3 + w0 * w1),
                    1 - 2 * (w1 * w1 + w2 * w2)]])
    for k in range(K - 1):
        i0, i1 = at[k], at[k + 1]
        span = t[i1] - t[i0]
        for i in range(i0, i1):
            alpha = (t[i] - t[i0]) / span if span > 0.0 else 0.0
            x = (1.0 - alpha) * d[k, 0] + alpha * e[k + 1, 0]
            y = (1.0 - alpha) * d[k, 1] + alpha * e[k + 1, 1]
            z = (1.0 - alpha) * d[k, 2] + alpha * e[k + 1, 2]
            ux = rw[0, 0] * x + rw[0, 1] * y + rw[0, 2] * z
            uy = rw[1, 0] * x + rw[1, 1] * y + rw[1, 2] * z
            uz = rw[2, 0] * x + rw[2, 1] * y + rw[2, 2] * z
            if not (math.isfinite(q[i, 0]) and math.isfinite(ux + uy + uz)):
                continue
            c = quat_exp(ux, uy, uz)
            r = quat_multiply(c[0], c[1], c[2], c[3], q[i, 0], q[i, 1], q[i, 2], q[i, 3])
            norm = math.sqrt(r[0] ** 2 + r[1] ** 2 + r[2] ** 2 + r[3] ** 2)
            for m in range(4):
                qs[i, m] = r[m] / norm
            for m in range(3):
                bs[i, m] = b[i, m] + (1.0 - alpha) * d[k, 3 + m] + alpha * e[k + 1, 3 + m]
    return qs, bs
