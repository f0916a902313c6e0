"""Fitting a :class:`~imu.calibration.SensorCalibration` from recorded samples.

Four fits, numpy least squares only:

* **gyro offset** — the mean rate over the longest stretch where the board is still;
* **accelerometer** — with all six faces among the static poses (the PX4/ArduPilot
  procedure), offset and full matrix from ``M (a - b) = G e_i`` on the faces plus the
  norm condition on the other poses (:mod:`imu.calibration_faces`; faces assumed
  square on a level surface). Otherwise the poses' mean readings only lie on an
  ellipsoid: offset b and symmetric M with ``|M (a - b)| = G`` (Gauss-Newton on the norm
  residuals). Norms only see the symmetric part of the sensor's error matrix; the
  rotation left over is a misalignment of a few tenths of a degree for percent-level
  cross-axis errors, and the report says the full model was not possible;
* **magnetometer** — the Earth's field has one strength, so the readings of a board
  turned through all orientations lie on an ellipsoid (hard iron = its centre, soft
  iron = its shape): an algebraic quadric fit, then ``M = r · A^(1/2)`` with r the mean
  field strength, so corrected vectors keep the usual magnitude;
* **gyro matrix** — scale and cross-axis errors from the turns between the static
  poses, whose rotation the calibrated accelerometer and magnetometer know
  (:mod:`imu.calibration_gyro`, Tedaldi et al. 2014); fitted last, on the other fits.

Each fit refuses (ValueError saying why) data that cannot determine it — too few
static poses, poses or field directions covering too little of the sphere — because a
calibration fitted to such data is confidently wrong, which is worse than none.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from .boards import G
from .calibration import SensorCalibration
from .calibration_faces import FACE_MAX_RESIDUAL_DEG, face_labels, fit_faces
from .calibration_gyro import Turn, fit_gyro_matrix

# --- still detection --------------------------------------------------------------
BLOCK_S = 0.1  # samples are judged in blocks of this length
GYRO_STD_STILL = 0.02  # rad/s: per-axis std within a block; a hand-held board shakes more
ACCEL_STD_STILL = 0.25  # m/s^2: per-axis std within a block (noise is ~0.07)
ACCEL_STEP_STILL = 0.05  # m/s^2: largest change of the block mean between neighbours
GYRO_STEP_STILL = 0.005  # rad/s: same for the gyro (a slow steady turn is not still)
MIN_POSE_S = 0.5  # a static pose lasts at least this long
POSE_SEPARATION_DEG = 20.0  # two poses closer than this count as one orientation
MIN_POSES = 6  # offset + diagonal scale: 6 unknowns
MIN_POSES_FULL = 12  # offset + symmetric matrix: 9 unknowns, with some redundancy
MAX_JACOBIAN_CONDITION = 1e4  # beyond: the poses do not pin the parameters down

# --- magnetometer coverage ---------------------------------------------------------
MIN_MAG_SAMPLES = 50
#: Smallest eigenvalue of the mean outer product of the field's unit directions (from
#: the fitted centre): 1/3 for the whole sphere, 0 for a flat circle (yaw-only turns).
MIN_MAG_SPREAD = 0.08
#: Of the 26 cube directions (faces, edges, corners), how many must have a sample
#: within 45°: catches a cap on one side that the eigenvalue test would pass.
MIN_MAG_DIRECTIONS = 18
MAX_QUADRIC_CONDITION = 1e8

# --- unusable samples ----------------------------------------------------------------
#: Readings beyond these are no sensor's: the widest MEMS ranges are ±4000 °/s (70 rad/s)
#: and ±200 g, magnetometers read up to ±50 gauss. Such a reading is a wrong unit or a
#: corrupt value; it is unusable like a non-finite one (and its square would overflow).
SAMPLE_LIMITS = {"gyro": (100.0, "rad/s"), "accelerometer": (2000.0, "m/s^2"),
                 "magnetometer": (100.0, "gauss")}
#: Runs of unusable gyro/accelerometer samples up to this long are interpolated from
#: their neighbours. The fits assume evenly spaced samples (a turn is integrated at
#: 1/rate per sample), so dropping a sample would shorten the turn, while over a few
#: milliseconds a rate is all but linear. Longer runs stay NaN and end still stretches
#: and turns, as a gap between pooled logs does.
MAX_FILL_S = 0.02
#: At rest the accelerometer reads g; with MEMS offsets and scale errors of a few
#: percent a static pose is within these factors of it, or the data is not in m/s^2.
POSE_NORM_RANGE = (0.5, 1.5)


@dataclass(frozen=True)
class FitReport:
    """What a fit saw and achieved, for the user to judge the calibration."""

    gyro_still_s: float = 0.0
    gyro_turns: int = 0  # turns between poses the gyro matrix was fitted on (0: not)
    gyro_weakest_rotation_deg: float = float("nan")  # rotation about the least-turned axis
    gyro_turn_error_before_deg: float = float("nan")  # RMS direction error, identity M
    gyro_turn_error_after_deg: float = float("nan")  # ... with the fitted M
    accel_poses: int = 0
    accel_faces: int = 0  # of the six face-down poses, how many were held
    accel_model: str = ""  # "full", "symmetric" or "diagonal"
    accel_face_residual_deg: float = float("nan")  # largest, full model only
    accel_note: str = ""  # why not the full model
    accel_norm_std_before: float = float("nan")  # std of |a| over poses [m/s^2]
    accel_norm_std_after: float = float("nan")
    accel_norm_rms_error_before: float = float("nan")  # RMS of |a| - G [m/s^2]
    accel_norm_rms_error_after: float = float("nan")
    mag_samples: int = 0
    mag_spread: float = 0.0
    mag_norm_rel_std_before: float = float("nan")  # std(|m|) / mean(|m|)
    mag_norm_rel_std_after: float = float("nan")

    def lines(self) -> list[str]:
        out = []
        if self.gyro_still_s:
            out.append(f"gyro:  offset from {self.gyro_still_s:.1f} s still")
        if self.gyro_turns:
            out.append(f"gyro:  scale and cross-axis from {self.gyro_turns} turns between "
                       f"poses (least-turned axis {self.gyro_weakest_rotation_deg:.0f}°); "
                       f"turn error RMS {self.gyro_turn_error_before_deg:.3f}° -> "
                       f"{self.gyro_turn_error_after_deg:.3f}°")
        if self.accel_poses:
            out.append(f"accel: {self.accel_poses} static poses ({self.accel_faces} of 6 "
                       f"faces), {self.accel_model} model; "
                       f"gravity norm std {self.accel_norm_std_before:.4f} -> "
                       f"{self.accel_norm_std_after:.4f} m/s^2, RMS |a|-G "
                       f"{self.accel_norm_rms_error_before:.4f} -> "
                       f"{self.accel_norm_rms_error_after:.4f} m/s^2")
            if self.accel_model == "full":
                out.append("accel: full matrix assumes each face was square on a level "
                           f"surface; largest face residual {self.accel_face_residual_deg:.3f}°")
            elif self.accel_note:
                out.append(f"accel: no rotation correction ({self.accel_note})")
        if self.mag_samples:
            out.append(f"mag:   {self.mag_samples} readings, direction spread "
                       f"{self.mag_spread:.2f} (sphere 0.33); field norm relative std "
                       f"{self.mag_norm_rel_std_before:.4f} -> "
                       f"{self.mag_norm_rel_std_after:.4f}")
        return out


@dataclass(frozen=True)
class Repair:
    """What :func:`repair_samples` found in and did to one sensor's samples."""

    sensor: str
    non_finite: int = 0  # samples with a NaN or infinite component
    beyond: int = 0  # samples beyond SAMPLE_LIMITS
    filled: int = 0  # of those, interpolated from their neighbours

    @property
    def unusable(self) -> int:
        return self.non_finite + self.beyond

    @property
    def left_out(self) -> int:
        return self.unusable - self.filled

    def note(self) -> str:
        """One line for the user ('' when every sample was usable)."""
        if not self.unusable:
            return ""
        limit, unit = SAMPLE_LIMITS[self.sensor]
        kinds = [f"{self.non_finite} non-finite"] if self.non_finite else []
        kinds += [f"{self.beyond} beyond ±{limit:g} {unit}"] if self.beyond else []
        done = [f"{self.filled} interpolated from their neighbours"] if self.filled else []
        done += [f"{self.left_out} left out"] if self.left_out else []
        return (f"{self.sensor}: {self.unusable} samples unusable ({', '.join(kinds)}); "
                f"{', '.join(done)}")


