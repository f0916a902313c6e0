"""``replay PATH... --report OUT.html`` for a corpus: one offline page with the summary's
tables and a box chart of each estimator's per-log scores.

The single-file report (``replay.report``) draws time series; a corpus has too many logs
for that, so this page shows what the text summary shows (per log worst first, per
estimator, per vehicle type, per flight phase, the logs not scored and why) plus the
distribution behind the per-estimator means: a box (quartiles, median) and whiskers
(lowest and highest log) per estimator, every log as a dot whose tooltip names it.
Same style and offline BokehJS as the single-file report.
"""

from __future__ import annotations

import html
import math
from pathlib import Path

import numpy as np

from .corpus_summary import SCORE_RULE, CorpusSummary, _named
from .corpus_task import FAILED, NOT_SCORED
from .report import PLOT_WIDTH, STYLE, product_version

TITLE = "attitude-bridge corpus replay"
LOG_FLOOR_DEG = 0.001  # log-scale axis: a zero score is drawn here


def _cell(v: float | None) -> str:
    return f"{v:.3f}" if v is not None and math.isfinite(v) else "–"


def _table(head: list[str], rows: list[list[str]]) -> str:
    h = "".join(f"<th>{html.escape(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table class='scores'><tr>{h}</tr>{body}</table>"


def tables_html(s: CorpusSummary) -> str:
    labels = list(s.labels)
    doc = s.as_json()
    parts = [f"<p>{doc['logs']} logs: {doc['scored']} scored, {doc['not_scored']} not "
             f"scored, {doc['failed']} failed. Score in degrees: {html.escape(SCORE_RULE)}."
             "</p>", "<h3>By estimator</h3>"]
    parts.append(_table(
        ["estimator", "logs", "mean", "median", "worst", "worst log", "inclination mean"],
        [[html.escape(lab), str(a["score"]["logs"]), _cell(a["score"]["mean_deg"]),
          _cell(a["score"]["median_deg"]), _cell(a["score"]["worst_deg"]),
          html.escape(a["score"]["worst_file"] or "–"), _cell(a["inclination"]["mean_deg"])]
         for lab, a in doc["by_estimator"].items()]))
    for title, groups in (("By vehicle type", doc["by_vehicle"]),
                          ("By flight phase", doc["by_phase"])):
        if groups:
            parts.append(f"<h3>{title} (mean score)</h3>")
            parts.append(_table(["", "logs", *labels], [
                [html.escape(name), str(g["logs"]),
                 *(_cell(g["estimators"][lab]["mean_deg"]) for lab in labels)]
                for name, g in groups.items()]))
    parts.append("<h3>Per log, worst first</h3>")
    parts.append(_table(["log", "format", "vehicle", *labels], [
        [html.escape(e["file"]), html.escape(e.get("format", "")),
         html.escape(e.get("vehicle", "")), *(_cell(s.score(e, lab)) for lab in labels)]
        for e in s.worst_first() if e["status"] not in (NOT_SCORED, FAILED)]))
    for status in (NOT_SCORED, FAILED):
        entries = s.with_status(status)
        if entries:
            parts.append(f"<h3>{status.capitalize()}</h3><ul class='notes'>" + "".join(
                f"<li>{html.escape(_named(e))}</li>"
                for e in entries) + "</ul>")
    return "".join(parts)


def box_chart(s: CorpusSummary):
    """Per estimator: quartile box, median, whiskers to the best and worst log, and one
    dot per log (tooltip: the log and its score)."""
    from bokeh.models import ColumnDataSource, HoverTool
    from bokeh.plotting import figure
    from bokeh.transform import jitter

    labels = list(s.labels)
    fig = figure(title="score per log [deg] by estimator (box: quartiles and median; "
                       "whiskers: best and worst log)", x_range=labels, width=PLOT_WIDTH,
                 height=420, tools="pan,wheel_zoom,box_zoom,reset,save",
                 y_axis_label="score [deg] (log scale)", y_axis_type="log")
    dots: dict[str, list] = {"x": [], "y": [], "log": []}
    boxes: dict[str, list] = {k: [] for k in ("x", "q1", "q2", "q3", "lo", "hi")}
    for label in labels:
        pairs = [(s.score(e, label), e["file"]) for e in s.scored]
        pairs = [(max(v, LOG_FLOOR_DEG), f) for v, f in pairs if math.isfinite(v)]
        if not pairs:
            continue
        values = np.array([v for v, _ in pairs])
        q1, q2, q3 = np.percentile(values, [25, 50, 75])
        for key, v in zip(boxes, (label, q1, q2, q3, values.min(), values.max()),
                          strict=True):
            boxes[key].append(v)
        for v, f in pairs:
            dots["x"].append(label)
            dots["y"].append(v)
            dots["log"].append(f)
    box = ColumnDataSource(boxes)
    fig.segment("x", "lo", "x", "hi", source=box, line_color="black")
    fig.vbar("x", 0.6, "q2", "q3", source=box, fill_color="#8ecae6", line_color="black")
    fig.vbar("x", 0.6, "q1", "q2", source=box, fill_color="#8ecae6", line_color="black")
    points = fig.scatter(jitter("x", width=0.4, range=fig.x_range), "y",
                         source=ColumnDataSource(dots), size=5, alpha=0.6, color="#d62728")
    fig.add_tools(HoverTool(renderers=[points], tooltips=[("log", "@log"),
                                                          ("score", "@y{0.000} deg")]))
    return fig


def html_report(s: CorpusSummary) -> str:
    from bokeh.embed import file_html
    from bokeh.layouts import column
    from bokeh.models import Div
    from bokeh.resources import INLINE

    head = Div(text=STYLE + f"<h1>{TITLE}</h1><p>attitude-bridge "
                            f"{html.escape(product_version())}</p>", width=PLOT_WIDTH)
    parts = [head]
    if s.scored:
        parts.append(box_chart(s))
    parts.append(Div(text=STYLE + tables_html(s), width=PLOT_WIDTH))  # each Div: own styles
    return file_html(column(*parts), INLINE, TITLE)


def write_report(s: CorpusSummary, path: str | Path) -> Path:
    p = Path(path)
    p.write_text(html_report(s), encoding="utf-8")
    return p
