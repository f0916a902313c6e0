"""``-e vqf``: the published VQF package's online filter as a reference estimator, the
same filter sample for sample, wherever our estimators run (live bridge, replay).

The real ``vqf`` package throughout; the one "not installed" case hides it the way a
missing package looks to Python (None in sys.modules)."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
import vqf
from bridge_support import UdpListener, async_test, running_bridge, stream_emulator
from test_estimator_common import EXPECTED_COUNTS, _messy_sequence

import estimators
from bridge.app.cli import main
from bridge.app.table import render
from estimators import quat as Q
from estimators.registry import reference_names
from estimators.vqf_online import TS_TOLERANCE
from hil import EmulatorConfig
from replay.evaluate import default_specs

G = 9.80665


def _motion(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Turning body with consistent gravity and field (body FRD, NED world)."""
    rng = np.random.default_rng(seed)
    rate = 200.0
    phase = np.array([0.0, 1.0, 2.0])
    w = 0.5 * np.sin(np.outer(np.arange(n) / rate, [0.7, 1.1, 0.4]) + phase)
    q = Q.identity(n)
    for i in range(1, n):
        q[i] = Q.multiply(q[i - 1], Q.from_rotvec(w[i] / rate))
    body = Q.conjugate(q)
    acc = Q.rotate(body, np.array([0.0, 0.0, -G])) + rng.normal(0.0, 0.05, (n, 3))
    mag = Q.rotate(body, np.array([0.2, 0.0, 0.45])) + rng.normal(0.0, 0.005, (n, 3))
    return w + rng.normal(0.0, 0.005, (n, 3)), acc, mag


def _by_hand(gyr, acc, mag, ts: float) -> np.ndarray:
    """vqf.VQF itself, body -> NED (its ENU re-expressed)."""
    out = vqf.VQF(ts).updateBatch(np.ascontiguousarray(gyr), np.ascontiguousarray(acc),
                                  None if mag is None else np.ascontiguousarray(mag))
    return Q.enu_to_ned(out["quat9D" if mag is not None else "quat6D"])


@pytest.mark.parametrize("with_mag", [True, False])
def test_it_is_vqf_sample_for_sample(with_mag):
    gyr, acc, mag = _motion(2000)
    m = mag if with_mag else None
    est = estimators.create("vqf", rate_hz=200.0)
    live = np.array([est.update(gyr[i], acc[i], None if m is None else m[i], 0.005)
                     for i in range(len(gyr))])
    assert np.degrees(Q.angle_between(live, _by_hand(gyr, acc, m, 0.005))).max() < 1e-9
    batch = estimators.create("vqf", rate_hz=200.0).run(gyr, acc, m, 0.005)
    assert np.array_equal(batch.q, live)


def test_declination_and_world_frame_turn_the_output_like_ours():
    gyr, acc, mag = _motion(800)
    ned = estimators.create("vqf", rate_hz=200.0).run(gyr, acc, mag, 0.005).q
    decl = math.radians(3.5)
    turned = estimators.create("vqf", rate_hz=200.0, declination=decl).run(
        gyr, acc, mag, 0.005).q
    about_down = Q.from_axis_angle(np.array([0.0, 0.0, 1.0]), np.array(decl))
    assert np.degrees(Q.angle_between(turned, Q.multiply(about_down, ned))).max() < 1e-9
    enu = estimators.create("vqf", rate_hz=200.0, world="ENU").run(gyr, acc, mag, 0.005).q
    assert np.degrees(Q.angle_between(enu, Q.ned_to_enu(ned))).max() < 1e-9
    moved = estimators.create("vqf", rate_hz=200.0)
    moved.run(gyr[:400], acc[:400], mag[:400], 0.005)
    moved.set_declination(decl)  # live: a declination learned later turns the output
    rest = moved.run(gyr[400:], acc[400:], mag[400:], 0.005).q
    assert np.degrees(Q.angle_between(rest, turned[400:])).max() < 1e-9


