"""Bytes <-> MAVLink messages for one connection: parsing, packing, optional signing.

Transports (``links``) only move bytes; this class owns the pymavlink state. It keeps
one packer per source system id so that sequence numbers run per sender, as MAVLink
requires when the bridge speaks for several vehicles on one link.
"""

from __future__ import annotations

import hashlib
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from .fastframe import decode_single_imu_frame
from .mav import MAVLink, MAVLinkMessage, mavlink

#: MAVLink signing timestamps count 10 µs units since 2015-01-01 00:00 UTC.
_SIGNING_EPOCH = 1420070400.0


@dataclass(frozen=True)
class SigningConfig:
    """A MAVLink 2 signing secret shared by both ends of a link."""

    key: bytes  # 32 bytes
    link_id: int = 0
    allow_unsigned: bool = False  # accept unsigned input (counted) instead of rejecting it

    def __post_init__(self) -> None:
        if len(self.key) != 32:
            raise ValueError(f"a MAVLink signing key has 32 bytes, got {len(self.key)}")


def signing_key_from_text(text: str) -> bytes:
    """64 hex digits are the key itself; anything else is a passphrase, hashed (SHA-256)."""
    text = text.strip()
    try:
        if len(text) == 64:
            return bytes.fromhex(text)
    except ValueError:
        pass
    if not text:
        raise ValueError("empty MAVLink signing key")
    return hashlib.sha256(text.encode()).digest()


def load_signing_key(spec: str) -> bytes:
    """Key from ``env:NAME`` (an environment variable) or ``file:PATH`` / a plain path."""
    if spec.startswith("env:"):
        name = spec[4:]
        value = os.environ.get(name)
        if value is None:
            raise ValueError(f"signing key environment variable {name!r} is not set")
        return signing_key_from_text(value)
    path = Path(spec[5:] if spec.startswith("file:") else spec)
    try:
        return signing_key_from_text(path.read_text())
    except OSError as exc:
        raise ValueError(f"cannot read signing key file {path}: {exc}") from None


def _signing_now() -> int:
    return int((time.time() - _SIGNING_EPOCH) * 1e5)


def _apply_signing(mav: MAVLink, signing: SigningConfig) -> None:
    mav.signing.secret_key = signing.key
    mav.signing.link_id = signing.link_id
    mav.signing.timestamp = _signing_now()
    mav.signing.sign_outgoing = True
    allow = signing.allow_unsigned
    mav.signing.allow_unsigned_callback = lambda _mav, _msg_id: allow


@dataclass
class CodecStats:
    """Counters of one connection's input, by what went wrong."""

    bytes_in: int = 0
    messages_in: int = 0
    messages_out: int = 0
    bad_crc: int = 0  # checksum mismatch: corrupted on the wire
    bad_frame: int = 0  # junk between frames, truncated or malformed frames
    unsigned_rejected: int = 0  # unsigned or wrongly signed input while signing is on
    unknown_message: int = 0  # valid frame of a message id outside the dialect
    truncated: int = 0  # datagrams ending in an incomplete packet
    reasons: dict[str, int] = field(default_factory=dict)

    def count_bad(self, reason: str) -> None:
        if "signature" in reason:
            self.unsigned_rejected += 1
        elif "CRC" in reason:
            self.bad_crc += 1
        else:
            self.bad_frame += 1
        key = reason.split(" in msgID")[0][:40]
        self.reasons[key] = self.reasons.get(key, 0) + 1


class MavCodec:
    """Parser for one byte stream plus per-sender packers sharing one signing setup."""

    def __init__(self, signing: SigningConfig | None = None) -> None:
        self.signing = signing
        self.stats = CodecStats()
        self._parser = self._new_mav(0, 0)
        self._packers: dict[tuple[int, int], MAVLink] = {}

    def _new_mav(self, sysid: int, compid: int) -> MAVLink:
        mav = MAVLink(None, sysid, compid)
        mav.robust_parsing = True  # bad input becomes MAVLink_bad_data, not an exception
        if self.signing is not None:
            _apply_signing(mav, self.signing)
        return mav

    def reset_parser(self) -> None:
        """Forget buffered partial input (after a reconnect)."""
        self._discard_partial()

    def parse(self, data: bytes, datagram: bool = False) -> list[MAVLinkMessage]:
        """All complete, valid messages in ``data``; everything else is counted.

        ``datagram=True``: ``data`` is one UDP datagram, which carries whole packets
        only, so an incomplete packet at its end is truncated garbage: counted and
        discarded rather than glued to the start of the next datagram.
        """
        self.stats.bytes_in += len(data)
        if datagram and self.signing is None:
            msg = decode_single_imu_frame(data)  # the common case, without the state machine
            if msg is not None:
                self.stats.messages_in += 1
                return [msg]
        msgs = self._parse(data)
        if datagram and self._parser.buf_len() > 0:
            self.stats.truncated += 1
            self._discard_partial()
        return msgs

    def _discard_partial(self) -> None:
        p = self._parser
        p.buf = bytearray()
        p.buf_index = 0
        p.expected_length = mavlink.HEADER_LEN_V1 + 2

    def _parse(self, data: bytes) -> list[MAVLinkMessage]:
        try:
            msgs = self._parser.parse_buffer(data)
        except Exception as exc:  # pymavlink raising on input is a bug we must survive
            self.stats.count_bad(f"parser error {type(exc).__name__}")
            self._parser = self._new_mav(0, 0)
            return []
        if not msgs:
            return []
        good = []
        for msg in msgs:
            if isinstance(msg, mavlink.MAVLink_bad_data):
                self.stats.count_bad(str(msg.reason))
            elif isinstance(msg, mavlink.MAVLink_unknown):
                self.stats.unknown_message += 1
            else:
                good.append(msg)
        self.stats.messages_in += len(good)
        return good

    def pack(self, msg: MAVLinkMessage, sysid: int, compid: int) -> bytes:
        """Encode ``msg`` as sent by (sysid, compid), advancing that sender's sequence."""
        mav = self._packers.get((sysid, compid))
        if mav is None:
            mav = self._packers[(sysid, compid)] = self._new_mav(sysid, compid)
        buf = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
        self.stats.messages_out += 1
        return buf