def _fillable(bad: np.ndarray, max_run: int) -> np.ndarray:
    """The bad samples in runs of at most ``max_run`` with a good sample on each side."""
    fill = np.zeros_like(bad)
    for s, e in _runs(bad):
        if e - s <= max_run and s > 0 and e < len(bad):
            fill[s:e] = True
    return fill


def repair_samples(x: np.ndarray, sensor: str, rate_hz: float, fill: bool = True
                   ) -> tuple[np.ndarray, Repair]:
    """(samples with unusable ones set to NaN — short runs of them interpolated when
    ``fill`` — and what was done). ``sensor`` is a key of SAMPLE_LIMITS.

    ValueError when no sample at all is usable because of the limit: a wrong unit or
    column, which no fit should be left to discover.
    """
    v = np.array(x, dtype=float)
    limit, unit = SAMPLE_LIMITS[sensor]
    non_finite = ~np.all(np.isfinite(v), axis=1)
    with np.errstate(invalid="ignore"):
        beyond = ~non_finite & np.any(np.abs(v) > limit, axis=1)
    bad = non_finite | beyond
    if beyond.any() and bad.all():
        raise ValueError(f"{sensor}: every sample is unusable ({beyond.sum()} beyond "
                         f"±{limit:g} {unit}, up to {np.nanmax(np.abs(v[beyond])):.3g}): "
                         f"a wrong unit or column")
    v[bad] = np.nan
    filled = np.zeros_like(bad)
    if fill and bad.any() and not bad.all():
        filled = _fillable(bad, max(1, round(MAX_FILL_S * rate_hz)))
        good = np.flatnonzero(~bad)
        for k in range(3):
            v[filled, k] = np.interp(np.flatnonzero(filled), good, v[good, k])
    return v, Repair(sensor, int(non_finite.sum()), int(beyond.sum()), int(filled.sum()))


