"""A short path for the packets the bridge gets hundreds of times a second.

A UDP datagram from a flight controller usually holds exactly one unsigned MAVLink 2
frame, and at IMU rates almost all of them are RAW_IMU / SCALED_IMU* / HIGHRES_IMU, with
a simulator's truth (HIL_STATE_QUATERNION, SIMSTATE) or the autopilot's own attitude
(ATTITUDE_QUATERNION, ATTITUDE) as often beside them. pymavlink's general parser spends
~10 µs on such a datagram (byte-stream state machine, then a decoder that handles
strings, signing and MAVLink 1 and works out each array's place anew); most of that work
does not apply to these messages, and at 30 k samples/s it is a third of the budget.

:func:`decode_single_frame` handles only that common case and uses pymavlink's own
definitions for everything it knows (payload layout, field order, array lengths,
CRC_EXTRA, message classes), so it cannot drift from the dialect; checksums come from
``fastcrc`` (pymavlink's own CRC backend). Anything else — another message, MAVLink 1, a
signed frame, several frames, a bad checksum, a wrong length — returns None and goes the
general way, where it is parsed or counted as before. The result is the same message
object pymavlink builds, with the same header, so nothing downstream can tell the
difference (tested).
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
    #: per constructor argument, (first wire value, count): None when the wire holds the
    #: arguments as they stand (declaration order, no arrays)
    fields: tuple[tuple[int, int], ...] | None


def _frame_type(cls: type) -> _FrameType:
    # The wire sorts fields by size; ``orders[i]`` is declared field i's place there and
    # ``lengths`` the wire fields' element counts (pymavlink's own decode reads them so).
    assert not any(t == "char" for t in cls.fieldtypes), cls.msgname  # no strings here
    fields = None
    if list(cls.orders) != list(range(len(cls.orders))) or any(n != 1 for n in cls.lengths):
        fields = tuple((sum(cls.lengths[:order]), cls.lengths[order]) for order in cls.orders)
    return _FrameType(cls, cls.id, bytes((cls.crc_extra,)), cls.unpacker.size,
                      cls.unpacker.unpack, fields)


_FAST_TYPES: dict[int, _FrameType] = {
    t.msg_id: t for t in map(_frame_type, (
        mavlink.MAVLink_raw_imu_message, mavlink.MAVLink_scaled_imu_message,
        mavlink.MAVLink_scaled_imu2_message, mavlink.MAVLink_scaled_imu3_message,
        mavlink.MAVLink_highres_imu_message, mavlink.MAVLink_hil_state_quaternion_message,
        mavlink.MAVLink_simstate_message, mavlink.MAVLink_attitude_quaternion_message,
        mavlink.MAVLink_attitude_message))}


def decode_single_frame(data: bytes) -> MAVLinkMessage | None:
    """The message if ``data`` is exactly one valid unsigned MAVLink 2 frame of a type
    above, else None (the caller then uses the general parser)."""
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
    values = ftype.unpack(payload)
    if ftype.fields is not None:
        values = [values[first] if count == 1 else list(values[first:first + count])
                  for first, count in ftype.fields]
    msg = ftype.cls(*values)
    msg._header = mavlink.MAVLink_header(ftype.msg_id, 0, data[3], payload_len, data[4],
                                         data[5], data[6])
    msg._payload = payload
    msg._crc = crc
    msg._msgbuf = bytearray(data)
    return msg
