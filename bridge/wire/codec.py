"""Bytes <-> MAVLink messages for one connection: parsing, packing, optional signing.

Transports (``links``) only move bytes; this class owns the pymavlink state. It keeps
one packer per source system id so that sequence numbers run per sender, as MAVLink
requires when the bridge speaks for several vehicles on one link.

Signatures are checked here, not by pymavlink: pymavlink stores a frame's signing
timestamp *before* it verifies the signature (one forged frame with timestamp 2^48-1
locks the sender out for good) and keeps that state per parser, i.e. per UDP peer (a
replay from a new port passes). :class:`SigningState` keeps the last timestamp per
(link id, sysid, compid) for the whole connection and stores it only after the
signature is verified; ``allow_unsigned`` lets *unsigned* frames through (counted) but
never wrongly signed or replayed ones.
"""

from __future__ import annotations

import hashlib
import os
import string
import time
from dataclasses import dataclass, field
from pathlib import Path

from .fastframe import decode_single_frame
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


#: Hex digits in a MAVLink signing key written out (32 bytes).
KEY_HEX_DIGITS = 64


def signing_key_from_text(text: str) -> bytes:
    """64 hex digits are the key itself; anything else is a passphrase, hashed (SHA-256).

    Except a long run of hex digits that is not 64 (from 32): that is a key copied with
    a digit missing or added, and hashing it as a passphrase would sign with a key the
    autopilot does not have, each frame refused there without a word here."""
    text = text.strip()
    if not text:
        raise ValueError("empty MAVLink signing key")
    hex_only = all(c in string.hexdigits for c in text)
    if hex_only and len(text) == KEY_HEX_DIGITS:
        return bytes.fromhex(text)
    if hex_only and len(text) >= KEY_HEX_DIGITS // 2:
        raise ValueError(f"the signing key has {len(text)} hex digits; a key has "
                         f"{KEY_HEX_DIGITS} (a passphrase is taken when it is not all hex "
                         f"digits)")
    return hashlib.sha256(text.encode()).digest()


#: Longest signing key file read: 64 hex digits or a passphrase, with room to spare.
MAX_KEY_FILE_BYTES = 4096


def load_signing_key(spec: str) -> bytes:
    """Key from ``env:NAME`` (an environment variable) or ``file:PATH`` / a plain path."""
    if spec.startswith("env:"):
        name = spec[4:]
        value = os.environ.get(name)
        if value is None:
            raise ValueError(f"signing key environment variable {name!r} is not set")
        return signing_key_from_text(value)
    name = spec[5:] if spec.startswith("file:") else spec
    if not name.strip():
        raise ValueError("no signing key file given (an empty --signing-key)")
    path = Path(name)
    try:
        with path.open("rb") as f:  # a key is short: /dev/zero must not fill the memory
            data = f.read(MAX_KEY_FILE_BYTES + 1)
    except OSError as exc:
        raise ValueError(f"cannot read signing key file {path}: "
                         f"{exc.strerror or exc}") from None
    if len(data) > MAX_KEY_FILE_BYTES:
        raise ValueError(f"signing key file {path}: longer than {MAX_KEY_FILE_BYTES} bytes, "
                         f"not a key (64 hex digits or a passphrase)")
    try:
        return signing_key_from_text(data.decode("utf-8"))
    except UnicodeDecodeError:
        raise ValueError(f"signing key file {path}: not text (64 hex digits or a "
                         f"passphrase)") from None


def _signing_now() -> int:
    return int((time.time() - _SIGNING_EPOCH) * 1e5)


def _apply_signing(mav: MAVLink, signing: SigningConfig) -> None:
    """Sign what ``mav`` packs (it never verifies: parsers get no key, see SigningState)."""
    mav.signing.secret_key = signing.key
    mav.signing.link_id = signing.link_id
    mav.signing.timestamp = _signing_now()
    mav.signing.sign_outgoing = True


#: A new signed stream is accepted if its timestamp is at most this far behind our clock
#: (10 µs units: one minute, as the MAVLink signing specification suggests).
NEW_STREAM_WINDOW = 60 * 100_000
#: Signed streams remembered per connection; beyond it the stalest is forgotten.
MAX_SIGNED_STREAMS = 1024
SIGNED, UNSIGNED_OK, UNSIGNED, BAD_SIGNATURE, REPLAYED = (
    "signed", "unsigned_ok", "unsigned", "bad_signature", "replayed")


