"""Unit tests of the bridge's pure parts: clock verdicts, sequence loss, rotations,
codec (bad bytes, signing), ingest scaling, URL/estimator parsing, comparison."""

from __future__ import annotations

import math
import socket
import time

import numpy as np
import pytest
from bridge_support import (
    MAG_NED,
    ZERO3,
    G,
    UdpListener,
    async_test,
    euler_q,
    gy86_counts,
    wait_until,
)

from bridge.app.config import BridgeConfig
from bridge.estimate.compare import compare_series, pairs_at_shift
from bridge.estimate.pipeline import Estimate
from bridge.publish.mqtt import MqttSettings
from bridge.publish.output import AttitudeOutput
from bridge.vehicle import clock as C
from bridge.vehicle.ingest import Ingest, SourceKey
from bridge.wire.admission import Admission
from bridge.wire.codec import MavCodec, SigningConfig, load_signing_key, signing_key_from_text
from bridge.wire.kernelfilter import MARK_LEN, SAMPLE, KernelFilter
from bridge.wire.links import open_link, parse_url
from bridge.wire.mav import mavlink
from bridge.wire.sequence import SequenceTracker
from estimators import quat as Q
from estimators.shifted_error import rms_at_shifts
from estimators.spec import EstimatorSpec
from imu.boards import gy86
from imu.rotations import rotation_matrix


def verdicts(clock: C.SampleClock, stamps: list[int], t0: float = 0.0,
             pace_s: float = 0.001) -> list[str]:
    """Verdicts of stamps arriving ``pace_s`` apart from local time ``t0``."""
    return [clock.classify(s, t0 + i * pace_s).verdict for i, s in enumerate(stamps)]


def test_clock_accepts_steady_stream_with_dt():
    clock = C.SampleClock(1e-6)
    assert clock.classify(1000, 0.0).verdict == C.FIRST
    v = clock.classify(2000, 0.001)
    assert v.verdict == C.OK and v.accepted[0].ticks == 2000
    assert v.accepted[0].dt == pytest.approx(1e-3)


def test_clock_duplicate_reordered_and_isolated_glitches():
    clock = C.SampleClock(1e-6)
    v = verdicts(clock, [0, 1000, 2000, 2000, 4000, 3000, 5000, 900_000, 6000,
                         -400_000 + 2**40, 7000])
    assert v == ["first", "ok", "ok", "duplicate", "ok", "reordered", "ok", "jump", "ok",
                 "jump", "ok"]
    late = C.SampleClock(1e-6)
    assert verdicts(late, [1_000_000, 1_001_000, 100]) == ["first", "ok", "backwards"]


def stream(clock: C.SampleClock, t0_us: int, n: int, arrival0: float,
           step_us: int = 1000) -> list[C.Verdict]:
    """n stamps step_us apart, arriving in real time from arrival0 (content: the arrival
    time, as distinct as real sensor readings)."""
    return [clock.classify(t0_us + i * step_us, arrival0 + i * step_us * 1e-6,
                           arrival0 + i * step_us * 1e-6) for i in range(n)]


def test_clock_adopts_a_permanent_step_only_on_sustained_evidence_and_loses_nothing():
    clock = C.SampleClock(1e-6, resync_s=1.0)
    stream(clock, 0, 100, 0.0)
    # The board clock steps forward by 0.5 s and stays there: held for 1 s, then adopted
    # with every held sample handed back in order.
    after = stream(clock, 600_000, 1100, 0.1)
    names = [v.verdict for v in after]
    assert names[:1000] == ["jump"] * 1000 and names[1000] == "resync"
    assert names[1001:] == ["ok"] * 99
    adopted = after[1000]
    assert [a.ticks for a in adopted.accepted] == [600_000 + 1000 * i for i in range(1001)]
    assert adopted.reclassified == ["jump"] * 1000
    # A step back by 50 ms (inside the reorder window) costs 50 ms of samples: the
    # stream then overtakes the old timeline and simply continues.
    back = [v.verdict for v in stream(clock, 1_650_000, 200, 1.2)]
    assert back[:49] == ["reordered"] * 49 and back[49] == "backwards"
    assert back[50:] == ["ok"] * 150