# --- still stretches and poses ----------------------------------------------------

def _blocks(x: np.ndarray, n: int) -> np.ndarray:
    m = len(x) // n
    return x[: m * n].reshape(m, n, 3)


def still_blocks(gyr: np.ndarray, acc: np.ndarray, rate_hz: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(still flag, mean gyro, mean accel) per block, and the block length in samples.

    A block is still when gyro and accelerometer barely vary within it and their means
    match both neighbours' (a slow steady rotation has a quiet gyro but a moving
    gravity direction).
    """
    n = max(2, round(BLOCK_S * rate_hz))
    g, a = _blocks(np.asarray(gyr, float), n), _blocks(np.asarray(acc, float), n)
    if len(g) < 3:
        return np.zeros(len(g), bool), g.mean(axis=1), a.mean(axis=1), n
    finite = np.all(np.isfinite(g), axis=(1, 2)) & np.all(np.isfinite(a), axis=(1, 2))
    with np.errstate(invalid="ignore"):
        g_mean, a_mean = g.mean(axis=1), a.mean(axis=1)
        quiet = ((g.std(axis=1).max(axis=1) < GYRO_STD_STILL)
                 & (a.std(axis=1).max(axis=1) < ACCEL_STD_STILL))
        a_step = np.abs(np.diff(a_mean, axis=0)).max(axis=1) < ACCEL_STEP_STILL
        g_step = np.abs(np.diff(g_mean, axis=0)).max(axis=1) < GYRO_STEP_STILL
    steady = a_step & g_step
    neighbours = np.zeros(len(g), bool)
    neighbours[1:-1] = steady[:-1] & steady[1:]
    return finite & quiet & neighbours, g_mean, a_mean, n


def _runs(flag: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of each run of True."""
    edges = np.diff(np.concatenate(([0], flag.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def static_poses(gyr: np.ndarray, acc: np.ndarray, rate_hz: float
                 ) -> tuple[np.ndarray, list[tuple[int, int]], int]:
    """(mean accelerometer per static pose (P, 3), block runs, block length)."""
    still, _, a_mean, n = still_blocks(gyr, acc, rate_hz)
    min_blocks = max(1, round(MIN_POSE_S / BLOCK_S))
    runs = [(s, e) for s, e in _runs(still) if e - s >= min_blocks]
    poses = np.array([a_mean[s:e].mean(axis=0) for s, e in runs]).reshape(-1, 3)
    return poses, runs, n


def distinct_directions(vectors: np.ndarray, separation_deg: float) -> int:
    """How many of the vectors point more than ``separation_deg`` from all earlier kept ones."""
    units = vectors / np.linalg.norm(vectors, axis=1, keepdims=True)
    kept: list[np.ndarray] = []
    cos_sep = np.cos(np.radians(separation_deg))
    for u in units:
        if all(float(u @ k) < cos_sep for k in kept):
            kept.append(u)
    return len(kept)


# --- gyro ---------------------------------------------------------------------------

def fit_gyro_offset(gyr: np.ndarray, acc: np.ndarray, rate_hz: float,
                    min_still_s: float = 1.0) -> tuple[np.ndarray, float]:
    """(offset [rad/s], seconds of stillness used): the mean rate over the longest
    still stretch, where the true rate is zero."""
    still, g_mean, _, n = still_blocks(gyr, acc, rate_hz)
    runs = _runs(still)
    if not runs:
        raise ValueError("gyro offset: no still stretch found (keep the board motionless "
                         f"for at least {min_still_s:g} s)")
    s, e = max(runs, key=lambda r: r[1] - r[0])
    seconds = (e - s) * n / rate_hz
    if seconds < min_still_s:
        raise ValueError(f"gyro offset: longest still stretch is {seconds:.2f} s, need "
                         f"{min_still_s:g} s")
    return g_mean[s:e].mean(axis=0), seconds


# --- accelerometer ----------------------------------------------------------------

def _sym(p: np.ndarray) -> np.ndarray:
    return np.array([[p[0], p[3], p[4]], [p[3], p[1], p[5]], [p[4], p[5], p[2]]])


def fit_norm_ellipsoid(points: np.ndarray, radius: float, symmetric: bool,
                       iterations: int = 50) -> tuple[np.ndarray, np.ndarray, float]:
    """(offset b, matrix M, Jacobian condition) minimising sum (|M (x - b)| - radius)^2.

    Gauss-Newton from the identity (sensor errors are small). Parameters: b, then the
    diagonal of M, then (symmetric model) its three off-diagonal entries.
    """
    x = np.asarray(points, float)
    b = np.zeros(3)
    m = np.eye(3)
    n_mat = 6 if symmetric else 3
    cond = np.inf
    for _ in range(iterations):
        d = x - b
        y = d @ m.T
        norm = np.linalg.norm(y, axis=1)
        u = y / norm[:, None]
        r = norm - radius
        jac = np.empty((len(x), 3 + n_mat))
        jac[:, 0:3] = -u @ m  # d|y|/db = -u^T M
        for k in range(3):  # diagonal M_kk
            jac[:, 3 + k] = u[:, k] * d[:, k]
        if symmetric:  # M_jk = M_kj
            for col, (j, k) in enumerate(((0, 1), (0, 2), (1, 2))):
                jac[:, 6 + col] = u[:, j] * d[:, k] + u[:, k] * d[:, j]
        scale = np.linalg.norm(jac, axis=0)
        scale[scale == 0.0] = 1.0
        sv = np.linalg.svd(jac / scale, compute_uv=False)
        cond = sv[0] / sv[-1] if sv[-1] > 0 else np.inf
        if not np.isfinite(cond) or cond > MAX_JACOBIAN_CONDITION:
            return b, m, cond
        step = np.linalg.lstsq(jac / scale, -r, rcond=None)[0] / scale
        b = b + step[0:3]
        diag = np.diag(m) + step[3:6]
        off = (m[0, 1], m[0, 2], m[1, 2])
        if symmetric:
            off = tuple(np.array(off) + step[6:9])
        m = _sym(np.array([*diag, *off]))
        if np.max(np.abs(step)) < 1e-12 * max(1.0, radius):
            break
    return b, m, cond


def check_pose_norms(poses: np.ndarray) -> None:
    """ValueError unless every static pose reads about g (POSE_NORM_RANGE): a pose at
    rest reading far from it means the wrong unit (g for m/s^2), the wrong board profile
    or a dead or clipped axis, and the fits would be fitted to nonsense."""
    if not len(poses):
        return
    norms = np.linalg.norm(poses, axis=1)
    lo, hi = (f * G for f in POSE_NORM_RANGE)
    off = int(np.sum((norms < lo) | (norms > hi)))
    if off:
        raise ValueError(f"accelerometer: {off} of {len(poses)} static poses read |a| "
                         f"outside {lo:.1f}..{hi:.1f} m/s^2 (median "
                         f"{np.median(norms):.3f} m/s^2), but at rest it is g = {G:.2f}: "
                         "is the log in m/s^2 (not g), and the board profile right?")


def fit_accelerometer(gyr: np.ndarray, acc: np.ndarray, rate_hz: float
                      ) -> tuple[np.ndarray, np.ndarray, dict]:
    """(offset, matrix, report fields) from the static poses in the samples.

    The full matrix (rotation included) when all six faces were held square and level;
    else the norm-only fit (symmetric with ≥ 12 distinct poses, diagonal with 6-11),
    with ``accel_note`` saying why.
    """
    poses, _, _ = static_poses(gyr, acc, rate_hz)
    check_pose_norms(poses)
    count = distinct_directions(poses, POSE_SEPARATION_DEG) if len(poses) else 0
    if count < MIN_POSES:
        raise ValueError(f"accelerometer: found {count} distinct static pose(s) (at least "
                         f"{POSE_SEPARATION_DEG:g}° apart, each held still "
                         f"{MIN_POSE_S:g} s), need {MIN_POSES}; hold the board still on "
                         "each face (and ideally on edges and corners) in turn")
    labels = face_labels(poses)
    faces = len(set(labels[labels >= 0].tolist()))
    model, note, worst = "", "", float("nan")
    if faces == 6:
        b, m, worst, cond = fit_faces(poses, labels, G)
        if cond > MAX_JACOBIAN_CONDITION:
            note = f"the face fit is ill-conditioned ({cond:.3g})"
        elif worst > FACE_MAX_RESIDUAL_DEG:
            note = (f"a face was not square and level: face residual {worst:.2f}° > "
                    f"{FACE_MAX_RESIDUAL_DEG:g}°")
        else:
            model = "full"
    else:
        note = f"only {faces} of the 6 faces held still face-down"
    if not model:
        model = "symmetric" if count >= MIN_POSES_FULL else "diagonal"
        b, m, cond = fit_norm_ellipsoid(poses, G, model == "symmetric")
        if cond > MAX_JACOBIAN_CONDITION:
            raise ValueError(f"accelerometer: the {count} static poses do not cover enough "
                             f"orientations to determine offset and scale (condition "
                             f"{cond:.3g}); add poses with gravity along the other axes")
    before = np.linalg.norm(poses, axis=1)
    after = np.linalg.norm((poses - b) @ m.T, axis=1)
    report = {"accel_poses": count, "accel_faces": faces, "accel_model": model,
              "accel_face_residual_deg": worst if model == "full" else float("nan"),
              "accel_note": note,
              "accel_norm_std_before": float(before.std()),
              "accel_norm_std_after": float(after.std()),
              "accel_norm_rms_error_before": float(np.sqrt(np.mean((before - G) ** 2))),
              "accel_norm_rms_error_after": float(np.sqrt(np.mean((after - G) ** 2)))}
    return b, m, report


# --- magnetometer -----------------------------------------------------------------

def distinct_mag_readings(mag: np.ndarray) -> np.ndarray:
    """Finite readings, each once: a board holds (and re-sends) the last reading between
    magnetometer updates, which would weight still moments by how long they lasted."""
    m = np.asarray(mag, float)
    m = m[np.all(np.isfinite(m), axis=1)]
    if len(m) == 0:
        return m
    changed = np.concatenate(([True], np.any(np.diff(m, axis=0) != 0.0, axis=1)))
    return m[changed]


def _cube_directions() -> np.ndarray:
    d = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                  if (i, j, k) != (0, 0, 0)], dtype=float)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def fit_magnetometer(mag: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """(hard iron, soft iron matrix, report fields) from readings in many orientations.

    Fits the quadric ``x^T A x + 2 g^T x = 1`` to normalised data by linear least
    squares; the centre is ``-A^-1 g`` and ``(x - c)^T A (x - c) = 1 + c^T A c``.
    """
    m = distinct_mag_readings(mag)
    if len(m) < MIN_MAG_SAMPLES:
        raise ValueError(f"magnetometer: {len(m)} distinct readings, need "
                         f"{MIN_MAG_SAMPLES}; turn the board slowly through all "
                         "orientations")
    mu = m.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((m - mu) ** 2, axis=1))))
    if not s > 0.0:
        raise ValueError("magnetometer: readings do not change; turn the board")
    z = (m - mu) / s
    x, y, w = z[:, 0], z[:, 1], z[:, 2]
    design = np.column_stack([x * x, y * y, w * w, 2 * x * y, 2 * x * w, 2 * y * w,
                              2 * x, 2 * y, 2 * w])
    sv = np.linalg.svd(design, compute_uv=False)
    if sv[-1] <= 0 or sv[0] / sv[-1] > MAX_QUADRIC_CONDITION:
        raise ValueError("magnetometer: readings span too little of the sphere to fit "
                         "an ellipsoid (e.g. turned about one axis only); turn the board "
                         "through all orientations, including upside down")
    p = np.linalg.lstsq(design, np.ones(len(z)), rcond=None)[0]
    a = _sym(p[[0, 1, 2, 3, 4, 5]])
    g = p[6:9]
    try:
        centre = -np.linalg.solve(a, g)
    except np.linalg.LinAlgError:
        raise ValueError("magnetometer: the readings do not lie on an ellipsoid") from None
    k = 1.0 + centre @ a @ centre
    shape = a / k
    evals, evecs = np.linalg.eigh(shape)
    if not np.all(evals > 0):
        raise ValueError("magnetometer: the readings do not lie on an ellipsoid (fit is "
                         "not closed); turn the board through all orientations, away from "
                         "magnets and motors")
    root = evecs @ np.diag(np.sqrt(evals)) @ evecs.T  # unit sphere in normalised units
    offset = mu + s * centre
    units = (m - offset) / np.linalg.norm(m - offset, axis=1, keepdims=True)
    spread = float(np.linalg.eigvalsh(units.T @ units / len(units))[0])
    covered = int(np.sum(np.max(units @ _cube_directions().T, axis=0) > np.cos(np.pi / 4)))
    if spread < MIN_MAG_SPREAD or covered < MIN_MAG_DIRECTIONS:
        raise ValueError(f"magnetometer: readings cover too little of the sphere "
                         f"(direction spread {spread:.3f}, need {MIN_MAG_SPREAD}; "
                         f"{covered} of 26 directions, need {MIN_MAG_DIRECTIONS}); turn "
                         "the board through all orientations, including upside down")
    strength = float(np.mean(np.linalg.norm(m - offset, axis=1)))
    matrix = strength * root / s
    before = np.linalg.norm(m, axis=1)
    after = np.linalg.norm((m - offset) @ matrix.T, axis=1)
    report = {"mag_samples": len(m), "mag_spread": spread,
              "mag_norm_rel_std_before": float(before.std() / before.mean()),
              "mag_norm_rel_std_after": float(after.std() / after.mean())}
    return offset, matrix, report


