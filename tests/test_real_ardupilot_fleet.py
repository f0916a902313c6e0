"""Two real ArduPilot Copter SITL instances into one bridge port, one of them restarting.

Both send their onboard link to the same UDP port; the bridge, told to serve both
(``--vehicle 1 --vehicle 2``: by default it serves the first autopilot it hears), tells
them apart by system id, answers each at its own address, asks each for 400 Hz RAW_IMU — which
ArduPilot denies (its limit is 1.25 main-loop periods, in whole milliseconds) — and
must settle at the next interval it allows (3 ms: 333 Hz). Each takes its declination
from its own COMPASS_DEC. Then vehicle 2 is killed and started again (its parameters
kept, its stream intervals forgotten, its clock back at zero): the bridge, still
running, must notice, ask again and estimate it again, while vehicle 1 goes on.
"""

from __future__ import annotations

import math
import time

import pytest
from sitl_support import BridgeProcess, stop_all

from hil.sitl import Sitl, free_udp_port

pytestmark = pytest.mark.xdist_group("autopilots")

DECLINATION_RAD = {1: 0.3, 2: -0.2}  # COMPASS_DEC, set with COMPASS_AUTODEC off


def _vehicle(api: int, sysid: int) -> Sitl:
    return Sitl("ardupilot", {"AP_GCS_PORT": str(free_udp_port()), "AP_API_PORT": str(api),
                              "AP_PARAM_MAV_SYSID": str(sysid),  # (SYSID_THISMAV before 4.7)
                              "AP_PARAM_SERIAL2_PROTOCOL": "-1",  # no TCP port of its own
                              "AP_PARAM_COMPASS_AUTODEC": "0",
                              "AP_PARAM_COMPASS_DEC": str(DECLINATION_RAD[sysid])})


def _estimating(st: dict, sysid: int, rate_hz: float) -> bool:
    v = st.get("vehicles", {}).get(str(sysid), {})
    achieved = v.get("imu_stream", {}).get("achieved_hz")
    return bool(v.get("online") and v.get("compare", {}).get("truth") and achieved
                and abs(achieved - rate_hz) < 0.03 * rate_hz)


def test_two_vehicles_one_port_and_a_restart(tmp_path):
    api = free_udp_port()
    sitls = {1: _vehicle(api, 1), 2: _vehicle(api, 2)}
    bridge = BridgeProcess.start(tmp_path, f"udpin:127.0.0.1:{api}", "--vehicle", "1",
                                 "--vehicle", "2", "--imu-rate", "400")
    try:
        for s in sitls.values():
            s.start()
        st = bridge.wait_for(lambda st: _estimating(st, 1, 333.3) and _estimating(st, 2, 333.3),
                             20, "both vehicles estimating at 333 Hz")
        before = {k: st["vehicles"][str(k)]["samples"] for k in (1, 2)}
        for k in (1, 2):
            v = st["vehicles"][str(k)]
            stream = v["imu_stream"]
            assert stream["refused"][0] == "RAW_IMU at 400 Hz: MAV_RESULT_DENIED", stream
            assert stream["asked_hz"] == pytest.approx(1000 / 3, abs=0.01), stream
            assert v["declination"]["source"] == "parameter", v["declination"]
            assert v["declination"]["deg"] == pytest.approx(math.degrees(DECLINATION_RAD[k]),
                                                            abs=0.01)
            assert v["imu_delay"] == {"ms": 11.25, "source": "INS_GYRO_FILTER 20 Hz"}
        # an autopilot that has run a while (a fresh SITL restarted within seconds
        # repeats its own stamps and readings: indistinguishable from an outage)
        bridge.wait_for(lambda st: st["vehicles"]["2"]["time_s"] > 8.0, 10, "8 s of uptime")
        sitls[2].kill()
        st = bridge.wait_for(lambda st: not st["vehicles"]["2"]["online"], 10,
                             "vehicle 2 offline")
        sitls[2].start(fresh=False)
        t_restart = time.monotonic()
        st = bridge.wait_for(lambda st: st["vehicles"]["2"]["samples"] > before[2] + 1000
                             and _estimating(st, 2, 333.3), 20,
                             "vehicle 2 estimating again")
        recovered_s = time.monotonic() - t_restart
    finally:
        stop_all(*sitls.values())
        code = bridge.stop()
    log = bridge.log()
    assert code == 0, log[-2000:]
    assert "denied RAW_IMU at 400 Hz (too fast for its main loop); asking for 333.3 Hz" in log
    assert "vehicle 2: no IMU data" in log  # the outage is a warning
    assert "vehicle 2 rebooted" in log, log[-3000:]
    v1, v2 = st["vehicles"]["1"], st["vehicles"]["2"]
    assert v1["samples"] > before[1] + 333 * 5 and v1["restarts"] == 0  # went on meanwhile
    assert v2["restarts"] >= 1
    assert v2["declination"]["source"] == "parameter"
    print(f"vehicle 2 estimating again {recovered_s:.1f} s after its restart")