def test_clock_never_flips_while_the_vehicle_keeps_talking():
    """Bursts of agreeing forged stamps (10 s ahead, 10 min ahead, 10 s behind), even
    sustained for seconds, between the real samples: the real timeline stays."""
    clock = C.SampleClock(1e-6, resync_s=1.0)
    stream(clock, 1_000_000, 10, 0.0)
    real_ok = forged_used = 0
    for i in range(10, 3000):
        v = clock.classify(1_000_000 + i * 1000, i * 0.001)
        real_ok += v.verdict == "ok"
        for offset in (10_000_000, 600_000_000, -10_000_000):
            f = clock.classify(1_000_000 + i * 1000 + offset, i * 0.001 + 0.0002)
            forged_used += len(f.accepted)
    assert real_ok == 2990 and forged_used == 0
    assert clock.last_ticks == 1_000_000 + 2999 * 1000


def test_clock_ignores_a_fast_burst_of_agreeing_stamps_during_silence():
    """Two seconds of consistent stamps sent within 20 ms is no evidence of a timeline."""
    clock = C.SampleClock(1e-6, resync_s=1.0)
    stream(clock, 0, 100, 0.0)
    burst = [clock.classify(50_000_000 + i * 1000, 0.2 + i * 1e-5) for i in range(2000)]
    assert all(not v.accepted for v in burst)
    # The real stream resumes (after silence it would be a gap; after the burst it needs
    # the full evidence) and is adopted: none of the burst's stamps is ever used.
    back = stream(clock, 300_000, 1100, 0.3)
    names = [v.verdict for v in back]
    assert "resync" in names and names[-1] == "ok"
    used = [a.ticks for v in back for a in v.accepted]
    assert used[0] == 300_000 and max(used) < 50_000_000


def test_clock_unwraps_uint32_milliseconds():
    clock = C.SampleClock(1e-3)
    stamps = [2**32 - 2, 2**32 - 1, 0, 1]
    v = [clock.classify(s, i * 0.001) for i, s in enumerate(stamps)]
    assert [x.verdict for x in v] == ["first", "ok", "ok", "ok"]
    assert [x.accepted[0].ticks for x in v] == [2**32 - 2, 2**32 - 1, 2**32, 2**32 + 1]
    assert clock.wraps == 1


def test_clock_unwrap_is_not_moved_by_dropped_samples():
    """Stamps one hour ahead (top quarter of the µs counter) or a 0 after 53.7 min of
    uptime used to count as a counter wrap and shift every later sample by 2^32 µs."""
    for forged in ([3_600_000_000] * 3, [0]):
        clock = C.SampleClock(1e-6)
        t0 = 3_222_000_000 if forged == [0] else 1_000_000
        stream(clock, t0, 100, 0.0)
        for i, f in enumerate(forged):
            assert not clock.classify(f + i, 0.1 + i * 1e-4).accepted
        later = stream(clock, t0 + 100_000, 100, 0.1001)
        assert [v.verdict for v in later] == ["ok"] * 100
        assert later[-1].accepted[0].ticks == t0 + 100_000 + 99_000
        assert clock.wraps == 0


@pytest.mark.parametrize("uptime_min", [5.0, 53.7, 60.0, 71.5])
def test_clock_reboot_at_any_uptime_is_a_reboot(uptime_min):
    clock = C.SampleClock(1e-6, resync_s=1.0)
    t0 = int(uptime_min * 60e6) % 2**32
    stream(clock, t0, 500, 0.0)
    # 3 s later the board is back, stamping from 2.5 s after boot.
    after = stream(clock, 2_500_000, 1200, 3.5)
    names = [v.verdict for v in after]
    adopted = names.index("reboot")
    assert 990 <= adopted <= 1001 and "resync" not in names and "ok" in names
    assert after[adopted].accepted[0].ticks == 2_500_000
    assert all(v.verdict == "ok" for v in after[adopted + 1:])


