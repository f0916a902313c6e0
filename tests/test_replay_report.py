"""The HTML report and PNG figures render and are self-contained."""

from __future__ import annotations

import base64
import io
import re

import matplotlib.image as mpimg
import numpy as np

import replay
from replay import report
from replay.evaluate import prepare
from replay.synthetic import SyntheticConfig, generate
from replay.tune import ParamAxis, sweep

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def decode_png(data: bytes) -> np.ndarray:
    assert data.startswith(PNG_SIGNATURE)
    return mpimg.imread(io.BytesIO(data), format="png")


def test_report_embeds_valid_pngs(tmp_path):
    rec = generate(SyntheticConfig(duration_s=8.0, seed=3))
    ev = replay.evaluate(rec, ["mahony", "quaternion"])
    out = report.write_report([ev], tmp_path / "r.html")
    text = out.read_text(encoding="utf-8")
    images = re.findall(r"src='data:image/png;base64,([A-Za-z0-9+/=]+)'", text)
    assert len(images) == 3  # angles, error, flags
    for b64 in images:
        img = decode_png(base64.b64decode(b64))
        assert img.shape[0] >= 200 and img.shape[1] >= 600
        assert img[..., :3].std() > 0.05  # something was drawn, not a blank canvas
    assert "http" not in text.split("<body>", 1)[1]  # nothing fetched from elsewhere
    for label in ("mahony", "quaternion", "total_deg"):
        assert label in text


def test_sweep_heatmap_png(tmp_path):
    prep = prepare(generate(SyntheticConfig(duration_s=6.0, seed=4)))
    result = sweep([prep], "mahony", [ParamAxis("kp", np.array([0.1, 1.0, 5.0])),
                                      ParamAxis("ki", np.array([0.0, 0.1]))],
                   jobs=1, progress=False)
    path = report.save_png(report.sweep_figure(result), tmp_path / "heat.png")
    img = decode_png(path.read_bytes())
    assert img.shape[0] >= 300 and img.shape[1] >= 400
