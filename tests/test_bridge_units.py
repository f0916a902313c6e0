"""Unit tests of the bridge's pure parts: clock verdicts, sequence loss, rotations,
codec (bad bytes, signing), ingest scaling, URL/estimator parsing, comparison."""

from __future__ import annotations

import math

import numpy as np
import pytest
from bridge_support import MAG_NED, G, euler_q, gy86_counts

from bridge import clock as C
from bridge.codec import MavCodec, SigningConfig, load_signing_key, signing_key_from_text
from bridge.compare import compare_series
from bridge.config import BridgeConfig
from bridge.ingest import Ingest
from bridge.links import parse_url
from bridge.mav import mavlink
from bridge.mqtt import MqttSettings
from bridge.output import euler_zyx
from bridge.sequence import SequenceTracker
from estimators import quat as Q
from estimators.spec import EstimatorSpec
from imu.boards import gy86
from imu.rotations import rotation_matrix


def verdicts(clock: C.SampleClock, stamps: list[int]) -> list[str]:
    return [clock.classify(s)[0] for s in stamps]


def test_clock_accepts_steady_stream_with_dt():
    clock = C.SampleClock(1e-6)
    assert clock.classify(1000)[0] == C.FIRST
    v, ticks, dt = clock.classify(2000)
    assert (v, ticks) == (C.OK, 2000) and dt == pytest.approx(1e-3)


def test_clock_duplicate_reordered_and_isolated_glitches():
    clock = C.SampleClock(1e-6)
    v = verdicts(clock, [0, 1000, 2000, 2000, 4000, 3000, 5000, 900_000, 6000,
                         -400_000 + 2**40, 7000])
    assert v == ["first", "ok", "ok", "duplicate", "ok", "reordered", "ok", "jump", "ok",
                 "jump", "ok"]
    late = C.SampleClock(1e-6)
    assert verdicts(late, [1_000_000, 1_001_000, 100]) == ["first", "ok", "backwards"]


def test_clock_resyncs_after_a_permanent_step_and_reclassifies():
    clock = C.SampleClock(1e-6)
    verdicts(clock, list(range(0, 10_000, 1000)))
    # The board clock steps forward by 0.5 s and stays there.
    v = verdicts(clock, [510_000, 511_000, 512_000, 513_000])
    assert v == ["jump", "jump", "resync", "ok"]
    assert clock.reclassified == [] or clock.reclassified == ["jump", "jump"]
    # ... and backwards by 50 ms (inside the reorder window).
    v = verdicts(clock, [464_000, 465_000, 466_000, 467_000])
    assert v == ["reordered", "reordered", "resync", "ok"]


def test_clock_unwraps_uint32_milliseconds():
    clock = C.SampleClock(1e-3)
    stamps = [2**32 - 2, 2**32 - 1, 0, 1]
    v = [clock.classify(s) for s in stamps]
    assert [x[0] for x in v] == ["first", "ok", "ok", "ok"]
    assert [x[1] for x in v] == [2**32 - 2, 2**32 - 1, 2**32, 2**32 + 1]
    assert clock.wraps == 1


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
    assert rx.stats.unsigned_rejected == 2


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


def test_euler_matches_quat_module():
    q = euler_q(10.0, -20.0, 170.0)
    np.testing.assert_allclose(euler_zyx(q), Q.to_euler(q), atol=1e-12)


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