def test_clock_reboot_corroborated_by_system_time_needs_less_evidence():
    clock = C.SampleClock(1e-6, resync_s=1.0)
    stream(clock, 3_500_000_000, 500, 0.0)
    clock.boot_hint = (2.4, 3.4)  # SYSTEM_TIME: 2.4 s since boot, received at 3.4 s
    after = stream(clock, 2_500_000, 600, 3.5)
    assert [v.verdict for v in after].index("reboot") < 300


def test_clock_outage_on_the_same_timeline_is_a_gap():
    clock = C.SampleClock(1e-6)
    stream(clock, 0, 100, 0.0)
    v = clock.classify(1_600_000, 1.6)
    assert v.verdict == "gap" and v.gap_s == pytest.approx(1.501)
    assert clock.classify(1_601_000, 1.601).verdict == "ok"


def test_sequence_tracker_counts_loss_reorder_duplicates():
    t = SequenceTracker()
    for s in [250, 251, 252, 254, 253, 255, 0, 0, 3]:  # 253 late, 0 repeated, 1-2 lost
        t.observe(s)
    assert (t.lost, t.late, t.duplicate) == (2, 1, 1)


@pytest.mark.parametrize("name, v_board, v_body", [
    ("NONE", [1, 2, 3], [1, 2, 3]),
    ("ROTATION_YAW_90", [1, 2, 3], [-2, 1, 3]),  # ArduPilot: x' = -y, y' = x
    ("ROLL_180", [1, 2, 3], [1, -2, -3]),
    ("ROLL_180_YAW_90", [1, 2, 3], [2, 1, -3]),
    ("PITCH_180", [1, 2, 3], [-1, 2, -3]),
])
def test_rotation_names(name, v_board, v_body):
    np.testing.assert_allclose(rotation_matrix(name) @ v_board, v_body, atol=1e-12)


@pytest.mark.parametrize("bad", ["YAW", "YAW_90_ROLL_10", "SPIN_90", "ROLL_x"])
def test_rotation_rejects_unknown_names(bad):
    with pytest.raises(ValueError, match="unknown rotation"):
        rotation_matrix(bad)


def test_parse_url_forms():
    assert parse_url("udpin:0.0.0.0:14550").kind == "udpin"
    assert parse_url("udp:127.0.0.1:14550").kind == "udpin"
    assert parse_url("udpout:10.0.0.2:14550").port == 14550
    assert parse_url("tcp:127.0.0.1:5760").kind == "tcp"
    s = parse_url("/dev/ttyACM0:921600")
    assert (s.kind, s.device, s.baud) == ("serial", "/dev/ttyACM0", 921600)
    for bad in ("udpout:host", "http://x", "tcp:h:0", "udpin:h:70000"):
        with pytest.raises(ValueError, match="bad connection URL"):
            parse_url(bad)
    # IPv6 literals in brackets, as URLs write them: TCP takes them, UDP says it cannot
    # (it said "cannot resolve host '[::1]'")
    assert parse_url("tcp:[::1]:5760").host == "::1"
    with pytest.raises(ValueError, match="UDP links are IPv4 only"):
        parse_url("udpin:[::1]:14550")


def _packet(sysid=1, compid=1, mav=None) -> bytes:
    mav = mav or mavlink.MAVLink(None, sysid, compid)
    return mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3).pack(mav)


def test_codec_survives_and_counts_garbage_crc_and_truncation():
    codec = MavCodec()
    good = _packet()
    bad = bytearray(good)
    bad[12] ^= 0xFF
    assert codec.parse(b"\x00\x01garbage" + good) != []
    assert codec.parse(bytes(bad)) == []
    assert codec.parse(good[:7], datagram=True) == []  # truncated datagram
    assert len(codec.parse(good, datagram=True)) == 1  # the next one is intact
    s = codec.stats
    assert (s.bad_crc, s.truncated, s.messages_in) == (1, 1, 2)
    assert s.bad_frame >= 1


