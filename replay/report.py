"""The interactive HTML report: linked, zoomable Bokeh plots in one offline file.

Like PX4 Flight Review (also Bokeh), every time plot of a file shares one time axis, so
zooming into a manoeuvre in one panel zooms all of them; legends hide lines on click.
BokehJS is inlined (``bokeh.resources.INLINE``): the file opens without a network.
Contents per file: where the data came from (source, reference, declination used and
why, aiding, board), the estimators' full parameters, the scores with the reason for
every missing number, then attitude per axis with the reference (unwrapped), errors,
gyro-bias estimates and |acc| / |mag| with each estimator's rejections.
"""

from __future__ import annotations

import dataclasses
import html
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

import estimators
from estimators import _core, metrics
from estimators.spec import user_param

from .evaluate import Evaluation, amount, vehicle_note
from .flight import PHASES
from .plotdata import decimation, plot_angles
from .summary import COLUMNS

MAX_POINTS = 4000  # per line: keeps the file a few MB and the browser responsive
ERROR_FLOOR_DEG = 0.01  # log-scale error axes: zero errors drawn here
PLOT_WIDTH, PLOT_HEIGHT = 1000, 220
TOOLS = "xpan,xwheel_zoom,box_zoom,reset,save"
TITLE = "attitude-bridge replay"


def product_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("attitude-bridge")
    except PackageNotFoundError:
        return "unknown (not installed)"


def _colour(k: int) -> str:
    from bokeh.palettes import Category10_10

    return Category10_10[k % len(Category10_10)]


def _figure(title: str, y_label: str, x_range=None, y_log: bool = False):
    from bokeh.plotting import figure

    kwargs = {"x_range": x_range} if x_range is not None else {}
    fig = figure(title=title, width=PLOT_WIDTH, height=PLOT_HEIGHT, tools=TOOLS,
                 active_scroll="xwheel_zoom", x_axis_label="time [s]", y_axis_label=y_label,
                 y_axis_type="log" if y_log else "linear", output_backend="webgl", **kwargs)
    return fig


def _finish(fig) -> None:
    if fig.legend:
        fig.legend.click_policy = "hide"
        fig.legend.location = "top_left"
        fig.legend.label_text_font_size = "8pt"
        fig.legend.background_fill_alpha = 0.6


def _line(fig, t: np.ndarray, y: np.ndarray, label: str, colour: str, width: float = 1.2):
    """NaN-free decimated line (NaN breaks the line, as a gap should)."""
    sl = decimation(len(t), MAX_POINTS)
    fig.line(t[sl], y[sl], legend_label=label, line_color=colour, line_width=width)


def _info_html(ev: Evaluation) -> str:
    rec, prep = ev.recording, ev.prepared
    ref = rec.reference
    rows = [
        ("file", f"{rec.path} ({rec.format})"),
        ("IMU", f"{rec.source}: {rec.n} samples over {amount(rec.duration)} s at "
                f"{amount(rec.rate_hz)} Hz; body {rec.body}, world {rec.world}"),
        ("reference", "none" if ref is None else
         f"{ref.kind} ({ref.source}), {ref.north} north" + (f"; {ref.timing}" if ref.timing
                                                            else "")),
        ("declination used", prep.declination.describe()),
        ("IMU delay", f"{prep.imu_delay.ms:.1f} ms ({prep.imu_delay.source})"),
        ("aiding", prep.aid_note),
        ("vehicle", vehicle_note(prep.recording)),
        ("flight state", prep.flight.note() if prep.flight is not None else "not read"),
        ("board profile", rec.board or "not applicable (SI units in the log)"),
        ("attitude-bridge", product_version()),
    ]
    rows += [("note", n) for n in rec.notes]
    rows += [("warning", w) for w in rec.warnings]
    if ev.not_run:
        rows.append(("not scored", ev.not_run + "; estimators not run"))
    elif prep.unscored:
        rows.append(("not scored", prep.unscored))
    body = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>"
                   for k, v in rows)
    return f"<table class='info'>{body}</table>"


def _params_html(ev: Evaluation) -> str:
    """Every estimator's complete parameter set (defaults included), angles in degrees."""
    rows = []
    for label, run in ev.runs.items():
        given = {"declination": ev.prepared.declination.rad,
                 "imu_delay": ev.prepared.imu_delay.seconds, **run.spec.params}
        params = dataclasses.asdict(
            estimators.estimator_class(run.spec.name).make_params(**given))
        cls = estimators.estimator_class(run.spec.name)
        text = ", ".join(_param_text(*user_param(cls, k, v)) for k, v in params.items())
        rows.append(f"<tr><th>{html.escape(label)}</th><td>{html.escape(text)}</td></tr>")
    return f"<h3>Estimator parameters</h3><table class='info'>{''.join(rows)}</table>"


