"""Figures (matplotlib PNG) and a single self-contained HTML report.

Figures follow the seed paper's comparison of the complementary and Kalman filters:
attitude angles of every estimator over the reference, and the error over time; plus
each estimator's rejection flags and, from ``tune``, parameter-sweep heatmaps.
"""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only: no display on servers and in CI
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

from estimators import _core, metrics
from estimators import quat as Q

from .evaluate import Evaluation

MAX_POINTS = 6000  # per line: enough for the eye, keeps PNGs small and plotting fast
ANGLE_NAMES = ("roll", "pitch", "yaw")
ERROR_FLOOR_DEG = 0.01  # bottom of the log-scale error axes


def _decimate(n: int) -> slice:
    return slice(None, None, max(1, n // MAX_POINTS))


def angles_figure(ev: Evaluation) -> Figure:
    """Roll, pitch, yaw [deg] vs time: reference in black, one colour per estimator."""
    rec = ev.recording
    t = rec.t - rec.t[0]
    sl = _decimate(rec.n)
    fig, axes = plt.subplots(3, 1, figsize=(10, 7.5), sharex=True)
    if ev.prepared.q_ref is not None:
        ref = np.degrees(Q.to_euler(ev.prepared.q_ref))
        for k, ax in enumerate(axes):
            ax.plot(t[sl], ref[sl, k], color="black", lw=1.6,
                    label=f"reference ({rec.reference.kind})")
    for label, run in ev.runs.items():
        e = np.degrees(Q.to_euler(run.q))
        for k, ax in enumerate(axes):
            ax.plot(t[sl], e[sl, k], lw=0.9, label=label)
    for k, ax in enumerate(axes):
        ax.set_ylabel(f"{ANGLE_NAMES[k]} [deg]")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8, ncol=2)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"Attitude ({rec.world}, Z-Y-X Euler) — {rec.path.name}")
    fig.tight_layout()
    return fig


def error_figure(ev: Evaluation) -> Figure:
    """Total, inclination and heading error [deg] vs time per estimator (BROAD definitions)."""
    rec = ev.recording
    t = rec.t - rec.t[0]
    sl = _decimate(rec.n)
    fig, axes = plt.subplots(3, 1, figsize=(10, 7.5), sharex=True)
    lows = [[], [], []]
    if ev.prepared.q_ref is not None:
        for label, run in ev.runs.items():
            err = metrics.attitude_errors(run.q, ev.prepared.q_ref)
            for k, values in enumerate((err.total, err.inclination, err.heading)):
                deg = np.degrees(values[sl])
                # log scale shows small and drifting errors together; floor the zeros
                axes[k].plot(t[sl], np.maximum(deg, ERROR_FLOOR_DEG), lw=0.9, label=label)
                if np.isfinite(deg).any():
                    lows[k].append(np.nanpercentile(deg, 1))
        if rec.score_mask is not None:  # shade the samples that are not scored
            for ax in axes:
                ax.fill_between(t[sl], 0, 1, where=~rec.score_mask[sl], color="0.85",
                                transform=ax.get_xaxis_transform(), lw=0)
    for ax, name, low in zip(axes, ("total", "inclination", "heading"), lows, strict=True):
        ax.set_ylabel(f"{name} error [deg]")
        ax.set_yscale("log")
        ax.set_ylim(bottom=max(ERROR_FLOOR_DEG, 0.5 * min(low)) if low else ERROR_FLOOR_DEG)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8, ncol=2)
    axes[-1].set_xlabel("time [s]")
    kind = rec.reference.kind if rec.reference else "no reference"
    fig.suptitle(f"Error against {kind} — {rec.path.name}")
    fig.tight_layout()
    return fig


def flags_figure(ev: Evaluation) -> Figure:
    """When each estimator rejected its accelerometer / magnetometer or skipped a sample."""
    rec = ev.recording
    t = rec.t - rec.t[0]
    bits = ((_core.F_ACC_REJECTED, "acc rejected"), (_core.F_MAG_REJECTED, "mag rejected"),
            (_core.F_SKIPPED, "skipped"), (_core.F_ACC_UNUSABLE, "acc unusable"))
    labels = list(ev.runs)
    fig, ax = plt.subplots(figsize=(10, 0.6 + 0.9 * max(1, len(labels))))
    for row, label in enumerate(labels):
        flags = ev.runs[label].flags
        for j, (bit, name) in enumerate(bits):
            on = (flags & bit) != 0
            y = row + 0.2 * j - 0.3
            ax.scatter(t[on][_decimate(int(on.sum()))], np.full(on.sum(), y)[
                _decimate(int(on.sum()))], s=2, color=f"C{j}",
                label=name if row == 0 else None)
    ax.set_yticks(range(len(labels)), labels)
    ax.set_ylim(-0.6, len(labels) - 0.4)
    ax.set_xlim(t[0], t[-1])
    ax.set_xlabel("time [s]")
    ax.legend(loc="upper right", fontsize=8, ncol=4, markerscale=4)
    ax.set_title("Estimator flags over time")
    fig.tight_layout()
    return fig


def heatmap_figure(x_name: str, x: np.ndarray, y_name: str, y: np.ndarray,
                   values: np.ndarray, title: str = "mean total RMSE [deg]") -> Figure:
    """``values[i, j]`` at (x[j], y[i]) as a colour map, best cell marked."""
    fig, ax = plt.subplots(figsize=(7, 5.5))
    finite = np.isfinite(values)
    vmax = np.nanpercentile(values, 95) if finite.any() else 1.0
    mesh = ax.pcolormesh(_edges(x), _edges(y), values, shading="flat", cmap="viridis_r",
                         vmax=vmax)
    fig.colorbar(mesh, ax=ax, label=title)
    if finite.any():
        i, j = np.unravel_index(np.nanargmin(values), values.shape)
        ax.plot(x[j], y[i], marker="*", color="red", ms=14,
                label=f"best {x_name}={x[j]:.4g}, {y_name}={y[i]:.4g}: {values[i, j]:.3g}")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_xlabel(x_name)
    ax.set_ylabel(y_name)
    ax.set_title(title)
    fig.tight_layout()
    return fig