def test_codec_signing_rejects_unsigned_and_accepts_signed():
    key = signing_key_from_text("correct horse battery staple")
    rx = MavCodec(SigningConfig(key))
    tx = MavCodec(SigningConfig(key))
    assert rx.parse(_packet()) == []
    assert rx.stats.unsigned_rejected == 1
    signed = tx.pack(mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3), 1, 1)
    msgs = rx.parse(signed)
    assert len(msgs) == 1 and msgs[0].get_signed()
    wrong = MavCodec(SigningConfig(signing_key_from_text("other")))
    assert rx.parse(wrong.pack(mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3), 1, 2)) == []
    assert rx.stats.bad_signature == 1
    assert rx.parse(signed) == [] and rx.stats.replayed == 1  # the same frame again


def _forged(frame: bytes, timestamp: int) -> bytes:
    """``frame`` with its signing timestamp replaced (the signature no longer matches)."""
    b = bytearray(frame)
    b[-12:-6] = timestamp.to_bytes(6, "little")
    return bytes(b)


def test_codec_signing_lockout_replay_and_allow_unsigned():
    key = signing_key_from_text("correct horse battery staple")
    hb = mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3)
    tx = MavCodec(SigningConfig(key))
    rx = MavCodec(SigningConfig(key))
    assert len(rx.parse(tx.pack(hb, 1, 1))) == 1
    # A forged frame from the vehicle's (link, sysid, compid) with the largest timestamp
    # and a bad signature must not lock the vehicle out.
    assert rx.parse(_forged(tx.pack(hb, 1, 1), 2**48 - 1)) == []
    assert rx.stats.bad_signature == 1
    good = [tx.pack(hb, 1, 1) for _ in range(5)]
    assert all(len(rx.parse(f)) == 1 for f in good)
    # Replayed from another UDP peer: the signing state is the connection's, so the
    # second parser (another peer of the same link) refuses it.
    peer2 = MavCodec(SigningConfig(key), verifier=rx.verifier)
    assert peer2.parse(good[-1]) == [] and peer2.stats.replayed == 1
    # allow_unsigned lets unsigned frames through, never wrongly signed ones.
    lax = MavCodec(SigningConfig(key, allow_unsigned=True))
    assert len(lax.parse(_packet())) == 1 and lax.stats.unsigned_accepted == 1
    other = MavCodec(SigningConfig(signing_key_from_text("other")))
    assert lax.parse(other.pack(hb, 1, 1)) == [] and lax.stats.bad_signature == 1
    assert lax.parse(_forged(tx.pack(hb, 1, 1), 2**48 - 1)) == []


def test_signing_key_sources(tmp_path, monkeypatch):
    hexkey = "ab" * 32
    (tmp_path / "k").write_text(hexkey + "\n")
    assert load_signing_key(f"file:{tmp_path / 'k'}") == bytes.fromhex(hexkey)
    monkeypatch.setenv("BRIDGE_KEY", "pass phrase")
    assert len(load_signing_key("env:BRIDGE_KEY")) == 32
    with pytest.raises(ValueError, match="not set"):
        load_signing_key("env:NOPE_NOT_SET")


def test_ingest_gy86_counts_give_frd_si_and_flag_saturation():
    ingest = Ingest(gy86())
    q = euler_q(20.0, -10.0, 30.0)
    acc, gyr, mag = gy86_counts(q, np.radians([10.0, -5.0, 3.0]))
    msg = mavlink.MAVLink_raw_imu_message(5000, *acc, *gyr, *mag, 0, 0)
    msg.pack(mavlink.MAVLink(None, 1, 1))
    s = ingest.handle(mavlink.MAVLink(None).decode(bytearray(msg.get_msgbuf())))
    np.testing.assert_allclose(s.acc, Q.rotate(Q.conjugate(q), [0, 0, -G]), atol=0.01)
    np.testing.assert_allclose(s.gyr, np.radians([10.0, -5.0, 3.0]), atol=1e-3)
    mag_frd = Q.rotate(Q.conjugate(q), MAG_NED)
    np.testing.assert_allclose(s.mag, mag_frd, atol=2e-3)
    sat = mavlink.MAVLink_raw_imu_message(6000, 32767, 0, 0, -32768, 0, 0, *mag, 0, 0)
    sat.pack(mavlink.MAVLink(None, 1, 1))
    s2 = ingest.handle(mavlink.MAVLink(None).decode(bytearray(sat.get_msgbuf())))
    assert np.all(np.isnan(s2.acc))
    np.testing.assert_array_equal(s2.gyr, s.gyr)  # the clipped gyro holds the last good rate
    counts = next(iter(ingest.sources.values())).counts
    assert counts["acc_saturated"] == 1 and counts["gyro_saturated"] == 1