def _param_text(name: str, value: object) -> str:
    if name.endswith(("_deg", "_dps")) and isinstance(value, float):
        return f"{name}={value:.3f}"
    if isinstance(value, int | float):
        return f"{name}={value:.6g}"
    return f"{name}={value}"


def _scores_html(ev: Evaluation) -> str:
    if ev.not_run:
        return f"<p><b>Not scored:</b> {html.escape(ev.not_run)}</p>"
    head = "".join(f"<th>{html.escape(h)}</th>" for _, h, _, _ in COLUMNS)
    extra = ("roll_deg", "pitch_deg", "yaw_deg", "acc_rejected_frac", "mag_rejected_frac",
             "samples")
    head += "".join(f"<th>{c}</th>" for c in extra)
    notes: list[str] = []
    rows = []
    for label, s in ev.scores.items():
        cells = []
        for name, _, scale, fmt in COLUMNS:
            v = getattr(s, name)
            if math.isfinite(v):
                cells.append(fmt.format(v * scale))
            else:
                reason = s.reasons.get(name, "not available")
                if reason not in notes:
                    notes.append(reason)
                cells.append(f"<span title='{html.escape(reason)}'>"
                             f"–({notes.index(reason) + 1})</span>")
        for name in extra:
            v = getattr(s, name)
            cells.append("–" if isinstance(v, float) and not math.isfinite(v)
                         else (f"{v:.3f}" if isinstance(v, float) else str(v)))
        rows.append(f"<tr><th>{html.escape(label)}</th>"
                    + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    foot = "".join(f"<li>({k}) {html.escape(n)}</li>" for k, n in enumerate(notes, 1))
    return (f"<h3>Scores</h3><table class='scores'><tr><th>estimator</th>{head}</tr>"
            f"{''.join(rows)}</table><ul class='notes'>{foot}</ul>{_phases_html(ev)}")


def _phases_html(ev: Evaluation) -> str:
    """Total error (inclination without magnetometer) per flight phase, worst marked."""
    present = [p for p in PHASES if any(p in s.phases for s in ev.scores.values())]
    if len(present) < 2:
        return ""
    head = "".join(f"<th>{p}</th>" for p in present)
    rows = []
    for label, sc in ev.scores.items():
        key = "inclination_deg" if sc.six_d else "total_deg"
        worst = sc.worst_phase
        cells = []
        for p in present:
            v = sc.phases.get(p, {}).get(key, math.nan)
            text = f"{v:.3f}" if math.isfinite(v) else "–"
            cells.append(f"<b>{text}</b>" if worst and worst[0] == p else text)
        rows.append(f"<tr><th>{html.escape(label)}</th>"
                    + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    return ("<h3>By flight phase</h3><p>RMS total error in degrees (inclination without a "
            "magnetometer); the worst phase in bold. Phases from the vehicle's own reports "
            "(armed, landed state).</p><table class='scores'><tr><th>estimator</th>"
            f"{head}</tr>{''.join(rows)}</table>")


def _plots(ev: Evaluation) -> list:
    rec, prep = ev.recording, ev.prepared
    t = rec.t - rec.t[0]
    figs: list = []
    x_range = None

    def new(title: str, y_label: str, y_log: bool = False):
        nonlocal x_range
        fig = _figure(title, y_label, x_range, y_log)
        x_range = fig.x_range  # every later panel shares the first one's time axis
        figs.append(fig)
        return fig

    ref, angles = plot_angles(ev)
    for k, axis in enumerate(("roll", "pitch", "yaw")):
        fig = new(f"{axis} ({rec.world}, Z-Y-X Euler, unwrapped)", f"{axis} [deg]")
        if ref is not None:
            _line(fig, t, ref[:, k], f"reference ({rec.reference.kind})", "black", 2.0)
        for j, (label, e) in enumerate(angles.items()):
            _line(fig, t, e[:, k], label, _colour(j))
    if prep.q_ref is not None and ev.runs:
        for name in ("total", "inclination", "heading"):
            fig = new(f"{name} error against the {rec.reference.kind} (log scale)",
                      f"{name} error [deg]", y_log=True)
            for j, (label, run) in enumerate(ev.runs.items()):
                err = getattr(metrics.attitude_errors(run.q, prep.q_ref), name)
                deg = np.degrees(err)
                deg[~prep.scored] = np.nan  # only what is scored
                _line(fig, t, np.maximum(deg, ERROR_FLOOR_DEG), label, _colour(j))
    if ev.runs:
        for k, axis in enumerate("xyz"):
            fig = new(f"gyro bias estimate, body {axis}", "bias [deg/s]")
            for j, (label, run) in enumerate(ev.runs.items()):
                _line(fig, t, np.degrees(run.bias[:, k]), label, _colour(j))
    sensors = [("|acc|", "m/s²", rec.acc, _core.F_ACC_REJECTED)]
    if rec.mag is not None:
        sensors.append(("|mag|", "log units", rec.mag, _core.F_MAG_REJECTED))
    for name, unit, data, bit in sensors:
        norm = np.linalg.norm(data, axis=1)
        fig = new(f"{name} with each estimator's rejections (markers)", f"{name} [{unit}]")
        _line(fig, t, norm, name, "gray", 1.0)
        for j, (label, run) in enumerate(ev.runs.items()):
            on = np.flatnonzero((run.flags & bit) != 0)
            on = on[decimation(len(on), MAX_POINTS)]
            if on.size:
                fig.scatter(t[on], norm[on], size=4, color=_colour(j), alpha=0.7,
                            legend_label=f"{label} rejected")
    if rec.velocity is not None:
        fig = new(f"velocity aiding ({rec.velocity.source}; {prep.aid_note.split(':')[0]})",
                  "velocity [m/s]")
        v = rec.velocity.vel
        for k, axis in enumerate(("north", "east", "down")):
            ok = np.isfinite(v[:, k])
            sl = decimation(int(ok.sum()), MAX_POINTS)
            fig.scatter(t[ok][sl], v[ok, k][sl], size=3, color=_colour(k), legend_label=axis)
    for fig in figs:
        _flight_bands(fig, ev, rec.t[0])
        _finish(fig)
    return figs


#: Background of the time axis by the flight state the estimators were given.
BAND_COLOURS = {"airborne": "#8ecae6", "on ground": "#e9c46a"}


def _flight_bands(fig, ev: Evaluation, t0: float) -> None:
    """Shade the time axis where the vehicle said it was airborne / on the ground (no
    shade: nothing said, the estimator decided from the data)."""
    from bokeh.models import BoxAnnotation

    fl = ev.prepared.flight
    if fl is None or not fl.known:
        return
    for start, end, state in fl.bands(ev.recording.t):
        colour = BAND_COLOURS.get(state)
        if colour is not None:
            fig.add_layout(BoxAnnotation(left=start - t0, right=end - t0, fill_color=colour,
                                         fill_alpha=0.15, level="underlay"))


def section(ev: Evaluation) -> list:
    """Bokeh models for one replayed file."""
    from bokeh.models import Div

    head = Div(text=f"<h2>{html.escape(str(ev.recording.path))}</h2>"
                    + _info_html(ev) + _scores_html(ev) + _params_html(ev),
               width=PLOT_WIDTH)
    return [head, *_plots(ev)]


STYLE = ("<style>body{font-family:sans-serif;margin:1em auto;max-width:1040px}"
         "table{border-collapse:collapse;margin:.4em 0}td,th{border:1px solid #bbb;"
         "padding:2px 6px;font-size:9pt}table.scores td{text-align:right}"
         "table.info th{text-align:left;white-space:nowrap}ul.notes{font-size:9pt}</style>")


def html_report(evaluations: Sequence[Evaluation], title: str = TITLE) -> str:
    """The whole report as one HTML string (BokehJS inlined, no external resource)."""
    from bokeh.embed import file_html
    from bokeh.layouts import column
    from bokeh.models import Div
    from bokeh.resources import INLINE

    parts = [Div(text=STYLE + f"<h1>{html.escape(title)}</h1><p>attitude-bridge "
                          f"{html.escape(product_version())}</p>", width=PLOT_WIDTH)]
    for ev in evaluations:
        parts += section(ev)
    return file_html(column(*parts), INLINE, title)


def write_report(evaluations: Sequence[Evaluation], path: str | Path) -> Path:
    p = Path(path)
    p.write_text(html_report(evaluations), encoding="utf-8")
    return p