def test_uneven_steps_integrate_each_samples_own_rotation():
    """ArduPilot's RAW_IMU comes in 2.5 ms / 5 ms steps, PX4's at whatever rate it was
    asked for: VQF runs at one fixed sample time, so each sample's rotation is scaled
    to its own step. A level body turning at 0.5 rad/s for 600 samples of alternating
    steps has turned 0.5 rad/s times their sum, although the nominal rate is 1 kHz (a
    second: before VQF's rest detection could take the steady turn for a bias)."""
    n = 300
    dts = np.where(np.arange(n) % 2 == 0, 0.0025, 0.005)
    gyr = np.tile([0.0, 0.0, 0.5], (n, 1))
    acc = np.tile([0.0, 0.0, -G], (n, 1))
    est = estimators.create("vqf", rate_hz=1000.0)
    q = est.run(gyr, acc, None, dts).q
    turned = Q.to_euler(Q.multiply(Q.conjugate(q[0]), q[-1]))[2]
    assert abs(turned - 0.5 * dts[1:].sum()) < 1e-9  # (q[0] has the first step's turn)
    # and its sample time follows the stream's mean step (3.75 ms), not the nominal 1 ms
    longer = estimators.create("vqf", rate_hz=1000.0)
    longer.run(np.tile(gyr, (5, 1)), np.tile(acc, (5, 1)), None, np.tile(dts, 5))
    assert abs(longer.sample_time - 0.00375) <= TS_TOLERANCE * 0.00375


def test_bad_samples_are_counted_as_ours_are():
    data = _messy_sequence()
    est = estimators.create("vqf", rate_hz=400.0)
    out = est.run(data["gyr"], data["acc"], data["mag"], data["dt"])
    counters = est.counters
    for name, expected in EXPECTED_COUNTS.items():
        assert getattr(counters, name) == expected, name
    assert np.all(np.isfinite(out.q))
    assert out.skipped.sum() == EXPECTED_COUNTS["skipped"]
    one = estimators.create("vqf", rate_hz=400.0)
    each = np.array([one.update(data["gyr"][i], data["acc"][i], data["mag"][i],
                                data["dt"][i]) for i in range(len(data["dt"]))])
    assert np.array_equal(each, out.q)


def test_a_reference_runs_only_when_named():
    assert "vqf" in reference_names() and "vqf" not in estimators.names()
    assert "vqf" not in [s.name for s in default_specs()]
    with pytest.raises(ValueError, match="takes no q0"):
        estimators.create("vqf", q0=np.array([1.0, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="tau_acc"):
        estimators.create("vqf", tau_acc=-1.0)


def test_without_the_package_it_is_one_line_before_any_work(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "vqf", None)  # what an uninstalled package looks like
    with pytest.raises(ValueError, match=r"pip install 'attitude-bridge\[compare\]'"):
        estimators.create("vqf")
    assert main(["run", "-e", "eskf", "-e", "vqf", "--duration", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "needs the vqf package" in err


@async_test
async def test_live_beside_eskf_on_the_same_samples():
    """`run -e eskf -e vqf`: VQF gets every sample eskf gets, and is scored against the
    truth and the vehicle in the status and the live table like any estimator; eskf
    stays the primary."""
    cfg = EmulatorConfig(profile="flight", duration_s=12.0, seed=4, fast=True)
    listener = UdpListener()
    out_port = await listener.start()
    async with running_bridge(estimators=["eskf", "vqf"], out_rate=50.0,
                              imu_rate=cfg.imu_rate_hz, max_source_rate=1e7) as bridge:
        await stream_emulator(bridge, cfg, out_port)
        bridge.publish_status()
        status = bridge.last_status[cfg.sysid]
        table = render(bridge)
    listener.close()
    counters = status["estimator_counters"]
    assert counters["vqf"]["samples"] == counters["eskf"]["samples"] > 2000
    for ref in ("truth", "vehicle"):
        row = status["compare"][ref]["vqf"]
        assert row["samples"] > 100 and math.isfinite(row["total_deg"])
    assert bridge.pipeline.primary_label == "eskf"
    assert any(line.split()[1:2] == ["vqf"] for line in table.splitlines() if line.strip())
