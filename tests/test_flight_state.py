"""The flight-state policy (imu.flight_state) and the replay's use of it (replay.flight).

The rotor-drag model holds only while a multirotor flies; these tests check that the
vehicle's own reports decide, that a broken or foreign report never switches the model
per message, and that a recording's phases are found from those reports.
"""

from __future__ import annotations

import logging
import os
import struct
from pathlib import Path

import numpy as np
import pytest
from recordings import recording

from imu import flight_state as fs
from replay.dataset import ReplayInputError
from replay.flight import PHASES, track
from replay.readers import load
from replay.readers.ulog import _state_events as ulog_state_events

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink

SITL = Path(__file__).parent / "data" / "sitl"
PX4, GENERIC = fs.MAV_AUTOPILOT_PX4, 0
ARMED = fs.MAV_MODE_FLAG_SAFETY_ARMED


# --- the tracker -----------------------------------------------------------------------------
def test_disarmed_is_on_the_ground_whatever_the_landed_state_says():
    tr = fs.FlightStateTracker()
    tr.on_heartbeat(0.0, 0, PX4)
    for k in range(3):
        tr.on_extended_sys_state(1.0 + k, fs.LANDED_IN_AIR)
    assert tr.airborne is False and tr.source == fs.SOURCE_ARMED


def test_armed_and_in_air_is_airborne_and_every_switch_is_listed():
    tr = fs.FlightStateTracker()
    tr.on_heartbeat(0.0, ARMED, PX4)
    tr.on_extended_sys_state(0.1, fs.LANDED_ON_GROUND)
    assert tr.airborne is False and tr.source == fs.SOURCE_LANDED
    tr.on_extended_sys_state(1.0, fs.LANDED_TAKEOFF)
    assert tr.airborne is False, "one report is not enough to switch"
    tr.on_extended_sys_state(1.2, fs.LANDED_TAKEOFF)
    assert tr.airborne is True
    tr.on_extended_sys_state(5.0, fs.LANDED_IN_AIR)
    tr.on_extended_sys_state(5.2, fs.LANDED_IN_AIR)
    tr.on_extended_sys_state(9.0, fs.LANDED_ON_GROUND)
    tr.on_extended_sys_state(9.2, fs.LANDED_ON_GROUND)
    assert [(s.t, s.airborne) for s in tr.switches] == [(0.1, False), (1.2, True), (9.2, False)]
    assert tr.status()["state"] == "on ground" and tr.status()["switches"] == 3


def test_a_bare_board_that_never_arms_leaves_the_decision_to_the_data():
    tr = fs.FlightStateTracker()
    for k in range(5):
        tr.on_heartbeat(float(k), 0, GENERIC)
    assert tr.airborne is None and tr.source == fs.SOURCE_DATA
    tr.on_heartbeat(5.0, ARMED, GENERIC)  # once seen armed, its flag is believed
    tr.on_heartbeat(6.0, 0, GENERIC)
    assert tr.airborne is False


def test_armed_without_landed_state_is_unknown():
    tr = fs.FlightStateTracker()
    tr.on_heartbeat(0.0, ARMED, PX4)
    assert tr.airborne is None and tr.source == fs.SOURCE_DATA


def test_a_landed_state_flipping_every_message_never_switches_and_falls_back(caplog):
    tr = fs.FlightStateTracker(label="vehicle 1")
    tr.on_heartbeat(0.0, ARMED, PX4)
    tr.on_extended_sys_state(0.0, fs.LANDED_ON_GROUND)
    states = []
    with caplog.at_level(logging.WARNING, logger="imu.flight_state"):
        for k in range(1, 40):
            report = fs.LANDED_IN_AIR if k % 2 else fs.LANDED_ON_GROUND
            tr.on_extended_sys_state(0.1 * k, report)
            states.append(tr.airborne)
    assert True not in states, "a flapping source switched the model to flight"
    assert states[-1] is None and tr.source == fs.SOURCE_FLAPPING
    assert tr.flap_fallbacks == 1
    assert sum("not believed" in r.getMessage() for r in caplog.records) == 1
    # quiet again: believed after FLAP_WINDOW_S
    t = 4.0
    while t < 4.0 + fs.FLAP_WINDOW_S + 1.0:
        t += 0.2
        tr.on_extended_sys_state(t, fs.LANDED_IN_AIR)
    assert tr.airborne is True and tr.source == fs.SOURCE_LANDED


# --- replay ----------------------------------------------------------------------------------
def test_replay_follows_px4s_touchdown_and_second_take_off():
    """A real PX4 SIH flight: 10 s disarmed, take-off, touchdown, 10 s on the ground,
    second take-off, landing (tests/data/sitl)."""
    rec = recording(SITL / "px4_sih_touchdown.tlog")
    fl = track(rec)
    assert fl.known and "EXTENDED_SYS_STATE" in fl.events_source
    states = [s.airborne for s in fl.switches]
    assert states == [False, True, False, True, False]
    t_air = [s.t for s in fl.switches if s.airborne]
    assert t_air[1] - t_air[0] > 40.0
    names = set(fl.phase_names().tolist())
    assert {"ground", "takeoff", "flight", "landing", "touchdown"} <= names
    # on the ground between the flights the belief is "on ground"
    between = (rec.t > fl.switches[2].t + 1.0) & (rec.t < fl.switches[3].t - 1.0)
    assert between.sum() > 1000 and np.all(fl.airborne[between] == 0.0)


