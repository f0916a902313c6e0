"""The short single-frame path must give exactly what pymavlink gives, or step aside."""

from __future__ import annotations

import numpy as np
import pytest

from bridge.wire.codec import MavCodec, SigningConfig, signing_key_from_text
from bridge.wire.fastframe import _FAST_TYPES, decode_single_frame
from bridge.wire.mav import mavlink

RNG = np.random.default_rng(7)


def _imu_messages() -> list:
    """One of each IMU type with random values, plus ones whose tail is zero (MAVLink 2
    then trims the payload on the wire)."""
    i16 = lambda: int(RNG.integers(-32768, 32768))  # noqa: E731
    f32 = lambda: float(np.float32(RNG.normal(0.0, 10.0)))  # noqa: E731
    msgs = [
        mavlink.MAVLink_raw_imu_message(123456789012, *(i16() for _ in range(9)), 2, -1234),
        mavlink.MAVLink_raw_imu_message(5, 1, 2, 3, 4, 5, 6, 0, 0, 0, 0, 0),  # trimmed
        mavlink.MAVLink_highres_imu_message(987654321, *(f32() for _ in range(13)), 0x1FFF, 1),
        mavlink.MAVLink_highres_imu_message(7, 0.5, *([0.0] * 12), 0, 0),  # trimmed a lot
    ]
    for cls in (mavlink.MAVLink_scaled_imu_message, mavlink.MAVLink_scaled_imu2_message,
                mavlink.MAVLink_scaled_imu3_message):
        msgs.append(cls(4000000000, *(i16() for _ in range(9)), i16()))
    return msgs


_INT_RANGES = {"int8_t": (-128, 128), "uint8_t": (0, 256), "int16_t": (-32768, 32768),
               "uint16_t": (0, 65536), "int32_t": (-2**31, 2**31), "uint32_t": (0, 2**32),
               "uint64_t": (0, 2**63)}


def _random_value(ftype: str):
    if ftype in ("float", "double"):
        return float(np.float32(RNG.normal(0.0, 10.0))) if ftype == "float" else \
            float(RNG.normal(0.0, 10.0))
    lo, hi = _INT_RANGES[ftype]
    return int(RNG.integers(lo, hi))


def _random_message(cls, trimmed: bool):
    """Every field random (arrays included); ``trimmed``: all but the first zero, so that
    MAVLink 2 trims the payload on the wire."""
    args = []
    for k, (ftype, n) in enumerate(zip(cls.fieldtypes, cls.array_lengths, strict=True)):
        value = (lambda: 0) if trimmed and k > 0 else (lambda t=ftype: _random_value(t))
        args.append([value() for _ in range(n)] if n else value())
    return cls(*args)


def _assert_same_as_pymavlink(msg) -> None:
    tx = mavlink.MAVLink(None, 42, 7)
    tx.seq = 200
    data = bytes(msg.pack(tx))
    fast = decode_single_frame(data)
    ref = _reference(data)
    assert fast is not None and type(fast) is type(ref)
    assert fast.to_dict() == ref.to_dict()
    h, r = fast.get_header(), ref.get_header()
    assert (h.msgId, h.seq, h.srcSystem, h.srcComponent, h.mlen, h.incompat_flags,
            h.compat_flags) == (r.msgId, r.seq, r.srcSystem, r.srcComponent, r.mlen,
                                r.incompat_flags, r.compat_flags)
    assert (fast.get_msgId(), fast.get_srcSystem(), fast.get_srcComponent(),
            fast.get_seq()) == (ref.get_msgId(), 42, 7, 200)
    assert fast.get_crc() == ref.get_crc()


@pytest.mark.parametrize("name", sorted(t.cls.msgname for t in _FAST_TYPES.values()))
def test_decodes_every_short_path_type_exactly_like_pymavlink(name):
    """Arrays (the truth's and the attitude's quaternions) and fields the wire reorders
    by size come out as pymavlink builds them."""
    cls = mavlink.mavlink_map[getattr(mavlink, f"MAVLINK_MSG_ID_{name}")]
    for trimmed in (False, True, False):
        _assert_same_as_pymavlink(_random_message(cls, trimmed))


def _reference(data: bytes):
    mav = mavlink.MAVLink(None, 0, 0)
    (msg,) = mav.parse_buffer(data)
    return msg


@pytest.mark.parametrize("index", range(7))
def test_decodes_every_imu_type_exactly_like_pymavlink(index):
    _assert_same_as_pymavlink(_imu_messages()[index])


def test_steps_aside_for_everything_else():
    tx = mavlink.MAVLink(None, 1, 1)
    imu = bytes(_imu_messages()[0].pack(tx))
    heartbeat = bytes(mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3).pack(tx))
    corrupt = bytearray(imu)
    corrupt[15] ^= 0x40
    signer = MavCodec(SigningConfig(signing_key_from_text("k")))
    signed = signer.pack(_imu_messages()[0], 1, 1)
    for data in (heartbeat, imu + imu, imu[:-1], imu + b"\x00", bytes(corrupt), signed,
                 b"", b"\xfd", imu[:12]):
        assert decode_single_frame(data) is None


def test_codec_counts_a_corrupt_imu_datagram_the_fast_path_refused():
    tx = mavlink.MAVLink(None, 1, 1)
    good = bytes(_imu_messages()[0].pack(tx))
    corrupt = bytearray(good)
    corrupt[20] ^= 0x01
    codec = MavCodec()
    assert codec.parse(bytes(corrupt), datagram=True) == []
    assert codec.parse(good + good, datagram=True) != []  # two frames: general parser
    assert len(codec.parse(good, datagram=True)) == 1
    assert (codec.stats.bad_crc, codec.stats.messages_in) == (1, 3)