def test_ingest_rejects_disturbed_magnetometer_strength():
    ingest = Ingest(gy86())
    mav = mavlink.MAVLink(None, 1, 1)
    q = euler_q(0.0, 0.0, 10.0)
    results = []
    for i, extra in enumerate([0, 0, 0, 600, 600, 0]):  # counts: a magnet for 2 samples
        acc, gyr, mag = gy86_counts(q)
        msg = mavlink.MAVLink_raw_imu_message(1000 * (i + 1), *acc, *gyr, mag[0] + extra,
                                              mag[1], mag[2], 0, 0)
        results.append(ingest.handle(mavlink.MAVLink(None).decode(bytearray(msg.pack(mav)))))
    assert [r.mag is None for r in results] == [False, False, False, True, True, False]
    assert next(iter(ingest.sources.values())).counts["mag_disturbed"] == 2


def test_ingest_counts_stuck_readings_only_when_frozen_for_milliseconds():
    """An 8 kHz MPU6050 repeats a reading for a sample or three (its accelerometer
    register changes at 1 kHz): not stuck. A reading re-sent for 20 ms at 1 kHz is, and
    every one of its 20 repeats counts."""
    ingest = Ingest(gy86())
    mav = mavlink.MAVLink(None, 1, 1)

    def raw(t_us, gx):
        m = mavlink.MAVLink_raw_imu_message(t_us, 0, 0, 4096, gx, 0, 0, 100, 0, 200, 0, 0)
        return mavlink.MAVLink(None).decode(bytearray(m.pack(mav)))

    t, gx = 1_000_000, 0
    for i in range(400):  # 8 kHz: each reading held for 1..4 samples (125 µs each)
        if i % 4 == 0 or i % 7 == 0:
            gx += 1
        ingest.handle(raw(t, gx))
        t += 125
    counts = next(iter(ingest.sources.values())).counts
    assert counts["stuck"] == 0
    for _ in range(21):  # 1 kHz: one reading and 20 copies of it
        ingest.handle(raw(t, 999))
        t += 1000
    ingest.handle(raw(t, 1000))
    assert counts["stuck"] == 20


def test_ingest_highres_nonfinite_is_dropped_or_degraded():
    ingest = Ingest(gy86())
    mav = mavlink.MAVLink(None, 1, 1)

    def highres(t, gyr, acc, mag):
        m = mavlink.MAVLink_highres_imu_message(t, *acc, *gyr, *mag, 0, 0, 0, 0, 0, 0)
        return mavlink.MAVLink(None).decode(bytearray(m.pack(mav)))

    assert ingest.handle(highres(1000, [math.nan, 0, 0], [0, 0, -G], [0.2, 0, 0.4])) is None
    s = ingest.handle(highres(2000, [0, 0, 0], [math.inf, 0, -G], [math.nan, 0, 0.4]))
    assert s is not None and np.all(np.isnan(s.acc)) and s.mag is None
    counts = next(iter(ingest.sources.values())).counts
    assert (counts["nonfinite"], counts["acc_invalid"], counts["mag_invalid"]) == (1, 1, 1)


def test_estimator_spec_parsing_and_errors():
    spec = EstimatorSpec.parse("quaternion:exact=false")
    assert spec.name == "quaternion" and spec.params == {"exact": False}
    assert spec.label == "quaternion:exact=False"
    with pytest.raises(ValueError, match="valid"):
        EstimatorSpec.parse("nosuch")
    with pytest.raises(ValueError, match="k=v"):
        EstimatorSpec.parse("quaternion:exact")