# --- gyro matrix ------------------------------------------------------------------

def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def pose_turns(gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None, rate_hz: float,
               cal: SensorCalibration) -> list[Turn]:
    """The turns between consecutive static poses, for :func:`fit_gyro_matrix`.

    Each runs from the middle of one pose to the middle of the next, so a slow creep
    within a pose is integrated as well as seen in the pose's mean directions. The gyro
    offset is each pose's mean rate, interpolated in time between the two poses (it
    wanders); the references are the calibrated gravity and (when ``mag`` is given)
    field directions. Turns with missing samples (a gap between pooled logs) are left out.
    """
    g = np.asarray(gyr, float)
    _, runs, n = static_poses(gyr, acc, rate_hz)
    _, g_mean, a_mean, _ = still_blocks(gyr, acc, rate_hz)
    turns = []
    for (s0, e0), (s1, e1) in itertools.pairwise(runs):
        start, stop = (s0 + e0) * n // 2, (s1 + e1) * n // 2
        b0, b1 = g_mean[s0:e0].mean(axis=0), g_mean[s1:e1].mean(axis=0)
        frac = (np.arange(stop - start) + 0.5) / (stop - start)
        rates = g[start:stop] - (b0 + frac[:, None] * (b1 - b0))
        if not np.all(np.isfinite(rates)):
            continue
        refs, weight = [], np.ones(2)
        for s, e in ((s0, e0), (s1, e1)):
            field = np.full(3, np.nan)
            if mag is not None:  # skip the first block: it may hold a reading taken moving
                m = mag[(s + 1) * n:e * n]
                m = m[np.all(np.isfinite(m), axis=1)]
                if len(m):
                    field = cal.mag(m.mean(axis=0))
            refs.append((_unit(cal.accel(a_mean[s:e].mean(axis=0))), field))
        if not np.all(np.isfinite(refs[0][1])) or not np.all(np.isfinite(refs[1][1])):
            weight[1] = 0.0
            refs = [(a, np.zeros(3)) for a, _ in refs]
        else:
            refs = [(a, _unit(f)) for a, f in refs]
        turns.append(Turn(rates, np.stack(refs[0]), np.stack(refs[1]), weight))
    return turns


