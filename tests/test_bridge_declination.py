"""The magnetic declination without flags: from the autopilot's parameter or the World
Magnetic Model at the vehicle's position, over real UDP against the emulator."""

from __future__ import annotations

import asyncio
import logging
import math

import numpy as np
import pytest
from bridge_support import UdpListener, async_test, running_bridge, wait_until

import estimators
from bridge.app.config import BridgeConfig
from bridge.app.emulator import emulator_config, emulator_declination_deg
from bridge.app.table import render
from bridge.vehicle.declination import (
    CONFIRM_FIXES,
    NONE,
    OPTION,
    PARAMETER,
    REREAD_S,
    WMM,
    Declination,
)
from bridge.wire.mav import mavlink
from estimators import metrics
from estimators import quat as Q
from hil import Emulator, EmulatorConfig, GpsConfig, simulate

DURATION_S = 14.0


async def fly(autopilot: str, gps: bool, **settings):
    """A `flight` through the bridge; (heading and total RMS of the output against the
    truth after 8 s, final status, the rendered table, {time_boot_ms: output})."""
    listener = UdpListener()
    port = await listener.start()
    cfg = EmulatorConfig(profile="flight", duration_s=DURATION_S, seed=4, fast=True,
                         rate_hz=250.0, autopilot=autopilot,
                         gps=GpsConfig() if gps else None)
    async with running_bridge(estimators=["eskf"], imu_rate=250.0, max_source_rate=1e7,
                              outs=[f"udpout:127.0.0.1:{port}"], **settings) as bridge:
        stats = await Emulator(cfg).run(targets=[("127.0.0.1", bridge.port),
                                                 ("127.0.0.1", port)])
        n = stats.messages[bridge.vehicles[1].negotiation.message]
        await wait_until(lambda: sum(s.accepted for s in bridge.ingest.sources.values())
                         >= 0.8 * n, timeout=10.0)
        await asyncio.sleep(0.3)
        bridge.publish_status()
        status, table = bridge.last_status[1], render(bridge)
    listener.close()
    out, truth = listener.outputs_with_truth()
    stamps = np.array([m.time_boot_ms for m in out])
    late = stamps >= stamps[0] + 8000
    est = np.array([[m.q1, m.q2, m.q3, m.q4] for m in out])[late]
    ref = np.array([truth[t] for t in stamps[late]])
    err = metrics.rms_errors(est, ref)
    by_ms = {m.time_boot_ms: np.array([m.q1, m.q2, m.q3, m.q4]) for m in out}
    return err, status, table, by_ms


def apart_deg(a: dict, b: dict, after_ms: int = 1000) -> np.ndarray:
    """Angle between two runs' outputs at the same stamps (after the first second)."""
    common = sorted(set(a) & set(b))
    common = [t for t in common if t >= common[0] + after_ms]
    return np.degrees(Q.angle_between(np.array([a[t] for t in common]),
                                      np.array([b[t] for t in common])))


@async_test
async def test_declination_from_the_position_reaches_the_estimate():
    # Truth is refused as a source of anything (another sender is named), so the
    # position can only come from the GPS messages.
    auto, status, table, q_auto = await fly("stm32", gps=True, truth_source="1:99")
    right, _, _, q_right = await fly("stm32", gps=True, truth_source="1:99",
                                     declination_deg=emulator_declination_deg())
    d = status["declination"]
    assert d["source"] == WMM and d["detail"].startswith("WMM2025 at 47.39")
    # Today's WMM at the GPS position against the emulator's field on its fixed date.
    assert d["deg"] == pytest.approx(emulator_declination_deg(), abs=0.3)
    assert abs(auto.heading_deg - right.heading_deg) <= 0.5, (auto, right)
    assert np.max(apart_deg(q_auto, q_right)) < 0.5
    assert "(wmm: WMM2025 at 47.39" in table