def test_config_from_toml_and_validation(tmp_path):
    path = tmp_path / "bridge.toml"
    path.write_text('connect = "udpin:0.0.0.0:14550"\nestimators = ["quaternion"]\n'
                    'outs = ["udpout:127.0.0.1:14551"]\nout_rate = 20.0\n')
    cfg = BridgeConfig.from_toml(path)
    cfg.validate()
    assert cfg.outs == ["udpout:127.0.0.1:14551"] and cfg.out_rate == 20.0
    with pytest.raises(ValueError, match="unknown setting"):
        BridgeConfig.from_dict({"conect": "x"})
    with pytest.raises(ValueError, match="board"):
        BridgeConfig(board="pixhawk").validate()


def test_mqtt_url_settings():
    s = MqttSettings.from_url("mqtts://user:p%40ss@broker.local")
    assert (s.host, s.port, s.tls, s.username, s.password) == (
        "broker.local", 8883, True, "user", "p@ss")
    with pytest.raises(ValueError, match="MQTT URL"):
        MqttSettings.from_url("http://x")


def attitude_grid() -> tuple[np.ndarray, np.ndarray]:
    """Quaternions across pitch [-90°, 90°] (exactly ±90°, within 1e-6 degree and radian
    of it, a sweep between), each with several roll/yaw pairs; and their pitch."""
    edge = [np.pi / 2, np.pi / 2 - 1e-6, np.pi / 2 - np.radians(1e-6), np.pi / 2 - 1e-9]
    pitches = np.concatenate([np.radians(np.linspace(-90.0, 90.0, 37)), edge,
                              -np.array(edge)])
    roll_yaw = np.radians([(25.0, 5.0), (-170.0, 179.0), (120.0, -135.0), (0.0, -90.0)])
    pitch = np.repeat(pitches, len(roll_yaw))
    roll, yaw = np.tile(roll_yaw, (len(pitches), 1)).T
    return Q.from_euler(roll, pitch, yaw), pitch


@async_test
async def test_attitude_message_euler_is_to_euler_at_every_pitch():
    """The ATTITUDE message, sent through a real link and decoded by pymavlink, carries
    estimators.quat.to_euler's angles, and they rebuild the attitude sent — also at and
    next to ±90° pitch, where only yaw ∓ roll is defined (rotations compared there)."""
    qs, pitch = attitude_grid()
    listener = UdpListener()
    port = await listener.start()
    link = open_link(f"udpout:127.0.0.1:{port}")
    await link.start()
    output = AttitudeOutput([link], component_id=191, out_rate=0.0)
    try:
        for k, q in enumerate(qs):
            output.offer(Estimate(SourceKey(1, 1, 27, 0), 0.01 * k, k, q, ZERO3, 0.0))
        done = await wait_until(lambda: len(listener.of_type("ATTITUDE")) == len(qs))
    finally:
        await link.close()
        listener.close()
    assert done
    sent = sorted(listener.of_type("ATTITUDE"), key=lambda m: m.time_boot_ms)
    angles = np.array([[m.roll, m.pitch, m.yaw] for m in sent])  # float32 on the wire
    expected = Q.to_euler(qs)
    wrapped = np.angle(np.exp(1j * (angles - expected)))
    assert np.abs(wrapped).max() < 1e-6
    rebuilt = Q.from_euler(angles[:, 0], angles[:, 1], angles[:, 2])
    assert np.degrees(Q.angle_between(rebuilt, qs)).max() < 1e-3
    locked = np.cos(pitch) < 0.5 * Q.GIMBAL_LOCK_COS
    assert locked.any() and np.all(angles[locked, 0] == 0.0)  # heading all in yaw