class SigningState:
    """Verification of incoming signed frames for one connection (all its peers)."""

    def __init__(self, config: SigningConfig) -> None:
        self.config = config
        self.streams: dict[tuple[int, int, int], int] = {}  # -> last verified timestamp

    def check(self, frame: bytes | bytearray, sysid: int, compid: int) -> str:
        """The verdict on one whole MAVLink frame (header to signature)."""
        if len(frame) < 13 or frame[0] != mavlink.PROTOCOL_MARKER_V2 or \
                not frame[2] & mavlink.MAVLINK_IFLAG_SIGNED:
            return UNSIGNED_OK if self.config.allow_unsigned else UNSIGNED
        link_id = frame[-13]
        timestamp = int.from_bytes(frame[-12:-6], "little")
        digest = hashlib.sha256(self.config.key + bytes(frame[:-6])).digest()[:6]
        if digest != bytes(frame[-6:]):
            return BAD_SIGNATURE  # nothing is stored for a frame we cannot trust
        key = (link_id, sysid, compid)
        last = self.streams.get(key)
        if last is None:
            if timestamp + NEW_STREAM_WINDOW < _signing_now():
                return REPLAYED
        elif timestamp <= last:
            return REPLAYED
        if last is None and len(self.streams) >= MAX_SIGNED_STREAMS:
            del self.streams[min(self.streams, key=self.streams.__getitem__)]
        self.streams[key] = timestamp
        return SIGNED


@dataclass
class CodecStats:
    """Counters of one connection's input, by what went wrong."""

    bytes_in: int = 0
    messages_in: int = 0
    messages_out: int = 0
    bad_crc: int = 0  # checksum mismatch: corrupted on the wire
    bad_frame: int = 0  # junk between frames, truncated or malformed frames
    unsigned_rejected: int = 0  # unsigned input while signing is required
    unsigned_accepted: int = 0  # unsigned input let through by allow_unsigned
    bad_signature: int = 0  # signed with another key, or forged
    replayed: int = 0  # a signing timestamp not newer than the stream's last one
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

    def __init__(self, signing: SigningConfig | None = None,
                 verifier: SigningState | None = None) -> None:
        self.signing = signing
        self.verifier = verifier or (SigningState(signing) if signing is not None else None)
        self.stats = CodecStats()
        self._parser = self._new_parser()
        self._packers: dict[tuple[int, int], MAVLink] = {}

    @staticmethod
    def _new_parser() -> MAVLink:
        mav = MAVLink(None, 0, 0)
        mav.robust_parsing = True  # bad input becomes MAVLink_bad_data, not an exception
        return mav

    def _new_packer(self, sysid: int, compid: int) -> MAVLink:
        mav = MAVLink(None, sysid, compid)
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
            msg = decode_single_frame(data)  # the common case, without the state machine
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
            self._parser = self._new_parser()
            return []
        if not msgs:
            return []
        good = []
        for msg in msgs:
            if isinstance(msg, mavlink.MAVLink_bad_data):
                self.stats.count_bad(str(msg.reason))
            elif isinstance(msg, mavlink.MAVLink_unknown):
                self.stats.unknown_message += 1
            elif self.verifier is None or self._verified(msg):
                good.append(msg)
        self.stats.messages_in += len(good)
        return good

    def _verified(self, msg: MAVLinkMessage) -> bool:
        assert self.verifier is not None
        verdict = self.verifier.check(msg.get_msgbuf(), msg.get_srcSystem(),
                                      msg.get_srcComponent())
        if verdict == SIGNED:
            msg._signed = True
            return True
        if verdict == UNSIGNED_OK:
            self.stats.unsigned_accepted += 1
            return True
        if verdict == UNSIGNED:
            self.stats.unsigned_rejected += 1
        elif verdict == BAD_SIGNATURE:
            self.stats.bad_signature += 1
        else:
            self.stats.replayed += 1
        return False

    def pack(self, msg: MAVLinkMessage, sysid: int, compid: int) -> bytes:
        """Encode ``msg`` as sent by (sysid, compid), advancing that sender's sequence."""
        mav = self._packers.get((sysid, compid))
        if mav is None:
            mav = self._packers[(sysid, compid)] = self._new_packer(sysid, compid)
        if self.signing is not None:  # our timestamps follow real time (peers check them)
            mav.signing.timestamp = max(mav.signing.timestamp, _signing_now())
        buf = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
        self.stats.messages_out += 1
        return buf
