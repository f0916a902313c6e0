"""Accelerometer offset and full 3×3 matrix from the six face-down poses.

The norms of static readings (``|M (a - b)| = g``) see only the symmetric part of the
accelerometer's error matrix: a rotation of the sensing axes against the board leaves
every norm unchanged, so a few tenths of a degree of misalignment (percent-level
cross-axis errors) would stay in the tilt. The standard autopilot calibration (PX4,
ArduPilot: the vehicle placed on each of its six faces) knows more: in each face-down
pose one body axis points straight down, so the corrected reading must be exactly
``g`` along that axis, ``M (a_i - b) = g e_i``. With all six faces the offset and all
nine entries of ``M`` — rotation included — are determined; the other static poses
add their norm condition.

Assumption: each face is placed square on a level surface. A tilted face tilts the
result by a comparable angle; the six faces are redundant in the offset (each opposite
pair must agree on it), and the largest face residual after the fit exposes a tilted
or unsquare placement, so the caller can fall back to the norm-only fit.
"""

from __future__ import annotations

import numpy as np

#: A static pose whose specific force is within this of a body axis is a face-down pose.
FACE_TOLERANCE_DEG = 15.0
#: Largest angle between a face pose's corrected reading and its axis after the fit; a
#: larger one means a face was not square and level (a tilt δ of one face shows as
#: about δ/2 here and leaves about δ/4 of misalignment), and the full matrix would carry
#: that tilt; the norm-only fit is then the better choice.
FACE_MAX_RESIDUAL_DEG = 0.3
MAX_JACOBIAN_CONDITION = 1e4


def face_labels(poses: np.ndarray) -> np.ndarray:
    """(P,) face index per pose: 2·axis + (0 for +, 1 for −) of the body axis the
    specific force points along, -1 for a pose that is no face (e.g. on an edge)."""
    p = np.asarray(poses, float).reshape(-1, 3)
    units = p / np.linalg.norm(p, axis=1, keepdims=True)
    axis = np.argmax(np.abs(units), axis=1)
    along = np.abs(units[np.arange(len(p)), axis])
    negative = units[np.arange(len(p)), axis] < 0.0
    labels = 2 * axis + negative.astype(int)
    return np.where(along >= np.cos(np.radians(FACE_TOLERANCE_DEG)), labels, -1)


def face_targets(labels: np.ndarray, g: float) -> np.ndarray:
    """(F, 3) corrected specific force each face pose must read: g along its axis."""
    targets = np.zeros((len(labels), 3))
    targets[np.arange(len(labels)), labels // 2] = np.where(labels % 2, -g, g)
    return targets


def _residuals(b: np.ndarray, m: np.ndarray, faces: np.ndarray, targets: np.ndarray,
               others: np.ndarray, g: float) -> tuple[np.ndarray, np.ndarray]:
    """(residuals, Jacobian over [b, M row-major]) of the face and norm conditions."""
    d_f = faces - b
    r_f = (d_f @ m.T - targets).ravel()
    j_f = np.zeros((len(faces), 3, 12))
    j_f[:, :, 0:3] = -m  # d(M (a - b)) / db
    for row in range(3):  # d(M (a - b))_row / dM_row,col = (a - b)_col
        j_f[:, row, 3 + 3 * row: 6 + 3 * row] = d_f
    d_o = others - b
    y = d_o @ m.T
    norm = np.linalg.norm(y, axis=1)
    u = y / norm[:, None]
    r_o = norm - g
    j_o = np.zeros((len(others), 12))
    j_o[:, 0:3] = -u @ m
    j_o[:, 3:] = (u[:, :, None] * d_o[:, None, :]).reshape(len(others), 9)
    return np.concatenate([r_f, r_o]), np.concatenate([j_f.reshape(-1, 12), j_o])


def fit_faces(poses: np.ndarray, labels: np.ndarray, g: float, iterations: int = 20
              ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(offset b, full matrix M, largest face residual [deg], Jacobian condition).

    Linear least squares on the face conditions gives the start (``M a + c = g e_i`` is
    linear in M and c = -M b); Gauss-Newton then adds the norm conditions of the other
    poses. Needs every one of the six faces in ``labels``.
    """
    p = np.asarray(poses, float)
    is_face = labels >= 0
    faces, others = p[is_face], p[~is_face]
    targets = face_targets(labels[is_face], g)
    design = np.column_stack([faces, np.ones(len(faces))])
    x = np.linalg.lstsq(design, targets, rcond=None)[0]  # (4, 3): rows of [M^T; c]
    m = x[:3].T
    b = -np.linalg.solve(m, x[3])
    cond = np.inf
    for _ in range(iterations):
        r, jac = _residuals(b, m, faces, targets, others, g)
        scale = np.linalg.norm(jac, axis=0)
        scale[scale == 0.0] = 1.0
        sv = np.linalg.svd(jac / scale, compute_uv=False)
        cond = sv[0] / sv[-1] if sv[-1] > 0 else np.inf
        if cond > MAX_JACOBIAN_CONDITION:
            break
        step = np.linalg.lstsq(jac / scale, -r, rcond=None)[0] / scale
        b = b + step[:3]
        m = m + step[3:].reshape(3, 3)
        if np.max(np.abs(step)) < 1e-12 * max(1.0, g):
            break
    corrected = (faces - b) @ m.T
    cos = np.sum(corrected * targets, axis=1) / np.linalg.norm(corrected, axis=1) / g
    worst = float(np.degrees(np.max(np.arccos(np.clip(cos, -1.0, 1.0)))))
    return b, m, worst, cond