def test_compare_finds_lag_and_scores():
    t = np.arange(0.0, 5.0, 0.002)
    yaw = np.radians(30.0) * np.sin(2 * np.pi * 0.5 * t)
    ref = Q.from_euler(0 * t, 0 * t, yaw)
    lagged = Q.from_euler(0 * t, 0 * t, np.radians(30.0) * np.sin(2 * np.pi * 0.5 * (t - 0.04)))
    c = compare_series(t, lagged, t, ref, np.arange(0.0, 0.2, 0.002), score_at_best=False)
    assert c.lag_s == pytest.approx(0.04, abs=0.003)
    assert c.total_deg > 1.0  # scored at zero shift: the lag shows as error
    c2 = compare_series(t, lagged, t, ref, np.arange(-0.1, 0.1, 0.002), score_at_best=True)
    assert c2.total_deg < 0.2 and c2.heading_deg == pytest.approx(c2.total_deg, rel=1e-3)


def test_compare_reports_an_unmeasurable_lag_as_unknown_never_the_grid_end():
    t = np.arange(0.0, 5.0, 0.002)
    yaw = np.radians(30.0) * np.sin(2 * np.pi * 0.5 * t)
    ref = Q.from_euler(0 * t, 0 * t, yaw)
    late = Q.from_euler(0 * t, 0 * t, np.radians(30.0) * np.sin(2 * np.pi * 0.5 * (t - 0.3)))
    grid = np.arange(0.0, 0.2001, 0.002)
    beyond = compare_series(t, late, t, ref, grid, score_at_best=False, open_ends=(False, True))
    assert beyond.lag_s is None and beyond.lag_note.startswith("> 200 ms")
    assert beyond.to_dict()["lag_s"] is None and "lag_note" in beyond.to_dict()
    # On the ground every shift fits alike: no lag, whatever the grid search picks.
    still = Q.from_euler(0 * t, 0 * t, 0 * t + 0.3)
    static = compare_series(t, still, t, still, grid, score_at_best=False)
    assert static.lag_s is None and "does not move" in static.lag_note
    assert static.total_deg < 1e-6  # the errors are still scored
    # A causal estimator on the truth's clock: 0 is a lag (the grid's closed end).
    same = compare_series(t, ref, t, ref, grid, score_at_best=False, open_ends=(False, True))
    assert same.lag_s == 0.0


def test_all_shifts_at_once_equal_each_shift_on_its_own():
    """The compiled search scores every shift as pairing at that shift alone does: the
    same pairs (an estimate series with a hole wider than the gap allowed, a reference
    that runs past its end) and NaN where too few pairs are left."""
    rng = np.random.default_rng(3)
    t_est = np.cumsum(rng.choice([0.0025, 0.005], size=1500))
    t_est = np.delete(t_est, np.arange(600, 640))  # a 0.15 s hole
    q_est = Q.from_euler(0.3 * np.sin(t_est), 0.2 * np.cos(2 * t_est),
                         1.5 * np.sin(0.7 * t_est))
    t_ref = np.arange(0.5, t_est[-1] + 0.4, 0.02)
    q_ref = Q.from_euler(0.3 * np.sin(t_ref - 0.01), 0.2 * np.cos(2 * t_ref),
                         1.5 * np.sin(0.7 * t_ref))
    shifts = np.arange(-0.3, 0.3001, 0.004)
    max_gap = 0.0101
    min_pairs = int(0.92 * len(t_ref))  # the later shifts fall short of it
    rms = rms_at_shifts(t_est, q_est, t_ref, q_ref, shifts, max_gap, min_pairs)
    for shift, got in zip(shifts, rms, strict=True):
        est, ref = pairs_at_shift(t_est, q_est, t_ref, q_ref, float(shift), max_gap)
        if len(est) < min_pairs:
            assert np.isnan(got)
        else:
            assert got == pytest.approx(np.sqrt(np.mean(Q.angle_between(est, ref) ** 2)),
                                        rel=1e-12)
    assert np.isnan(rms).any() and np.isfinite(rms).any()


