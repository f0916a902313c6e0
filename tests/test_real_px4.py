"""The bridge against a real PX4 (SITL, SIH quadrotor, ../shared/autopilots), default flags.

A flight: the bridge listens on PX4's onboard link (it sends to 14540+N) while a ground
station on PX4's GCS link takes off, flies offboard velocity legs and lands. The bridge
must negotiate HIGHRES_IMU, take the declination from PX4's own parameter, aid from
LOCAL_POSITION_NED, follow the landed state, compare live with PX4's attitude and the
simulator's truth (HIL_STATE_QUATERNION, whose stamps are 0: placed by arrival), and
send an attitude PX4 forwards to its GCS link; over the armed span (take-off, flight,
landing) its estimate must be about as good as PX4's own attitude or better (it is
better in 13 flights of 14; see TOTAL_VS_PX4).
"""

from __future__ import annotations

import pytest
from sitl_support import (
    BRIDGE_COMPID,
    INCLINATION_VS_AUTOPILOT,
    TOTAL_VS_PX4,
    BridgeProcess,
    armed_span_scores,
    check_flight_state_and_references,
    check_live_session_matches_replay,
    landed_and_disarmed,
    read_param,
    replayed_beside_vqf,
    stop_all,
)

from hil.sitl import Leg, Link, Sitl, px4_instance
from hil.sitl_pilot import px4_land, px4_offboard, px4_ready, px4_takeoff, set_rates

pytestmark = pytest.mark.xdist_group("autopilots")

LEGS = [Leg(3, 6, 0), Leg(3, 6, 180, yaw=40), Leg(3, 5, 90, turn=60), Leg(2)]
TAKEOFF_M = 2.5  # PX4's default take-off altitude
#: EKF2_MAG_DECL saved from elsewhere (a fresh PX4 has 0, which the bridge does not
#: take as a value); PX4 replaces it on the ground with its own table's value at SIH's
#: home (Zurich, 3.41°) without a PARAM_VALUE, and the bridge must follow
SAVED_DECLINATION_DEG = 3.7