# --- all together -------------------------------------------------------------------

def fit_calibration(gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None,
                    rate_hz: float, gyro: bool = True, accel: bool = True,
                    magnetometer: bool = True, gyro_matrix: bool = True
                    ) -> tuple[SensorCalibration, FitReport]:
    """Fit the requested parts (the others stay identity); ValueError if one cannot be.

    The gyro matrix (needs ``gyro``) is fitted last, on the turns between poses as the
    fitted accelerometer and magnetometer see them (gravity only without ``magnetometer``).
    """
    values: dict[str, np.ndarray] = {}
    report: dict = {}
    if gyro:
        values["gyro_offset"], report["gyro_still_s"] = fit_gyro_offset(gyr, acc, rate_hz)
    if accel:
        values["accel_offset"], values["accel_matrix"], r = fit_accelerometer(gyr, acc,
                                                                              rate_hz)
        report.update(r)
    if magnetometer:
        if mag is None:
            raise ValueError("magnetometer: the samples have no magnetometer readings "
                             "(skip it with --no-mag)")
        values["mag_offset"], values["mag_matrix"], r = fit_magnetometer(mag)
        report.update(r)
    if gyro and gyro_matrix:
        turns = pose_turns(gyr, acc, mag if magnetometer else None, rate_hz,
                           SensorCalibration(**values))
        values["gyro_matrix"], r = fit_gyro_matrix(turns, rate_hz)
        report.update(r)
    return SensorCalibration(**values), FitReport(**report)