@async_test
async def test_declination_from_the_px4_parameter_reaches_the_estimate():
    auto, status, table, q_auto = await fly("px4", gps=False)
    right, _, _, q_right = await fly("px4", gps=False,
                                     declination_deg=emulator_declination_deg())
    d = status["declination"]
    assert d["source"] == PARAMETER and d["detail"] == "EKF2_MAG_DECL"
    assert d["deg"] == pytest.approx(emulator_declination_deg(), abs=1e-3)  # float32, 3 dp
    assert abs(auto.heading_deg - right.heading_deg) <= 0.5, (auto, right)
    # The parameter came within the first samples and turned the output in place: from
    # then on the same estimate as with the flag (a late parameter would leave the two
    # runs the whole declination, ~3°, apart). In fast mode the board time at which the
    # emulated PX4 switches HIGHRES_IMU to the asked rate depends on how quickly the
    # request crossed the socket, so the two runs' first seconds may see slightly
    # different streams: measured identical (< 1e-6°) in 2 of 3 runs, 0.02-0.04° apart
    # in the third, the gap fading as both converge...
    assert np.max(apart_deg(q_auto, q_right)) < 0.1
    # ...which is the declination away from the one without any.
    _, _, _, q_none = await fly("px4", gps=False, declination_deg=0.0)
    assert np.median(apart_deg(q_none, q_right)) == pytest.approx(
        emulator_declination_deg(), abs=0.05)
    # The PX4 personality's own attitude (ATTITUDE_QUATERNION) is scored against the
    # truth and shown next to the estimators (its error and lag), and each estimator
    # against it (the VEHICLE columns).
    own = status["vehicle_vs_truth"]
    # (measured 7.9°: the emulated autopilot's own filter on an uncalibrated board; 1.5x)
    assert own is not None and own["samples"] > 100 and 0.0 < own["total_deg"] < 11.8
    # Its lag: a number, or why there is none (beyond the search, reference static).
    assert (own["lag_s"] is not None and math.isfinite(own["lag_s"])) or own["lag_note"]
    vs_vehicle = status["compare"]["vehicle"]["eskf"]
    assert vs_vehicle["samples"] > 100 and np.isfinite(vs_vehicle["total_deg"])
    assert "(vehicle own)" in table and "PX4 quadrotor" in table


def test_declination_sources_in_order():
    px4, ardupilot = mavlink.MAV_AUTOPILOT_PX4, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    d = Declination(1)
    assert (d.source, d.deg) == (NONE, 0.0)
    d.plan(ardupilot)
    assert d.param_to_send(0.0) == "COMPASS_DEC"
    assert d.param_to_send(0.5) is None  # waiting for the answer
    for _ in range(CONFIRM_FIXES - 1):  # a place counts once fixes in a row agree on it
        assert not d.on_position(47.397742, 8.545594, 488.0) and d.source == NONE
    assert d.on_position(47.397742, 8.545594, 488.0) and d.source == WMM
    assert not d.on_position(47.3978, 8.5457, 490.0)  # same place: not evaluated again
    assert d.on_param("COMPASS_DEC", math.radians(2.5), 1.0, True)  # radians, and it wins
    assert (d.source, d.deg) == (PARAMETER, pytest.approx(2.5))
    assert not d.on_position(-33.9, 151.2, 0.0)  # the parameter stays
    assert d.param_to_send(5.0) is None  # answered
    p = Declination(2)
    p.plan(px4)
    assert not p.on_param("EKF2_MAG_DECL", 0.0, 0.0, False)  # PX4's default before it set it
    assert not p.on_position(0.0, 0.0, 0.0) and p.source == NONE  # the "no fix" place
    assert not p.on_param("EKF2_MAG_DECL", float("nan"), 0.0, False)
    given = Declination(3, option_deg=-7.0)
    given.plan(px4)
    assert given.param_to_send(0.0) is None  # the user's value needs no question
    assert not given.on_position(47.4, 8.5, 0.0) and (given.source, given.deg) == (OPTION, -7.0)


