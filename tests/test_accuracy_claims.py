"""The accuracy numbers the README states for eskf's defaults, each held by a gate at
most 1.1x over what was measured (in-sample: the defaults were chosen on these same
recordings, docs/accuracy.md), and against the references in the same run.

Measured with the product defaults (``python benchmarks/accuracy.py`` prints the same):

* BROAD dev trials (9): mean total 1.86°, worst-trial inclination 1.50°; VQF online on
  the same data 3.25° / 1.72°.
* PX4 SIH flights, whole recording (ground, take-off, flight, touchdown, landing), replay
  with its defaults (velocity aiding from the log, drag model while the log says
  airborne), total / inclination: aggressive 0.95 / 0.54, box 0.87 / 0.74, touchdown
  1.61 / 0.83, dashes 1.29 / 0.75; PX4's own attitude 1.23 / 0.61, 1.55 / 0.98,
  2.19 / 1.00, 2.26 / 0.93.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from recordings import recording

import estimators
from estimators.metrics import rms_errors
from replay.evaluate import evaluate

HEADROOM = 1.1
SITL = Path(__file__).parent / "data" / "sitl"
#: file -> (eskf total, eskf inclination) measured [deg]
PX4_MEASURED = {
    "px4_sih/sih_aggressive.tlog": (0.95, 0.54),
    "px4_sih/sih_box.tlog": (0.87, 0.74),
    "sitl/px4_sih_touchdown.tlog": (1.61, 0.83),
    "sitl/px4_sih_dashes.tlog": (1.29, 0.75),
}
BROAD_MEAN_TOTAL, BROAD_WORST_INCLINATION = 1.86, 1.50


def test_broad_dev_trials_mean_and_worst_beat_vqf(data_dir):
    import vqf

    ours, theirs = [], []
    for f in sorted((data_dir / "broad").glob("*.npz")):
        with np.load(f) as d:
            gyr, acc, mag = (np.ascontiguousarray(d[k], dtype=float)
                             for k in ("gyr", "acc", "mag"))
            rate, truth, moving = float(d["rate"]), d["quat_ref"], d["movement"]
        q = estimators.run("eskf", gyr, acc, mag, rate_hz=rate, world="ENU").q
        ours.append(rms_errors(q, truth, moving))
        ref = vqf.VQF(1.0 / rate).updateBatch(gyr, acc, mag)["quat9D"]
        theirs.append(rms_errors(ref, truth, moving))
    assert len(ours) == 9
    mean = float(np.mean([e.total_deg for e in ours]))
    worst = max(e.inclination_deg for e in ours)
    assert mean < HEADROOM * BROAD_MEAN_TOTAL, mean
    assert worst < HEADROOM * BROAD_WORST_INCLINATION, worst
    assert mean <= 0.9 * float(np.mean([e.total_deg for e in theirs]))
    assert worst <= max(e.inclination_deg for e in theirs)


@pytest.mark.parametrize("name", sorted(PX4_MEASURED))
def test_px4_sih_whole_flight_beats_px4s_own_attitude(data_dir, name):
    path = (SITL.parent / name) if name.startswith("sitl/") else data_dir / name
    rec = recording(path, reference="truth")
    ev = evaluate(rec, ["eskf"])
    assert ev.prepared.aid == "velocity" and ev.prepared.flight.known
    score = ev.scores["eskf"]
    assert score.samples > 0.95 * rec.n  # the whole recording is scored
    total, incl = PX4_MEASURED[name]
    assert score.total_deg < HEADROOM * total, score.total_deg
    assert score.inclination_deg < HEADROOM * incl, score.inclination_deg
    px4 = ev.scores["autopilot"]  # PX4's own attitude against the same truth
    assert score.total_deg <= px4.total_deg and score.inclination_deg <= px4.inclination_deg


@pytest.mark.parametrize(("name", "total", "inclination", "undelayed"), [
    ("arducopter_touchdown.tlog", 0.407, 0.207, 0.228),
    ("arducopter_circles.tlog", 0.507, 0.226, 0.262)])
def test_arducopter_sitl_flight_scored_against_simstate(name, total, inclination, undelayed):
    """Real ArduPilot Copter SITL flights with a touchdown (tests/data/sitl): SIMSTATE is
    the truth. Measured 0.407 / 0.207° and 0.507 / 0.226° (total / inclination);
    ArduPilot's own attitude 1.11 / 0.18° and 1.62 / 0.18° (better in inclination: a known
    limit, docs/accuracy.md). Its RAW_IMU is the 20 Hz low-passed gyro: without carrying
    the estimate forward by the filter's delay the inclination is 0.228° and 0.262°."""
    path = SITL / name
    rec = recording(path, reference="truth")
    assert rec.reference.source == "SIMSTATE" and rec.reference.kind == "truth"
    ev = evaluate(rec, ["eskf", "eskf:imu_delay=0"])
    assert ev.prepared.imu_delay.source == "ArduPilot default INS_GYRO_FILTER 20 Hz"
    score = ev.scores["eskf"]
    assert score.samples > 0.95 * rec.n
    assert score.total_deg < HEADROOM * total and score.inclination_deg < HEADROOM * inclination
    assert rec.autopilot is not None and rec.autopilot.source == "ATTITUDE"
    assert score.total_deg <= ev.scores["autopilot"].total_deg
    late = ev.scores["eskf:imu_delay=0"]
    assert late.inclination_deg == pytest.approx(undelayed, abs=0.002)
    assert score.inclination_deg < 0.92 * late.inclination_deg  # measured 0.908x, 0.863x


