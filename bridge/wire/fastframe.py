"""A short path for the one packet the bridge gets a thousand times a second.

A UDP datagram from a flight controller usually holds exactly one unsigned MAVLink 2
frame, and at IMU rates almost all of them are RAW_IMU / SCALED_IMU* / HIGHRES_IMU.
pymavlink's general parser spends ~10 µs on such a datagram (byte-stream state machine,
then a decoder that handles arrays, strings, signing and MAVLink 1); most of that work
does not apply to these messages, and at 30 k samples/s it is a third of the budget.

:func:`decode_single_imu_frame` handles only that common case and uses pymavlink's own
definitions for everything it knows (payload layout, CRC_EXTRA, message classes), so it
cannot drift from the dialect; checksums come from ``fastcrc`` (pymavlink's own CRC
backend). Anything else — another message, MAVLink 1, a signed frame, several frames,
a bad checksum, a wrong length — returns None and goes the general way, where it is
parsed or counted as before. The result is the same message object pymavlink builds,
with the same header, so nothing downstream can tell the difference (tested).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from fastcrc.crc16 import mcrf4xx

from .mav import MAVLinkMessage, mavlink

MAGIC_V2 = 0xFD
HEADER_LEN = 10  # MAVLink 2: magic, len, incompat, compat, seq, sysid, compid, msgid[3]
CHECKSUM_LEN = 2


@dataclass(frozen=True)
class _FrameType:
    """What pymavlink knows about one message type, in the form the short path needs."""

    cls: type
    msg_id: int
    crc_extra: bytes  # one byte, appended to the checksummed bytes
    payload_size: int  # full (untruncated) payload length
    unpack: Callable[[bytes], tuple]  # struct.Struct.unpack of the payload


def _frame_type(cls: type) -> _FrameType:
    # Only messages whose fields go on the wire in declaration order and hold no arrays:
    # then the unpacked tuple is the constructor's argument list as it stands.
    assert list(cls.orders) == list(range(len(cls.orders))), cls.msgname
    assert all(n == 1 for n in cls.lengths), cls.msgname
    return _FrameType(cls, cls.id, bytes((cls.crc_extra,)), cls.unpacker.size,
                      cls.unpacker.unpack)


_FAST_TYPES: dict[int, _FrameType] = {
    t.msg_id: t for t in map(_frame_type, (
        mavlink.MAVLink_raw_imu_message, mavlink.MAVLink_scaled_imu_message,
        mavlink.MAVLink_scaled_imu2_message, mavlink.MAVLink_scaled_imu3_message,
        mavlink.MAVLink_highres_imu_message))}


def decode_single_imu_frame(data: bytes) -> MAVLinkMessage | None:
    """The IMU message if ``data`` is exactly one valid unsigned MAVLink 2 IMU frame,
    else None (the caller then uses the general parser)."""
    n = len(data)
    if n < HEADER_LEN + CHECKSUM_LEN or data[0] != MAGIC_V2 or data[2] != 0:
        return None  # not MAVLink 2, or signed / unknown incompat flags
    payload_len = data[1]
    if n != HEADER_LEN + payload_len + CHECKSUM_LEN:
        return None  # several frames, or a truncated / padded one
    ftype = _FAST_TYPES.get(data[7] | data[8] << 8 | data[9] << 16)
    if ftype is None or payload_len > ftype.payload_size:
        return None
    crc = data[-2] | data[-1] << 8
    if mcrf4xx(data[1:-2] + ftype.crc_extra) != crc:
        return None  # corrupted: the general parser counts it
    payload = data[HEADER_LEN:-2]
    if payload_len < ftype.payload_size:  # MAVLink 2 trims trailing zero bytes
        payload += bytes(ftype.payload_size - payload_len)
    msg = ftype.cls(*ftype.unpack(payload))
    msg._header = mavlink.MAVLink_header(ftype.msg_id, 0, data[3], payload_len, data[4],
                                         data[5], data[6])
    msg._payload = payload
    msg._crc = crc
    msg._msgbuf = bytearray(data)
    return msg
