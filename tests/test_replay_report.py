"""The interactive report is one offline file with linked plots; PNGs and the time-series
CSV are what they claim to be."""

from __future__ import annotations

import io
import json
import re

import matplotlib.image as mpimg
import numpy as np

import replay
from replay import figures, report
from replay.evaluate import prepare
from replay.plotdata import plot_angles
from replay.synthetic import SyntheticConfig, generate
from replay.timeseries import write_csv
from replay.tune import ParamAxis, sweep

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def decode_png(data: bytes) -> np.ndarray:
    assert data.startswith(PNG_SIGNATURE)
    return mpimg.imread(io.BytesIO(data), format="png")


def bokeh_documents(text: str) -> list[dict]:
    """The Bokeh document JSON embedded in a report page."""
    blocks = re.findall(r'<script type="application/json" id="[^"]+">\s*(.*?)\s*</script>',
                        text, flags=re.S)
    assert blocks, "no Bokeh document in the page"
    return [json.loads(b) for b in blocks]


def x_ranges(node):
    """The id of every figure's x_range (defined in place or referenced)."""
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "x_range" and isinstance(value, dict) and "id" in value:
                yield value["id"]
            yield from x_ranges(value)
    elif isinstance(node, list):
        for item in node:
            yield from x_ranges(item)


def test_report_is_offline_bokeh_with_linked_time_axes(tmp_path):
    rec = generate(SyntheticConfig(duration_s=8.0, seed=3))
    ev = replay.evaluate(rec, ["mahony", "quaternion"], declination_deg=2.5)
    out = report.write_report([ev], tmp_path / "r.html")
    text = out.read_text(encoding="utf-8")
    # Self-contained: no script or stylesheet fetched from elsewhere, BokehJS inlined.
    assert not re.search(r"<(script|link)[^>]+(src|href)=[\"']https?:", text)
    assert "Bokeh" in text and len(text) > 500_000  # the library itself is in the file
    doc = json.dumps(bokeh_documents(text), ensure_ascii=False)
    for title in ("roll (NED", "yaw (NED", "total error", "gyro bias estimate, body z",
                  "|acc| with each estimator", "|mag| with each estimator"):
        assert title in doc, title
    # Source, declination used and why, product version, parameters in degrees
    for needle in ("declination used", "+2.50° (--declination-deg)", "attitude-bridge",
                   "declination_deg=2.500", "kp=", "mahony", "quaternion"):
        assert needle in doc, needle
    # One shared x range: every time plot links to the first one's (zoom one, zoom all).
    ranges = list(x_ranges(bokeh_documents(text)))
    assert len(ranges) == 11 and len(set(ranges)) == 1  # 3 angles, 3 errors, 3 bias, 2 norms


def test_yaw_is_unwrapped_for_plotting():
    """A steady yaw rotation through ±180° plots as one straight ramp, estimate beside
    the reference (no 360° jumps, no whole-turn offset between the two)."""
    rec = generate(SyntheticConfig(duration_s=20.0, amplitude_deg=(5.0, 5.0, 400.0),
                                   period_s=(7.0, 11.0, 17.0), seed=8))
    ev = replay.evaluate(rec, ["mahony"])
    ref, est = plot_angles(ev)
    assert np.nanmax(np.abs(np.diff(ref[:, 2]))) < 20.0
    assert np.nanmax(ref[:, 2]) - np.nanmin(ref[:, 2]) > 400.0  # beyond ±180: unwrapped
    yaw = est["mahony"][:, 2]
    assert np.nanmax(np.abs(np.diff(yaw))) < 20.0
    assert np.nanmedian(np.abs(yaw - ref[:, 2])) < 10.0


def test_png_figures_and_sweep_heatmap(tmp_path):
    ev = replay.evaluate(generate(SyntheticConfig(duration_s=6.0, seed=4)), ["mahony"])
    paths = figures.write_pngs(ev, tmp_path / "figs")
    assert [p.name for p in paths] == ["synthetic-seed4_angles.png", "synthetic-seed4_error.png",
                                       "synthetic-seed4_flags.png"]
    for p in paths:
        img = decode_png(p.read_bytes())
        assert img.shape[0] >= 100 and img.shape[1] >= 600  # flags: 0.9 in per estimator
        assert img[..., :3].std() > 0.05  # something was drawn, not a blank canvas
    result = sweep([prepare(ev.recording)], "mahony",
                   [ParamAxis("kp", np.array([0.1, 1.0, 5.0])),
                    ParamAxis("ki", np.array([0.0, 0.1]))], jobs=1, progress=False)
    heat = figures.save_png(figures.sweep_figure(result), tmp_path / "heat.png")
    assert decode_png(heat.read_bytes()).shape[0] >= 300


def test_time_series_csv(tmp_path):
    rec = generate(SyntheticConfig(duration_s=3.0, seed=5))
    ev = replay.evaluate(rec, ["mahony"])
    path = write_csv(ev, tmp_path / "ts.csv")
    lines = path.read_text().splitlines()
    head = lines[0].split(",")
    assert head[:3] == ["t", "acc_norm", "mag_norm"]
    for col in ("ref.qw", "ref.yaw_deg", "mahony.qx", "mahony.roll_deg",
                "mahony.err_total_deg", "mahony.acc_rejected", "mahony.flags"):
        assert col in head, col
    assert len(lines) == rec.n + 1
    table = np.genfromtxt(path, delimiter=",", skip_header=1)
    col = {name: k for k, name in enumerate(head)}
    np.testing.assert_allclose(table[:, col["t"]], rec.t - rec.t[0], atol=1e-9)
    np.testing.assert_allclose(table[:, [col[f"mahony.q{c}"] for c in "wxyz"]],
                               ev.runs["mahony"].q, atol=1e-8)
    err = table[:, col["mahony.err_total_deg"]]
    rms = np.sqrt(np.nanmean(err[ev.prepared.scored] ** 2))
    assert abs(rms - ev.scores["mahony"].total_deg) < 1e-6