def _edges(c: np.ndarray) -> np.ndarray:
    """Cell edges around centres (works for a single value too)."""
    c = np.asarray(c, dtype=float)
    if c.size == 1:
        return np.array([c[0] - 0.5, c[0] + 0.5])
    mid = 0.5 * (c[1:] + c[:-1])
    return np.concatenate(([2 * c[0] - mid[0]], mid, [2 * c[-1] - mid[-1]]))


def png_bytes(fig: Figure, dpi: int = 100) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    return buf.getvalue()


def save_png(fig: Figure, path: str | Path, dpi: int = 100) -> Path:
    p = Path(path)
    p.write_bytes(png_bytes(fig, dpi))
    return p


def evaluation_figures(ev: Evaluation) -> list[tuple[str, bytes]]:
    """(caption, PNG) for one replayed file."""
    figs = [("Attitude angles", angles_figure(ev))]
    if ev.prepared.q_ref is not None:
        figs.append(("Error over time", error_figure(ev)))
    figs.append(("Flags", flags_figure(ev)))
    return [(caption, png_bytes(fig)) for caption, fig in figs]


def _fmt(v: float | int | None, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "–"
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def metrics_table(ev: Evaluation) -> str:
    cols = ("total_deg", "heading_deg", "inclination_deg", "roll_deg", "pitch_deg",
            "yaw_deg", "lag_s", "convergence_s", "acc_rejected_frac", "mag_rejected_frac",
            "samples", "six_d")
    head = "".join(f"<th>{c}</th>" for c in ("estimator", *cols))
    rows = []
    for label, s in ev.scores.items():
        d = s.as_json()
        rows.append(f"<tr><td>{html.escape(label)}</td>"
                    + "".join(f"<td>{_fmt(d[c])}</td>" for c in cols) + "</tr>")
    return f"<table><tr>{head}</tr>{''.join(rows)}</table>"


def html_report(sections: Sequence[tuple[str, str, list[tuple[str, bytes]]]],
                title: str = "attitude-bridge replay") -> str:
    """One HTML page; each section is (heading, html body, [(caption, png)]).

    Images are embedded as ``data:image/png;base64`` URIs so the file is self-contained.
    """
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}"
             "</title><style>body{font-family:sans-serif;max-width:1100px;margin:auto}"
             "table{border-collapse:collapse}td,th{border:1px solid #bbb;padding:2px 6px;"
             "text-align:right}img{max-width:100%}</style></head><body>",
             f"<h1>{html.escape(title)}</h1>"]
    for heading, body, images in sections:
        parts.append(f"<h2>{html.escape(heading)}</h2>{body}")
        for caption, png in images:
            data = base64.b64encode(png).decode("ascii")
            parts.append(f"<figure><img alt='{html.escape(caption)}' "
                         f"src='data:image/png;base64,{data}'><figcaption>"
                         f"{html.escape(caption)}</figcaption></figure>")
    parts.append("</body></html>")
    return "\n".join(parts)


def evaluation_section(ev: Evaluation) -> tuple[str, str, list[tuple[str, bytes]]]:
    rec = ev.recording
    ref = rec.reference
    info = (f"<p>{html.escape(rec.format)} file, IMU {html.escape(rec.source)}, "
            f"{rec.n} samples over {rec.duration:.1f} s ({rec.rate_hz:.1f} Hz), world "
            f"{rec.world}; reference: "
            + (f"{ref.kind} ({html.escape(ref.source)})" if ref else "none") + "</p>"
            + "".join(f"<p><i>{html.escape(n)}</i></p>" for n in rec.notes))
    return str(rec.path), info + metrics_table(ev), evaluation_figures(ev)


def write_report(evaluations: Sequence[Evaluation], path: str | Path) -> Path:
    p = Path(path)
    p.write_text(html_report([evaluation_section(ev) for ev in evaluations]),
                 encoding="utf-8")
    return p


def sweep_figure(sweep) -> Figure:
    """Heatmap of a tune sweep over its first two parameters (best over any others),
    or a line plot for a one-parameter sweep."""
    grid = sweep.grid()
    axes = sweep.axes
    if len(axes) == 1:
        fig, ax = plt.subplots(figsize=(7, 4.5))
        ax.plot(axes[0].values, grid, marker="o")
        j = sweep.best_index
        ax.plot(axes[0].values[j], grid[j], marker="*", color="red", ms=14,
                label=f"best {axes[0].name}={axes[0].values[j]:.4g}: {grid[j]:.3g}")
        ax.set_xlabel(axes[0].name)
        ax.set_ylabel(f"mean {sweep.objective} RMSE [deg]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        ax.set_title(f"{sweep.estimator}: sweep over {len(sweep.files)} file(s)")
        fig.tight_layout()
        return fig
    values = grid.reshape(grid.shape[0], grid.shape[1], -1)
    with np.errstate(all="ignore"):
        best_rest = np.where(np.all(np.isnan(values), axis=2), np.nan,
                             np.nanmin(np.where(np.isnan(values), np.inf, values), axis=2))
    # grid[i, j] is (first, second) parameter; the heatmap wants rows = y = second.
    return heatmap_figure(axes[0].name, axes[0].values, axes[1].name, axes[1].values,
                          best_rest.T,
                          title=f"{sweep.estimator}: mean {sweep.objective} RMSE [deg], "
                                f"{len(sweep.files)} file(s)")