def test_a_parameter_not_set_yet_is_asked_again_until_the_autopilot_sets_it(caplog):
    """ArduPilot's COMPASS_DEC reads 0 until its GPS has a position, and it sets the
    value without a PARAM_VALUE: asked again every REREAD_S, its own value replaces
    the World Magnetic Model's before the flight, not only at the next disarm."""
    d = Declination(1)
    d.plan(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    assert d.param_to_send(0.0) == "COMPASS_DEC"
    with caplog.at_level(logging.INFO, logger="bridge.vehicle.declination"):
        assert not d.on_param("COMPASS_DEC", 0.0, 0.1, True)  # even in the air
        for _ in range(CONFIRM_FIXES):
            d.on_position(-35.3632, 149.1652, 584.0)
        assert d.source == WMM
        assert d.param_to_send(0.1 + REREAD_S - 0.5) is None  # not yet
        assert d.param_to_send(0.1 + REREAD_S) == "COMPASS_DEC"
        assert not d.on_param("COMPASS_DEC", 0.0, 10.2, True)  # still not set: later again
        assert d.param_to_send(10.2 + REREAD_S) == "COMPASS_DEC"
    assert caplog.text.count("not set by the autopilot yet") == 1  # said once
    assert d.on_param("COMPASS_DEC", 0.2233572, 20.3, True)
    assert (d.source, d.deg) == (PARAMETER, pytest.approx(12.797, abs=1e-3))
    assert d.param_to_send(100.0) is None  # set, and flying: no more asking
    assert d.param_to_send(20.4) is None
    # the autopilot restarts with its parameters reset: said again, the value kept (the
    # vehicle has not moved) until it sets it again
    d.plan(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    with caplog.at_level(logging.INFO, logger="bridge.vehicle.declination"):
        assert not d.on_param("COMPASS_DEC", 0.0, 200.0, False)
    assert caplog.text.count("not set by the autopilot yet") == 2
    assert (d.source, d.deg) == (PARAMETER, pytest.approx(12.797, abs=1e-3))


def test_a_disarmed_vehicles_parameter_is_read_again_until_it_arms():
    """PX4 fills EKF2_MAG_DECL from its own tables once it has a position and saves it
    without a PARAM_VALUE (a value saved by an earlier flight, 3.70°, becomes 3.41°
    on the ground): re-read while disarmed, the flight starts with PX4's value."""
    d = Declination(2)
    d.plan(mavlink.MAV_AUTOPILOT_PX4)
    assert d.param_to_send(0.0) == "EKF2_MAG_DECL"
    assert d.on_param("EKF2_MAG_DECL", 3.70, 0.1, False)
    assert d.param_to_send(0.1 + REREAD_S - 0.5) is None
    assert d.param_to_send(0.1 + REREAD_S) == "EKF2_MAG_DECL"
    assert d.query.routine  # a re-read: logged at debug (bridge.app.requests)
    assert d.on_param("EKF2_MAG_DECL", 3.41, 10.2, False)
    assert (d.source, d.deg) == (PARAMETER, pytest.approx(3.41))
    assert d.param_to_send(10.2 + REREAD_S) == "EKF2_MAG_DECL"  # still on the ground
    assert not d.on_param("EKF2_MAG_DECL", 3.41, 20.3, True)  # armed: unchanged, and...
    assert d.param_to_send(1000.0) is None  # ...not asked again in the air
    d.plan(mavlink.MAV_AUTOPILOT_PX4)  # the disarm (bridge.app.routing) asks at once
    assert d.param_to_send(1000.0) == "EKF2_MAG_DECL" and not d.query.routine


def test_a_position_flipping_between_two_places_never_moves_the_declination(caplog):
    """A faulty receiver alternating between Zurich and New Zealand turned the heading
    by 22° with every fix; and a flood of one bad parameter value logged one warning
    per message."""
    caplog.set_level(logging.WARNING, logger="bridge")
    d = Declination(1)
    d.plan(mavlink.MAV_AUTOPILOT_PX4)
    for _ in range(CONFIRM_FIXES):
        d.on_position(47.397742, 8.545594, 488.0)
    zurich = d.deg
    assert d.source == WMM
    changes = sum(d.on_position(*((-45.0, 170.0) if k % 2 else (47.397742, 8.545594)), 0.0)
                  for k in range(200))
    assert changes == 0 and d.deg == zurich
    for _ in range(CONFIRM_FIXES):  # a real move is taken
        d.on_position(-45.0, 170.0, 0.0)
    assert d.deg == pytest.approx(25.5, abs=1.0)
    for _ in range(1000):
        assert not d.on_param("EKF2_MAG_DECL", float("nan"), 0.0, None)
    assert d.params_refused == 1000 and d.status()["params_refused"] == 1000
    assert len([r for r in caplog.records if "is no declination" in r.getMessage()]) == 1


def test_set_declination_turns_the_output_and_keeps_the_estimate():
    rec = simulate(EmulatorConfig(profile="flight", duration_s=8.0, seed=1, rate_hz=250.0,
                                  gps=GpsConfig()))
    vel, age = rec.gps_aiding()
    true_decl = math.radians(3.5)
    ref = estimators.create("eskf", rate_hz=250.0, declination=true_decl, drag=0.5)
    late = estimators.create("eskf", rate_hz=250.0, drag=0.5)
    for k in range(len(rec)):
        if k == 10:  # learned 40 ms in, before the first GPS fix (sent at 0.1 s)
            late.set_declination(true_decl)
        v = vel[k] if np.all(np.isfinite(vel[k])) else None
        a = ref.update(rec.gyr[k], rec.acc[k], rec.mag[k], vel=v, vel_age=age[k])
        b = late.update(rec.gyr[k], rec.acc[k], rec.mag[k], vel=v, vel_age=age[k])
        if k >= 10:
            np.testing.assert_allclose(a, b, atol=1e-12)
    with pytest.raises(ValueError):
        late.set_declination(math.inf)


def test_built_in_emulator_follows_the_bridge_settings():
    cfg = BridgeConfig(emulator_autopilot="px4", emulator_gps=True)
    cfg.validate()
    ecfg = emulator_config(cfg, 5.0)
    assert ecfg.autopilot == "px4" and ecfg.gps == GpsConfig()
    assert ecfg.imu_message == "HIGHRES_IMU"  # PX4 starts with its own stream
    with pytest.raises(ValueError, match="emulator autopilot"):
        BridgeConfig(emulator_autopilot="betaflight").validate()


def test_declination_options_are_degrees_under_both_names():
    from bridge.app.cli import build_parser
    from bridge.app.run_cli import config_from_args

    for flag in ("--declination-deg", "--declination"):
        args = build_parser().parse_args(["run", "--connect", "udpin:127.0.0.1:0", flag, "-4.5",
                                          "--emulator-autopilot", "ardupilot",
                                          "--emulator-gps", "--no-aiding"])
        cfg = config_from_args(args, demo=False)
        assert cfg.declination_deg == -4.5 and cfg.aiding is False
        assert (cfg.emulator_autopilot, cfg.emulator_gps) == ("ardupilot", True)


@async_test
async def test_ardupilot_gyro_filter_parameter_is_read_with_the_declination():
    """The ArduPilot personality answers COMPASS_DEC and INS_GYRO_FILTER (0: it sends
    its samples as measured), so the estimate is not carried forward by ArduPilot's
    default 11.25 ms (imu.filter_delay), and is as good as the same flight from the
    stm32 board, which has no filter to ask about."""
    ap, status, _, _ = await fly("ardupilot", gps=False)
    assert status["declination"]["detail"] == "COMPASS_DEC"
    assert status["imu_delay"] == {"ms": 0.0, "source": "INS_GYRO_FILTER 0 (filter off)"}
    board, plain, _, _ = await fly("stm32", gps=False,
                                   declination_deg=emulator_declination_deg())
    assert plain["imu_delay"] == {"ms": 0.0, "source": "none"}
    assert abs(ap.total_deg - board.total_deg) < 0.2, (ap, board)