def _tlog(path: Path, sender: list[tuple[float, int, int, object]]) -> None:
    """Write a tlog of (time s, sysid, compid, message) records."""
    links: dict[tuple[int, int], mavlink.MAVLink] = {}
    with path.open("wb") as f:
        for t, sysid, compid, msg in sender:
            mav = links.setdefault((sysid, compid), mavlink.MAVLink(None, sysid, compid))
            f.write(struct.pack(">Q", int(t * 1e6)) + bytes(msg.pack(mav)))


def _hover_log(path: Path, extra: list[tuple[float, int, int, object]]) -> None:
    """20 s of a level vehicle (HIGHRES_IMU 100 Hz) that is armed and on the ground."""
    rows = []
    for k in range(2000):
        t = k / 100.0
        rows.append((t, 1, 1, mavlink.MAVLink_highres_imu_message(
            int(t * 1e6), 0.0, 0.0, -9.81, 0.0, 0.0, 0.0, 0.2, 0.0, 0.4, 1013.0, 0.0, 0.0,
            20.0, 0x1FF)))
        if k % 100 == 0:
            rows.append((t, 1, 1, mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_QUADROTOR, PX4, ARMED, 0, mavlink.MAV_STATE_ACTIVE, 3)))
        if k % 20 == 0:
            rows.append((t, 1, 1, mavlink.MAVLink_extended_sys_state_message(
                0, fs.LANDED_ON_GROUND)))
    rows += extra
    rows.sort(key=lambda r: r[0])
    _tlog(path, rows)


def test_replay_ignores_a_spoofed_landed_state_from_another_system(tmp_path):
    spoof = [(0.05 + 0.1 * k, 99, 1, mavlink.MAVLink_extended_sys_state_message(
        0, fs.LANDED_IN_AIR)) for k in range(150)]
    path = tmp_path / "spoofed.tlog"
    _hover_log(path, spoof)
    rec = load(path)
    fl = track(rec)
    assert not np.any(fl.airborne == 1.0)
    assert any("ignored 150" in n for n in rec.notes), rec.notes


def test_replay_drops_a_flapping_landed_state_with_a_counted_note(tmp_path):
    flap = [(5.0 + 0.05 * k, 1, 1, mavlink.MAVLink_extended_sys_state_message(
        0, fs.LANDED_IN_AIR if k % 2 else fs.LANDED_ON_GROUND)) for k in range(100)]
    path = tmp_path / "flapping.tlog"
    _hover_log(path, flap)
    fl = track(load(path))
    assert fl.flap_fallbacks == 1 and "unreliable" in fl.note()
    assert len(fl.switches) <= 3  # ground -> unknown (fallback) -> ground, never per message
    assert not np.any(fl.airborne == 1.0)


def test_ulog_without_land_detector_topics_has_no_state_events():
    assert ulog_state_events({}, 0) == ((), "")


def test_ulog_land_detector_and_arming_are_read(data_dir):
    rec = load(data_dir / "logs" / "pyulog_sample_log_small.ulg")
    assert rec.state_events_source == "vehicle_status + vehicle_land_detected"
    kinds = {e.kind for e in rec.state_events}
    assert kinds == {"armed", "land_detector"}


def test_phases_cover_every_sample_of_a_recording():
    rec = recording(SITL / "px4_sih_dashes.tlog")
    ph = track(rec).phase
    assert ph.shape == (rec.n,) and ph.min() >= 0 and ph.max() < len(PHASES)
    # "unknown" only before the first report (a second at most)
    unknown = rec.t[ph == PHASES.index("unknown")]
    assert unknown.size == 0 or unknown.max() - rec.t[0] < 1.5


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(ReplayInputError):
        load(tmp_path / "nope.tlog")


def test_replay_output_shows_the_state_its_switches_and_the_phases(tmp_path):
    from replay.evaluate import evaluate
    from replay.report import write_report
    from replay.summary import print_summary

    ev = evaluate(recording(SITL / "px4_sih_touchdown.tlog"), ["eskf"])
    doc = ev.as_json()["flight_state"]
    assert [s["state"] for s in doc["switches"]] == ["on ground", "airborne", "on ground",
                                                     "airborne", "on ground"]
    assert [b["state"] for b in doc["bands"]][-4:] == ["airborne", "on ground", "airborne",
                                                       "on ground"]
    phases = ev.scores["eskf"].phases
    assert {"ground", "takeoff", "flight", "landing", "touchdown"} <= set(phases)
    assert ev.scores["eskf"].worst_phase[1] >= ev.scores["eskf"].total_deg
    import io
    out = io.StringIO()
    print_summary(ev, out)
    assert "flight:      from HEARTBEAT + EXTENDED_SYS_STATE" in out.getvalue()
    assert "by phase" in out.getvalue()
    page = write_report([ev], tmp_path / "r.html").read_text()
    assert "By flight phase" in page and page.count("BoxAnnotation") >= 4