def test_kernel_filter_keeps_vehicles_and_heartbeats_and_samples_the_rest():
    """The socket filter on a real UDP socket: the admitted vehicle's frames and anyone's
    HEARTBEAT pass whole; other frames are dropped but for a 1/64 sample cut to 3 bytes."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 * 1024 * 1024)
    rx.bind(("127.0.0.1", 0))
    rx.setblocking(False)
    kf = KernelFilter()
    assert kf.attach(rx, {1: frozenset({1}), 5: None})
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle, other = mavlink.MAVLink(None, 1, 1), mavlink.MAVLink(None, 9, 1)
    gimbal, any_comp = mavlink.MAVLink(None, 1, 154), mavlink.MAVLink(None, 5, 77)
    imu = mavlink.MAVLink_raw_imu_message(1000, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    sent = {"vehicle": imu.pack(vehicle), "heartbeat": _packet(mav=other),
            "any_component": imu.pack(any_comp), "gimbal_heartbeat": _packet(mav=gimbal)}
    for data in sent.values():
        tx.sendto(data, rx.getsockname())
    flood = imu.pack(other)
    n = 6400
    for i in range(n):  # half from another system, half from another component
        tx.sendto(flood if i % 2 else imu.pack(gimbal), rx.getsockname())
    time.sleep(0.1)
    got = []
    while True:
        try:
            got.append(rx.recv(65536))
        except BlockingIOError:
            break
    kf.detach(rx)
    rx.close()
    tx.close()
    whole = [g for g in got if len(g) > MARK_LEN]
    marks = [g for g in got if len(g) == MARK_LEN]
    assert whole == list(sent.values())
    assert all(m == flood[:MARK_LEN] for m in marks)  # (the first 3 bytes are alike)
    assert 0.5 * n / SAMPLE <= len(marks) <= 1.5 * n / SAMPLE


@pytest.mark.parametrize("settings, message", [
    ({"declination_deg": math.inf}, "finite"),
    ({"declination_deg": math.nan}, "finite"),
    ({"declination_deg": 200.0}, "declination"),
    ({"estimators": ["eskf:max_dt=-1"]}, "max_dt"),
    ({"estimators": ["mahony:declination=inf"]}, "declination"),
    ({"imu_rate": 0.0}, "imu_rate"),
    ({"out_rate": math.inf}, "out_rate"),
    ({"max_peers": 0}, "max_peers"),
    ({"vehicles": [0]}, "system id"),
    ({"vehicles": ["1"]}, "vehicles"),
    ({"clock_resync_s": -1.0}, "clock_resync_s"),
    ({"gyro_range_dps": math.nan}, "gyro_range_dps"),
    ({"truth_source": "1-1"}, "SYSID:COMPID"),
    ({"jump_s": "fast"}, "jump_s"),
])
def test_config_rejects_every_unusable_setting(settings, message):
    with pytest.raises(ValueError, match=message):
        BridgeConfig(**settings).validate()


def test_admission_budgets_each_sender_and_lets_only_heartbeats_of_strangers_in():
    gate = Admission(rate=100.0, burst=10.0)
    vehicle, other_comp = mavlink.MAVLink(None, 1, 1), mavlink.MAVLink(None, 1, 2)
    stranger = mavlink.MAVLink(None, 9, 1)
    imu = mavlink.MAVLink_raw_imu_message(1000, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    assert gate(imu.pack(stranger))  # learning: nobody admitted yet, all within budget
    gate.admit_vehicle(1)
    assert not gate(imu.pack(stranger)) and gate.stats.not_vehicle == 1
    assert gate(_packet(mav=stranger))  # a stranger's HEARTBEAT
    # Another component of the vehicle floods: it runs out of budget, the vehicle not.
    flood = [gate(imu.pack(other_comp)) for _ in range(100)]
    assert sum(flood) <= 12 and gate.stats.over_budget >= 88
    assert all(gate(imu.pack(vehicle)) for _ in range(10))
    # Once the vehicle's autopilot component is known, other components get heartbeats
    # through only.
    gate.admit_vehicle(1, frozenset({1}))
    refused = gate.stats.not_vehicle
    assert not gate(imu.pack(other_comp)) and gate.stats.not_vehicle == refused + 1
    time.sleep(0.05)  # the vehicle's bucket refills (100/s)
    assert gate(_packet(mav=other_comp)) and gate(imu.pack(vehicle))
    assert gate(b"\x01") and gate.stats.junk_over_budget == 0  # junk: parsed and counted