def test_px4_flight_through_the_bridge(tmp_path):
    bridge = pilot = sitl = None
    with px4_instance() as n:
        sysid = n + 1
        try:
            bridge = BridgeProcess.start(tmp_path, f"udpin:127.0.0.1:{14540 + n}")
            sitl = Sitl("px4", {"PX4_INSTANCE": str(n),
                                "PX4_PARAM_EKF2_MAG_DECL": str(SAVED_DECLINATION_DEG)})
            sitl.start()
            pilot = Link(18570 + n, keep=set(), listen=False)  # PX4's GCS link
            pilot.wait_heartbeat()
            set_rates(pilot, {"EXTENDED_SYS_STATE": 5.0, "GPS_RAW_INT": 5.0,
                              "GLOBAL_POSITION_INT": 5.0, "LOCAL_POSITION_NED": 10.0})
            px4_ready(pilot, settle_s=3.0)
            bridge.wait_for(lambda st: st["vehicles"].get(str(sysid), {}).get("compare", {})
                            .get("truth"), 10, "a comparison with the truth")
            px4_takeoff(pilot, TAKEOFF_M)
            in_air = bridge.wait_for(
                lambda st: st["vehicles"][str(sysid)]["flight_state"].get("armed") is True,
                5, "the armed vehicle")["vehicles"][str(sysid)]["declination"]
            px4_offboard(pilot, LEGS, TAKEOFF_M)
            px4_land(pilot)
            bridge.wait_for(lambda st: landed_and_disarmed(st, str(sysid)), 10, "the landing")
            # PX4 saves the declination its EKF learned when it disarms, and announces
            # the new value: the bridge follows the parameter
            decl = read_param(pilot, "EKF2_MAG_DECL")
            assert decl is not None and decl != 0.0
            st = bridge.wait_for(lambda st: abs(st["vehicles"][str(sysid)]["declination"]
                                                ["deg"] - decl) < 0.01, 5,
                                 f"the declination PX4 has now ({decl:.3f}°)"
                                 )["vehicles"][str(sysid)]
        except Exception:
            print("PX4 said:", *(t for _, t in pilot.statustext[-10:]) if pilot else (), sep="\n  ")
            raise
        finally:
            stop_all(pilot, sitl)
            code = bridge.stop() if bridge is not None else None
    log = bridge.log()
    assert code == 0, log[-2000:]

    imu = st["imu_stream"]
    assert (imu["message"], imu["state"]) == ("HIGHRES_IMU", "accepted"), imu
    # PX4 integrates its IMU at 400 Hz here and streams whole samples: asked 250 Hz it
    # sends every second one, and the bridge says so
    assert imu["achieved_hz"] == pytest.approx(200.0, rel=0.03), imu
    assert imu["below_request"] and "below the 250 Hz asked" in log
    # the declination from PX4's own parameter (as set at start, or as PX4 saved it)
    assert st["declination"]["source"] == "parameter", st["declination"]
    # PX4 replaced the value set at start (SAVED_DECLINATION_DEG) with its own on the
    # ground, without a PARAM_VALUE; re-read on the ground and as it armed, the bridge
    # flew with PX4's value (the one it saved at disarm too)
    assert in_air["source"] == "parameter" and in_air["deg"] == pytest.approx(decl, abs=0.05)
    assert "EKF2_MAG_DECL" in log
    assert st["aiding"]["source"] == "LOCAL_POSITION_NED" and st["aiding"]["used"] > 200
    # SIH's magnetometer is not calibrated (CAL_MAG0_*OFF are 0) and its raw field agrees
    # with HIGHRES_IMU's: the bridge uses the raw one, without PX4's bias estimate
    mag = st["px4_magnetometer"]
    assert st["imu_stream"]["raw_mag_stream"] == "MAV_RESULT_ACCEPTED"
    assert mag["state"] == "raw" and mag["source"] == "SCALED_IMU", mag
    assert mag["parameters"] == {"CAL_MAG0_XOFF": 0.0, "CAL_MAG0_YOFF": 0.0,
                                 "CAL_MAG0_ZOFF": 0.0}, mag
    # (from the first window of 5 s on, once the parameters are in)
    assert mag["replaced"] > 0.7 * st["samples"] and mag["difference_pct"] < 15.0, mag
    check_flight_state_and_references(st, "HIL_STATE_QUATERNION")
    # PX4 forwards the bridge's attitude from its onboard link to its GCS link
    assert pilot.seen_from[("ATTITUDE_QUATERNION", BRIDGE_COMPID)] > 100, pilot.seen_from

    ours, theirs = armed_span_scores(bridge.record, sysid, "PX4")
    assert ours.total_deg <= TOTAL_VS_PX4 * theirs.total_deg
    # inclination alone: comparable, not always better (README, "With a real autopilot":
    # 0.88-1.05x of PX4's own over 18 flights with the current defaults, 1.07x with
    # earlier ones and the whole suite running beside it, docs/accuracy.md "Live flights")
    assert ours.inclination_deg <= INCLINATION_VS_AUTOPILOT * theirs.inclination_deg
    # README: 0.88-1.49° with the defaults now (twelve flights; PX4's own 1.73-4.03°),
    # the total following SIH's magnetometer, whose field PX4's EKF2 turns differently
    # in every run
    assert ours.total_deg <= 1.8
    assert ours.inclination_deg <= 1.2  # README: 0.62-0.89° (every live flight 0.60-1.01°)
    # the same samples replayed beside VQF: eskf online better than VQF online in total
    # and inclination, and than VQF offline in inclination; offline against offline, the
    # eskf smoothed better than VQF offline in both (online, the heading of a filter that
    # sees the whole flight can be better than ours: 2.15 against 2.31° once in four)
    # replayed with the declination the bridge had in the air (a plain replay takes the
    # record's last value, the one PX4 saved at disarm, for the whole session)
    replayed = replayed_beside_vqf(bridge.record, "PX4", in_air["deg"])
    # the live comparison's whole-session numbers are the replay's (sitl_support)
    check_live_session_matches_replay(bridge.vehicle(sysid), replayed)
    online, smoothed = replayed["eskf"], replayed["eskf smoothed"]
    vqf_online, vqf_offline = replayed["vqf online"], replayed["vqf offline"]
    assert online.total_deg < vqf_online.total_deg, replayed
    assert online.inclination_deg < vqf_online.inclination_deg, replayed
    assert online.inclination_deg < vqf_offline.inclination_deg, replayed
    assert smoothed.total_deg < vqf_offline.total_deg, replayed
    assert smoothed.inclination_deg < vqf_offline.inclination_deg, replayed
    # 0.68-0.82° in the last eight runs (the total follows SIH's magnetometer, as above: held
    # against VQF's, not absolutely)
    assert replayed["eskf"].inclination_deg <= 1.1

