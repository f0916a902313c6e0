"""``replay --csv``: every IMU sample's time series in one flat CSV (PlotJuggler, pandas).

Columns: ``t`` [s from the first sample]; the sensors' magnitudes (``acc_norm``,
``mag_norm``) and the velocity aiding when the log has it; the reference
(``ref.qw..qz``, ``ref.roll_deg..yaw_deg``); then per estimator ``<label>.qw..qz``,
Euler angles, BROAD errors (``err_total_deg``, ``err_heading_deg``,
``err_inclination_deg``), the rejection flags and the raw flag byte; then the same but
the flags for each ``--compare`` reference filter (``vqf online.qw`` ...). Empty = unknown.
Euler angles are wrapped to ±180° here (the data, not a plot).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from estimators import _core, metrics

from .evaluate import Evaluation
from .plotdata import euler_deg


def columns(ev: Evaluation) -> tuple[list[str], np.ndarray]:
    """Header names and the (N, C) table."""
    rec = ev.recording
    names = ["t", "acc_norm"]
    parts = [(rec.t - rec.t[0])[:, None], np.linalg.norm(rec.acc, axis=1)[:, None]]
    if rec.mag is not None:
        names.append("mag_norm")
        parts.append(np.linalg.norm(rec.mag, axis=1)[:, None])
    if rec.velocity is not None:
        names += ["vel_n", "vel_e", "vel_d", "vel_age_s"]
        parts += [rec.velocity.vel, rec.velocity.age[:, None]]
    q_ref = ev.prepared.q_ref
    if q_ref is not None:
        names += ["ref.qw", "ref.qx", "ref.qy", "ref.qz",
                  "ref.roll_deg", "ref.pitch_deg", "ref.yaw_deg"]
        parts += [q_ref, euler_deg(q_ref)]
    for label, run in ev.runs.items():
        _attitude_columns(label, run.q, q_ref, names, parts)
        names += [f"{label}.{c}" for c in ("acc_rejected", "mag_rejected", "flags")]
        flags = run.flags.astype(int)
        parts.append(np.column_stack([(flags & _core.F_ACC_REJECTED) != 0,
                                      (flags & _core.F_MAG_REJECTED) != 0, flags]))
    for label, ref in ev.references.items():  # --compare's reference filters: no flags
        _attitude_columns(label, ref.q, q_ref, names, parts)
    return names, np.hstack([np.asarray(p, dtype=float) for p in parts])


def _attitude_columns(label: str, q: np.ndarray, q_ref: np.ndarray | None,
                      names: list[str], parts: list) -> None:
    """An attitude's quaternion, Euler angles and, with a reference, its errors."""
    names += [f"{label}.{c}" for c in ("qw", "qx", "qy", "qz", "roll_deg", "pitch_deg",
                                       "yaw_deg")]
    parts += [q, euler_deg(q)]
    if q_ref is not None:
        err = metrics.attitude_errors(q, q_ref)
        names += [f"{label}.err_{c}_deg" for c in ("total", "heading", "inclination")]
        parts.append(np.degrees(np.column_stack([err.total, err.heading, err.inclination])))


def write_csv(ev: Evaluation, path: str | Path) -> Path:
    names, table = columns(ev)
    buf = io.StringIO()
    np.savetxt(buf, table, fmt="%.9g", delimiter=",")
    p = Path(path)
    # "nan" is the only text %g writes that is not a number: unknown becomes empty
    p.write_text(",".join(names) + "\n" + buf.getvalue().replace("nan", ""), encoding="utf-8")
    return p
