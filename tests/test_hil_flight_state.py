"""The emulator tells the truth about its flight state.

Armed and MAV_LANDED_STATE follow from the motion: a board carried by hand is never
armed and never in the air, a multirotor flight arms, takes off, lands and disarms
where its plan says so. ``simulate()`` records that truth, and on the wire the HEARTBEAT
armed flag and EXTENDED_SYS_STATE (sent only when asked for, as PX4 and ArduPilot do)
carry it, unless the board is a bare one (``--no-flight-state``). Real UDP sockets and
real pymavlink on the listener's side; the emulator runs faster than real time
(``fast``) and at 100-250 Hz, since flight states change over seconds.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hil_support import Receiver

from hil import Emulator, EmulatorConfig, make_profile, simulate
from hil.cli import config_from_args, register
from hil.motion import HandheldThenFlight, calibration_duration_s, handheld
from hil.multirotor import bench_flights
from hil.source import CHUNK_S
from hil.truth import LANDED_IN_AIR, LANDED_LANDING, LANDED_ON_GROUND, LANDED_TAKEOFF

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink

REPO = Path(__file__).resolve().parents[1]
ESS = mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE
ARMED_FLAG = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
RATE_HZ = 100.0
GROUND, AIR, TAKEOFF, LANDING = LANDED_ON_GROUND, LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING
#: One flight, as (armed, landed_state) in the order they come.
ONE_FLIGHT = [(False, GROUND), (True, GROUND), (True, TAKEOFF), (True, AIR), (True, LANDING),
              (True, GROUND), (False, GROUND)]
FLIGHT_S = 91.0  # `flight` lands at 86.9 s and disarms 2 s later
HANDHELD_S = 105.0  # `handheld_flight` disarms for good at 103.8 s
#: A request applies from the chunk after the one being made; seen from its ACK's place
#: in the stream, up to one chunk more: the ACK goes out while one chunk is still being
#: sent and the next may already be made (128 ms measured on a loaded 2-core machine).
ACKED_CHUNKS_US = 3 * CHUNK_S * 1e6


# ---- the listener -------------------------------------------------------------------

def command(cmd: int, *params: float):
    """COMMAND_LONG for the board (system 1, autopilot component)."""
    padded = [*params, *[0.0] * (7 - len(params))]
    return mavlink.MAVLink_command_long_message(1, 1, cmd, 0, *padded)


def set_interval(msg_id: int, interval_us: float):
    return command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us)


def request_message(msg_id: int):
    return command(mavlink.MAV_CMD_REQUEST_MESSAGE, msg_id)


def get_interval(msg_id: int):
    return command(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, msg_id)


def board_s(rx: Receiver, cfg: EmulatorConfig) -> float:
    """How far the stream has got [s since the first sample], from the newest truth."""
    newest = next((r.msg for r in reversed(rx.valid)
                   if r.msg.get_type() == "HIL_STATE_QUATERNION"), None)
    return -1.0 if newest is None else newest.time_usec * 1e-6 - cfg.boot_time_s


def stream(cfg: EmulatorConfig, schedule: list[tuple[float, list]] = ()
           ) -> tuple[Emulator, Receiver]:
    """Stream cfg to a listener that sends each batch of ``schedule`` once the stream
    has reached that board time [s] (and then waits for the next)."""
    rx = Receiver.open()

    async def scenario() -> Emulator:
        loop = asyncio.get_running_loop()
        rx.attach(loop)
        emu = Emulator(cfg)
        task = asyncio.create_task(emu.run([("127.0.0.1", rx.port)]))
        try:
            for at_s, msgs in schedule:
                while not task.done() and board_s(rx, cfg) < at_s:
                    await asyncio.sleep(0.001)
                assert not task.done(), f"the stream ended before {at_s} s"
                for msg in msgs:
                    rx.send(msg)
            await task
            await asyncio.sleep(0.05)
        finally:
            rx.detach(loop)
        return emu

    return asyncio.run(scenario()), rx


def timeline(rx: Receiver) -> list[int | None]:
    """Board time [µs] of the sample each received message belongs to.

    Only HIL_STATE_QUATERNION (every sample here) says its time. A HEARTBEAT goes first
    at its instant, so it belongs to the next truth's sample; EXTENDED_SYS_STATE goes
    last, and replies go out between the stream's packets, so they belong to the
    previous truth's (the instant the stream had reached).
    """
    own = [r.msg.time_usec if r.msg.get_type() == "HIL_STATE_QUATERNION" else None
           for r in rx.valid]
    before = list(itertools.accumulate(own, lambda a, b: a if b is None else b))
    after = list(itertools.accumulate(reversed(own), lambda a, b: a if b is None else b))[::-1]
    return [a if r.msg.get_type() == "HEARTBEAT" else b
            for r, a, b in zip(rx.valid, after, before, strict=True)]


def sample_index(rec, times_us: list[int]) -> np.ndarray:
    """Indices into a recording of board times seen on the wire (exact matches)."""
    k = np.searchsorted(rec.time_us, times_us)
    assert np.array_equal(rec.time_us[k], times_us)
    return k


def wire_states(rx: Receiver) -> list[tuple[bool, int]]:
    """(armed from the latest HEARTBEAT, landed_state from the latest
    EXTENDED_SYS_STATE) each time either changes, once both have been seen."""
    armed = landed = None
    seen = []
    for r in rx.valid:
        kind = r.msg.get_type()
        if kind == "HEARTBEAT":
            armed = bool(r.msg.base_mode & ARMED_FLAG)
        elif kind == "EXTENDED_SYS_STATE":
            landed = r.msg.landed_state
        else:
            continue
        if armed is not None and landed is not None:
            seen.append((armed, landed))
    return [state for state, _ in itertools.groupby(seen)]


def runs(armed: np.ndarray, landed: np.ndarray) -> list[tuple[bool, int]]:
    """The sequence of distinct (armed, landed_state) of a recording."""
    return [state for state, _ in itertools.groupby(zip(armed.tolist(), landed.tolist(),
                                                        strict=True))]


def acks(rx: Receiver) -> list[tuple[int, int]]:
    return [(m.command, m.result) for m in rx.of_type("COMMAND_ACK")]


def positions(rx: Receiver, kind: str) -> list[int]:
    return [i for i, r in enumerate(rx.valid) if r.msg.get_type() == kind]


def check_heartbeats(rx: Receiver, rec, autopilot: str) -> None:
    """Every streamed HEARTBEAT says the recorded armed state of its instant, with
    system_status STANDBY when disarmed and ACTIVE when armed (PX4, the seeds' board)
    or STANDBY on the ground and ACTIVE off it (ArduPilot)."""
    at = timeline(rx)
    beats = [(r.msg, t) for r, t in zip(rx.valid, at, strict=True)
             if r.msg.get_type() == "HEARTBEAT"]
    k = sample_index(rec, [t for _, t in beats])
    armed = rec.armed[k]
    assert [bool(m.base_mode & ARMED_FLAG) for m, _ in beats] == armed.tolist()
    active = rec.landed_state[k] != GROUND if autopilot == "ardupilot" else armed
    assert [m.system_status for m, _ in beats] == [
        mavlink.MAV_STATE_ACTIVE if a else mavlink.MAV_STATE_STANDBY for a in active]


# ---- (1) hand-held profiles --------------------------------------------------------

CSV = "time_s,qw,qx,qy,qz\n0,1,0,0,0\n1,0.9659,0.2588,0,0\n2.5,0.9659,0,0,0.2588\n"
HAND_HELD = {  # duration [s] (the whole profile, or enough of it), personality
    "static": (3.0, "stm32"), "tilt": (3.0, "px4"), "gentle": (30.0, "ardupilot"),
    "aggressive": (12.0, "px4"), "calibration": (calibration_duration_s(), "stm32"),
    "file": (3.0, "ardupilot")}


@pytest.mark.parametrize("name", list(HAND_HELD))
def test_hand_held_profiles_are_disarmed_on_the_ground_throughout(name, tmp_path):
    """Moved by hand (gentle climbs 15 m, aggressive loops 5 m up: still no thrust of
    its own), the board never arms and never leaves the ground, in the profile, in
    simulate() and on the wire (10 heartbeats a second, EXTENDED_SYS_STATE asked for
    with every sample from the start)."""
    duration, autopilot = HAND_HELD[name]
    if name == "file":
        (tmp_path / "motion.csv").write_text(CSV)
        name = f"file:{tmp_path / 'motion.csv'}"
    t = np.arange(0.0, duration, 1e-3)
    armed, landed = make_profile(name, duration).flight_state(t)
    assert armed.dtype == bool and landed.dtype == np.uint8 and landed.shape == t.shape
    assert not armed.any() and np.all(landed == GROUND)

    cfg = EmulatorConfig(profile=name, autopilot=autopilot, rate_hz=RATE_HZ,
                         duration_s=duration, heartbeat_hz=10.0, fast=True)
    rec = simulate(cfg)
    assert len(rec.armed) == len(rec.landed_state) == len(rec)
    assert not rec.armed.any() and np.all(rec.landed_state == GROUND)

    _, rx = stream(cfg, [(0.0, [set_interval(ESS, 1)])])
    assert acks(rx) == [(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_ACCEPTED)]
    beats = rx.of_type("HEARTBEAT")
    assert len(beats) >= 10 * duration - 1
    check_heartbeats(rx, rec, autopilot)
    states = rx.of_type("EXTENDED_SYS_STATE")
    assert len(states) >= RATE_HZ * (duration - 0.5)
    assert {(s.landed_state, s.vtol_state) for s in states} == {
        (GROUND, mavlink.MAV_VTOL_STATE_UNDEFINED)}


# ---- (2) flight -------------------------------------------------------------------

@pytest.fixture(scope="module")
def flight_run():
    """`flight` from the ground to after the landing; the listener asks for
    EXTENDED_SYS_STATE at 5 Hz as soon as the stream begins (the seeds' board)."""
    cfg = EmulatorConfig(profile="flight", rate_hz=RATE_HZ, duration_s=FLIGHT_S, seed=5,
                         fast=True)
    _, rx = stream(cfg, [(0.0, [set_interval(ESS, 200_000)])])
    return simulate(cfg), rx


@pytest.mark.xdist_group("hil_flight_run")  # one worker builds the fixture once
def test_flight_state_follows_the_flight_plan(flight_run):
    rec, _ = flight_run
    assert runs(rec.armed, rec.landed_state) == ONE_FLIGHT
    t, state = rec.t_s, rec.landed_state
    alt, climb = -rec.truth_position_ned[:, 2], -rec.truth_velocity_ned[:, 2]
    ground = state == GROUND
    assert np.all(np.abs(alt[ground]) < 1e-6) and np.all(np.abs(climb[ground]) < 1e-6)
    assert alt[state == AIR].min() > 5.0
    assert np.all(climb[state == TAKEOFF] >= -1e-9) and climb[state == TAKEOFF].max() > 2.0
    assert np.all(climb[state == LANDING] <= 1e-9) and climb[state == LANDING].min() < -1.0
    # TAKEOFF ends at the cruise altitude, LANDING starts from it
    assert alt[state == TAKEOFF].max() == pytest.approx(10.0, abs=0.01)
    assert alt[state == LANDING].max() == pytest.approx(10.0, abs=0.01)
    # lift-off and touchdown are where the truth leaves and reaches the ground
    off_ground = np.flatnonzero(alt > 1e-3)
    assert state[off_ground[0]] == TAKEOFF and state[off_ground[-1]] == LANDING
    liftoff = t[np.argmax(state == TAKEOFF)]
    touchdown = t[np.flatnonzero(state == LANDING)[-1] + 1]
    assert liftoff == pytest.approx(5.0, abs=0.011) and touchdown == pytest.approx(86.9, abs=0.1)
    # armed a moment before lift-off, disarmed a couple of seconds after touchdown
    armed = np.flatnonzero(rec.armed)
    assert 1.0 <= liftoff - t[armed[0]] <= 2.0
    assert 1.5 <= t[armed[-1] + 1] - touchdown <= 2.5


@pytest.mark.xdist_group("hil_flight_run")  # one worker builds the fixture once
def test_flight_state_on_the_wire_is_the_recorded_one(flight_run):
    rec, rx = flight_run
    assert wire_states(rx) == ONE_FLIGHT
    check_heartbeats(rx, rec, "stm32")
    at = timeline(rx)
    ess = positions(rx, "EXTENDED_SYS_STATE")
    k = sample_index(rec, [at[i] for i in ess])
    assert [rx.valid[i].msg.landed_state for i in ess] == rec.landed_state[k].tolist()
    assert np.all(np.diff(rec.time_us[k]) == 200_000)  # 5 Hz, as asked
    assert len(ess) >= 5 * (FLIGHT_S - 0.5)


# ---- (3) handheld_flight ------------------------------------------------------------

@pytest.fixture(scope="module")
def handheld_rec():
    return simulate(EmulatorConfig(profile="handheld_flight", rate_hz=RATE_HZ,
                                   duration_s=HANDHELD_S, seed=3))


def test_handheld_flight_hands_over_to_the_flight_without_a_jump():
    profile = make_profile("handheld_flight")
    s = profile.switch_s
    assert s == pytest.approx(12.5)
    # either side of the switch, 0.1 µs apart: the same attitude, rates, velocity and
    # specific force (the hand's last 4.4 m/s³ of jerk stops there: no jump in the
    # acceleration itself)
    near = profile.truth(s + np.array([-1e-7, 1e-7]))
    for got in (near.q, near.rates, near.velocity_ned, near.specific_force()):
        assert np.abs(got[1] - got[0]).max() < 1e-5
    # on a 0.1 ms grid the step across the switch is no bigger than the steps beside it
    t = s + np.arange(-50, 51) * 1e-4
    truth = profile.truth(t)
    for got in (truth.q, truth.rates, truth.velocity_ned, truth.specific_force()):
        steps = np.abs(np.diff(got, axis=0)).max(axis=1)
        assert steps[49] <= 1.01 * max(steps[48], steps[50]) + 1e-12
    # set down at rest and level, facing 30°, where it started: the plan starts there
    sf = truth.specific_force()[50]
    assert np.allclose(sf, [0.0, 0.0, -9.80665], atol=1e-6)
    assert np.allclose(truth.position_ned[50], 0.0, atol=1e-9)
    assert np.allclose(truth.q[50], [math.cos(math.radians(15)), 0, 0,
                                     math.sin(math.radians(15))], atol=1e-9)
    # a plan that starts facing elsewhere would jump: refused
    with pytest.raises(ValueError, match="do not join"):
        HandheldThenFlight("x", handheld(), bench_flights(s, math.radians(40.0)), s)


@pytest.mark.xdist_group("hil_handheld")  # one worker builds the fixture once
def test_handheld_flight_is_carried_then_takes_off_twice(handheld_rec):
    rec = handheld_rec
    profile = make_profile("handheld_flight")
    assert runs(rec.armed, rec.landed_state) == ONE_FLIGHT + ONE_FLIGHT[1:]
    t, state = rec.t_s, rec.landed_state
    alt = -rec.truth_position_ned[:, 2]
    # in the hand: moved (lifted, tilted 30°) but disarmed, on the ground
    hand = t < profile.switch_s
    tilt = np.degrees(np.arccos(np.clip(-rec.truth_specific_force[hand, 2]
                                        / np.linalg.norm(rec.truth_specific_force[hand],
                                                         axis=1), -1, 1)))
    assert alt[hand].max() == pytest.approx(0.25) and tilt.max() > 25.0
    assert not rec.armed[hand].any() and np.all(state[hand] == GROUND)
    # after the hand, ON_GROUND means the truth is on the ground and IN_AIR well above
    grounded = ~hand & (state == GROUND)
    assert np.all(np.abs(alt[grounded]) < 1e-6)
    assert alt[state == AIR].min() > 5.0
    # two take-offs (16.5 s, 64.8 s), two touchdowns; 10 s on the ground between the
    # flights, disarmed there from 2 s after touchdown until 1.5 s before lift-off
    starts = t[np.flatnonzero(np.diff((state == TAKEOFF).astype(int)) == 1) + 1]
    ends = t[np.flatnonzero(np.diff((state == LANDING).astype(int)) == -1) + 1]
    assert starts == pytest.approx([16.5, 64.8], abs=0.011)
    assert ends == pytest.approx([54.8, 101.82], abs=0.011)
    assert starts[1] - ends[0] == pytest.approx(10.0, abs=0.011)
    edges = t[np.flatnonzero(np.diff(rec.armed.astype(int))) + 1]
    assert edges == pytest.approx([15.0, 56.8, 63.3, 103.82], abs=0.011)
    flights = [(f.liftoff, f.touchdown) for f in profile.flights]
    assert list(itertools.chain(*flights)) == pytest.approx(
        [starts[0], ends[0], starts[1], ends[1]], abs=0.011)


@pytest.mark.xdist_group("hil_handheld")  # one worker builds the fixture once
def test_handheld_flight_from_the_command_line(handheld_rec):
    """`attitude-bridge hil --profile handheld_flight` (ArduPilot, --fast): the same
    samples as simulate(), and HEARTBEAT disarmed, armed, disarmed, armed, disarmed."""
    rx = Receiver.open()
    proc = subprocess.Popen(
        [sys.executable, "-m", "bridge.app.cli", "hil", "--target", f"udp:127.0.0.1:{rx.port}",
         "--profile", "handheld_flight", "--rate", str(RATE_HZ), "--duration", str(HANDHELD_S),
         "--seed", "3", "--autopilot", "ardupilot", "--fast"],
        env=dict(os.environ, PYTHONPATH=str(REPO)), stderr=subprocess.PIPE, text=True)
    try:
        rx.blocking_collect(seconds_idle=1.0, limit_s=120.0)
    finally:
        _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert "handheld_flight" in err
    rec = handheld_rec
    truth = rx.of_type("HIL_STATE_QUATERNION")
    k = sample_index(rec, [m.time_usec for m in truth])
    assert np.allclose([m.attitude_quaternion for m in truth], rec.truth_q[k], atol=1e-6)
    check_heartbeats(rx, rec, "ardupilot")
    beats = [bool(m.base_mode & ARMED_FLAG) for m in rx.of_type("HEARTBEAT")]
    assert len(beats) == HANDHELD_S
    assert [a for a, _ in itertools.groupby(beats)] == [False, True, False, True, False]


def test_help_lists_handheld_flight_and_the_bare_board_switch(capsys):
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    with pytest.raises(SystemExit):
        parser.parse_args(["hil", "--help"])
    out = capsys.readouterr().out
    assert "handheld_flight" in out and "--no-flight-state" in out


# ---- (4) EXTENDED_SYS_STATE on request ---------------------------------------------

@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_extended_sys_state_only_when_asked(autopilot):
    """Off at start (GET_MESSAGE_INTERVAL: -1); REQUEST_MESSAGE sends one with an
    ACCEPTED ACK (PX4 the message first, ArduPilot the ACK); SET_MESSAGE_INTERVAL at
    10 Hz, then the default (0: 1 Hz), then off (-1)."""
    cfg = EmulatorConfig(profile="flight", autopilot=autopilot, rate_hz=250.0,
                         duration_s=11.0, seed=4, fast=True)
    emu, rx = stream(cfg, [(0.5, [get_interval(ESS)]), (1.0, [request_message(ESS)]),
                           (2.0, [set_interval(ESS, 100_000)]), (5.5, [set_interval(ESS, 0)]),
                           (8.5, [set_interval(ESS, -1)])])
    rec = simulate(cfg)
    accepted = mavlink.MAV_RESULT_ACCEPTED
    set_cmd = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    assert acks(rx) == [(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, accepted),
                        (mavlink.MAV_CMD_REQUEST_MESSAGE, accepted),
                        (set_cmd, accepted), (set_cmd, accepted), (set_cmd, accepted)]
    assert [(m.message_id, m.interval_us) for m in rx.of_type("MESSAGE_INTERVAL")] == [(ESS, -1)]
    assert emu.stats.requests.message_accepted == 1
    at = timeline(rx)
    _, i_req, i_fast, i_default, i_off = positions(rx, "COMMAND_ACK")
    ess = positions(rx, "EXTENDED_SYS_STATE")
    # nothing until asked; then exactly one, next to its ACK
    requested = i_req + 1 if autopilot == "ardupilot" else i_req - 1
    assert [i for i in ess if i < i_fast] == [requested]
    # every message says the recorded state of its instant (lift-off at 5 s)
    k = sample_index(rec, [at[i] for i in ess])
    landed = [rx.valid[i].msg.landed_state for i in ess]
    assert landed == rec.landed_state[k].tolist() and set(landed) == {GROUND, TAKEOFF}
    # the stream: 10 Hz from just after its ACK, 1 Hz from just after the next, then none
    times = np.array([at[i] for i in ess if i > i_fast])
    gaps = np.diff(times)
    slow = np.flatnonzero(gaps == 1_000_000)
    assert len(slow) >= 2 and np.all(gaps[slow[0]:] == 1_000_000)
    assert np.all(gaps[:slow[0] - 1] == 100_000) and gaps[slow[0] - 1] <= 100_000
    assert slow[0] >= 30
    assert at[i_fast] < times[0] <= at[i_fast] + ACKED_CHUNKS_US
    assert at[i_default] < times[slow[0]] <= at[i_default] + ACKED_CHUNKS_US
    assert times[-1] <= at[i_off] + ACKED_CHUNKS_US
    assert rec.time_us[-1] - at[i_off] > 1.5e6  # time enough for one more, had it been on
    check_heartbeats(rx, rec, autopilot)  # armed at 3.5 s, lift-off at 5 s
    assert rec.armed[0] == 0 and rec.armed[-1] == 1


# ---- (5) a bare board -------------------------------------------------------------

REFUSED = {"px4": mavlink.MAV_RESULT_DENIED, "ardupilot": mavlink.MAV_RESULT_FAILED}


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_bare_board_tells_no_flight_state(autopilot):
    """flight_state=False: never the armed flag (though the vehicle arms at 3.5 s), and
    EXTENDED_SYS_STATE is refused like a message the board has no stream of."""
    cfg = EmulatorConfig(profile="flight", autopilot=autopilot, rate_hz=250.0, duration_s=7.0,
                         seed=6, fast=True, flight_state=False)
    unknown = mavlink.MAVLINK_MSG_ID_BATTERY_STATUS
    emu, rx = stream(cfg, [(1.0, [request_message(ESS), request_message(unknown),
                                  set_interval(ESS, 0), set_interval(unknown, 0),
                                  get_interval(ESS), request_message(0)])])
    assert not rx.of_type("EXTENDED_SYS_STATE")
    refused, failed = REFUSED[autopilot], mavlink.MAV_RESULT_FAILED
    request, set_cmd = mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    assert acks(rx) == [(request, refused), (request, refused), (set_cmd, failed),
                        (set_cmd, failed), (mavlink.MAV_CMD_GET_MESSAGE_INTERVAL,
                                            mavlink.MAV_RESULT_ACCEPTED),
                        (request, mavlink.MAV_RESULT_ACCEPTED)]
    assert [m.interval_us for m in rx.of_type("MESSAGE_INTERVAL")] == [0]  # no such stream
    beats = rx.of_type("HEARTBEAT")
    assert len(beats) == 8  # 7 streamed, 1 requested
    assert all(not b.base_mode & ARMED_FLAG and b.system_status == mavlink.MAV_STATE_ACTIVE
               for b in beats)
    assert (emu.stats.requests.message_refused, emu.stats.requests.message_accepted) == (2, 1)
    assert simulate(cfg).armed[-1]  # the truth still has it: only the link is silent


def test_no_flight_state_switch_on_the_command_line():
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    base = ["hil", "--target", "udp:127.0.0.1:9"]
    assert config_from_args(parser.parse_args(base)).flight_state is True
    assert config_from_args(parser.parse_args([*base, "--no-flight-state"])).flight_state is False
