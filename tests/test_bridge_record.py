"""``run --record``: the session as a tlog that the replay tools read back.

The bridge runs on the HIL emulator over real UDP, records its connection, and the
recording is replayed with the same estimator: the offline run on what crossed the
wire must be what the bridge sent live, and the CSV/JSON outputs must describe it.
"""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from bridge_support import async_test

from bridge.app.cli import main
from bridge.app.config import BridgeConfig
from bridge.app.service import BridgeService
from bridge.vehicle.declination import CONFIRM_FIXES
from estimators import quat as Q
from hil import Emulator, EmulatorConfig

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil


def read_tlog(path) -> list:
    """(stamp_us, message) of every frame, as pymavlink's own tlog reader sees it."""
    log = mavutil.mavlink_connection(str(path), dialect="common")
    out = []
    while (m := log.recv_msg()) is not None:
        if m.get_type() != "BAD_DATA":
            out.append(m)
    log.close()
    return out


@async_test
async def test_recording_replays_to_what_the_bridge_sent(tmp_path):
    tlog = tmp_path / "session.tlog"
    ecfg = EmulatorConfig(profile="flight", duration_s=14.0, seed=2, fast=True)
    cfg = BridgeConfig(connect="udpin:127.0.0.1:0", estimators=["mahony"], out_rate=0.0,
                       record=str(tlog), aiding=False)

    async def emulator(port: int):
        await asyncio.sleep(0.2)
        return await Emulator(ecfg).run(targets=[("127.0.0.1", port)])

    service = BridgeService(cfg, emulator)
    await service.run()
    status = service.last_status[1]
    frames = read_tlog(tlog)
    ours = [m for m in frames if m.get_srcComponent() == cfg.component_id]
    imu = [m for m in frames if m.get_type() == "RAW_IMU"]
    # Everything in (the IMU, truth, heartbeats, command answers) and out (attitude,
    # heartbeats, stream requests), stamped with the wall clock in order.
    assert len(imu) >= status["samples"] > 1000
    assert {"HIL_STATE_QUATERNION", "HEARTBEAT", "COMMAND_ACK"} <= {m.get_type() for m in frames}
    assert {"ATTITUDE_QUATERNION", "ATTITUDE", "HEARTBEAT", "COMMAND_LONG"} <= {
        m.get_type() for m in ours}
    stamps = np.array([m._timestamp for m in frames])
    assert np.all(np.diff(stamps) >= 0) and abs(stamps[-1] - stamps[0]) < 60.0
    sent = [m for m in ours if m.get_type() == "ATTITUDE_QUATERNION"]
    assert len(sent) == status["sent"]

    # Replayed from the file, with the same estimator: the same attitudes.
    out_json, out_csv = tmp_path / "r.json", tmp_path / "r.csv"
    assert main(["replay", str(tlog), "-e", "mahony", "--json", str(out_json),
                 "--csv", str(out_csv)]) == 0
    doc = json.loads(out_json.read_text())
    assert doc["reference"] == "truth"
    assert 0.0 < doc["estimators"]["mahony"]["total_deg"] < 8.5  # measured 5.6°, 1.5x
    header, *rows = out_csv.read_text().splitlines()
    names = header.split(",")
    table = np.array([[float(x) if x else np.nan for x in r.split(",")] for r in rows])
    assert len(table) == len(imu)
    t_board = table[:, names.index("t")] + imu[0].time_usec * 1e-6
    q_replay = table[:, [names.index(f"mahony.q{c}") for c in "wxyz"]]
    at = {round(t * 1e3): i for i, t in enumerate(t_board)}
    # The bridge learns the declination from the position (in the truth message), once
    # CONFIRM_FIXES fixes agree on it, and turns its output then; the replay knows it
    # from the start.
    located_ms = sorted(m.time_usec for m in frames
                        if m.get_type() == "HIL_STATE_QUATERNION")[CONFIRM_FIXES - 1] / 1e3
    pairs = [(np.array([m.q1, m.q2, m.q3, m.q4]), q_replay[at[m.time_boot_ms]])
             for m in sent if m.time_boot_ms in at and m.time_boot_ms > located_ms]
    assert len(pairs) > 0.95 * len(sent)
    live, offline = map(np.array, zip(*pairs, strict=True))
    assert np.degrees(Q.angle_between(live, offline)).max() < 0.01


def test_a_recording_that_cannot_be_written_stops_with_one_warning(tmp_path):
    """`--record` on a full disk (/dev/full says ENOSPC to every write) printed a
    traceback per frame, about 2,700 in two seconds; now one warning, the bridge goes
    on, and the summary says the recording stopped early."""
    repo = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-m", "bridge.app.cli", "run", "--duration", "2",
                          "-q", "--record", "/dev/full"], cwd=repo, capture_output=True,
                         text=True, timeout=120)
    text = out.stdout + out.stderr
    assert out.returncode == 0, text[-2000:]
    assert "Traceback" not in text
    assert text.count("recording to /dev/full stopped: No space left on device") == 1
    assert "to /dev/full, stopped early: No space left on device" in text
    assert " estimates sent" in text