def test_px4_live_session_kept_for_its_inclination():
    """The live PX4 SIH session kept in tests/data/live because the live test failed on
    it (tests/data/live/README.md): the body sat tilted on the ground before lift-off,
    which the drag model read as speed. Replayed with the defaults it now gives
    2.03 / 0.78 (total / inclination) against PX4's own 1.85 / 0.75; before μ was
    estimated in logarithm, 2.10 / 0.93, beyond the live test's 1.2× PX4's inclination."""
    path = Path(__file__).parent / "data" / "live" / "px4_sih_start_heading.tlog"
    rec = recording(path, reference="truth")
    ev = evaluate(rec, ["eskf"])
    assert ev.prepared.aid == "velocity" and ev.prepared.flight.known
    score = ev.scores["eskf"]
    assert score.samples > 0.95 * rec.n
    assert score.total_deg < HEADROOM * 2.03, score.total_deg
    assert score.inclination_deg < HEADROOM * 0.78, score.inclination_deg
    px4 = ev.scores["autopilot"]  # PX4's own attitude against the same truth
    assert score.inclination_deg <= 1.2 * px4.inclination_deg, (score, px4)


#: aided + drag (the defaults) over the better of drag only and aiding only, measured
#: through the replay's evaluate, as here
AIDED_OVER_BEST = {
    "px4_sih/sih_aggressive.tlog": 0.989,
    "px4_sih/sih_box.tlog": 1.004,
    "sitl/px4_sih_touchdown.tlog": 1.002,
    "sitl/px4_sih_dashes.tlog": 1.002,
    "sitl/arducopter_touchdown.tlog": 1.000,
    "sitl/arducopter_circles.tlog": 1.003,
}


@pytest.mark.parametrize("name", sorted(AIDED_OVER_BEST))
def test_aiding_and_the_drag_model_together_are_no_worse_than_either_alone(data_dir, name):
    """Within half a percent of the better of the two alone on every recorded flight
    (the excess over 1 held with 1.5x headroom): once 1.012 on PX4 box, when the
    start-up rest levelled the drag-only runs but not the aided ones."""
    path = (SITL.parent / name) if name.startswith("sitl/") else data_dir / name
    rec = recording(path, reference="truth")
    both = evaluate(rec, ["eskf", "eskf:drag=0"])
    assert both.prepared.aid == "velocity" and both.prepared.flight.known
    drag_only = evaluate(rec, ["eskf"], aid="none").scores["eskf"].total_deg
    aiding_only = both.scores["eskf:drag=0"].total_deg
    ratio = both.scores["eskf"].total_deg / min(drag_only, aiding_only)
    assert ratio <= 1.0 + 1.5 * max(AIDED_OVER_BEST[name] - 1.0, 0.002), ratio
