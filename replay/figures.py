"""Static figures (matplotlib PNG) for papers: ``replay --png`` and ``tune --heatmap``.

They follow the seed paper's comparison of the complementary and Kalman filters:
attitude angles of every estimator over the reference, and the error over time; plus
each estimator's rejection flags and, from ``tune``, parameter-sweep heatmaps. The
interactive HTML report is :mod:`replay.report`.
"""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only: no display on servers and in CI
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

from estimators import _core, metrics

from .evaluate import Evaluation
from .plotdata import plot_angles

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
    ref, estimates = plot_angles(ev)
    if ref is not None:
        for k, ax in enumerate(axes):
            ax.plot(t[sl], ref[sl, k], color="black", lw=1.6,
                    label=f"reference ({rec.reference.kind})")
    for label, e in estimates.items():
        for k, ax in enumerate(axes):
            ax.plot(t[sl], e[sl, k], lw=0.9, label=label)
    for k, ax in enumerate(axes):
        ax.set_ylabel(f"{ANGLE_NAMES[k]} [deg]")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8, ncol=2)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"Attitude ({rec.world}, Z-Y-X Euler, unwrapped) — {rec.path.name}")
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
    """(name, PNG) for one replayed file."""
    figs = [("angles", angles_figure(ev))]
    if ev.prepared.q_ref is not None:
        figs.append(("error", error_figure(ev)))
    figs.append(("flags", flags_figure(ev)))
    return [(name, png_bytes(fig)) for name, fig in figs]


def write_pngs(ev: Evaluation, folder: str | Path) -> list[Path]:
    """``<file stem>_<figure>.png`` for each figure of ``ev`` in ``folder`` (created)."""
    out = Path(folder)
    out.mkdir(exist_ok=True)
    paths = []
    for name, data in evaluation_figures(ev):
        p = out / f"{ev.recording.path.stem}_{name}.png"
        p.write_bytes(data)
        paths.append(p)
    return paths


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
