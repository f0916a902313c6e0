"""What the emulated autopilot answers on its link, as the real ones do.

* COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL (511): param1 message id, param2 interval
  [µs] (0 = the default rate, -1 = stop). COMMAND_ACK: ACCEPTED and the stream follows
  (limited to one message per sensor sample); for a message the autopilot has no stream
  of, PX4 and ArduPilot answer MAV_RESULT_FAILED (PX4: ``set_message_interval`` finds
  no stream name; ArduPilot: no ``ap_message`` for the id), the seeds' board
  MAV_RESULT_DENIED. HEARTBEAT's rate cannot be set (FAILED). PX4 also refuses the
  unsupported param3/param4/param7 (response target) options.
  EXTENDED_SYS_STATE starts off; asked with 0 µs it goes at 1 Hz (a board without a
  flight state has no such stream: refused like any unknown message).
* MAV_CMD_GET_MESSAGE_INTERVAL (510): MESSAGE_INTERVAL (-1 stopped, 0 not available),
  then COMMAND_ACK.
* MAV_CMD_REQUEST_MESSAGE (512), param1 message id: HEARTBEAT and EXTENDED_SYS_STATE
  are made at once with the flight state of the stream's current instant and sent with
  an ACCEPTED COMMAND_ACK (PX4: the message, then the ACK; ArduPilot queues the message,
  so its ACK goes first); any other stream the board has sends its next sample once
  (ACCEPTED now, the message with the next sample / reading / fix); a message it has
  no stream of is refused with the personality's ``request_refused_result`` (PX4 and
  the seeds' board DENIED, ArduPilot FAILED).
* any other command: COMMAND_ACK MAV_RESULT_UNSUPPORTED.
* PARAM_REQUEST_READ / PARAM_REQUEST_LIST: the declination parameter (PX4
  ``EKF2_MAG_DECL`` in degrees, ArduPilot ``COMPASS_DEC`` in radians, both REAL32) from
  the emulator's World Magnetic Model field, and the personality's other parameters
  (ArduPilot ``INS_GYRO_FILTER``); unknown names get no answer (MAVLink's
  parameter protocol), and the seeds' board has no parameters.

Messages for another system or component are ignored, like on a real autopilot.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable
from dataclasses import dataclass

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink

from .personality import NATURAL, Personality
from .streams import OFF, StreamTable

log = logging.getLogger(__name__)


@dataclass
class Requests:
    """What the link asked for, counted (part of the emulator's stats)."""

    interval_accepted: int = 0
    interval_refused: int = 0
    other_commands: int = 0
    message_accepted: int = 0  # MAV_CMD_REQUEST_MESSAGE
    message_refused: int = 0
    param_reads: int = 0
    ignored: int = 0  # for another system/component, or not understood

    def to_dict(self) -> dict:
        return dict(self.__dict__)


class CommandHandler:
    """Replies to what a listener sends. ``now_message(kind)`` makes a message of that
    kind for the current instant of the stream (None if it cannot: then a requested
    message goes out with the stream's next candidate)."""

    def __init__(self, who: Personality, streams: StreamTable, sysid: int, compid: int,
                 declination_deg: float, counts: Requests,
                 now_message: Callable[[str], object | None] | None = None):
        self.who = who
        self.now_message = now_message
        self.streams = streams
        self.sysid, self.compid = sysid, compid
        self.counts = counts
        self.params: dict[str, float] = {}
        if who.declination_param is not None:
            value = (declination_deg if who.declination_unit == "deg"
                     else math.radians(declination_deg))
            self.params[who.declination_param] = value
        self.params.update(who.params)

    def handle(self, msg) -> list:
        """Replies (pymavlink messages) to one received message."""
        kind = msg.get_type()
        if kind == "COMMAND_LONG":
            if not self._for_me(msg.target_system, msg.target_component):
                self.counts.ignored += 1
                return []
            return self._command(msg)
        if kind in ("PARAM_REQUEST_READ", "PARAM_REQUEST_LIST"):
            if not self._for_me(msg.target_system, msg.target_component):
                self.counts.ignored += 1
                return []
            self.counts.param_reads += 1
            return self._params(msg)
        return []

    def _for_me(self, system: int, component: int) -> bool:
        return system in (0, self.sysid) and component in (0, self.compid)

    def _ack(self, msg, result: int) -> mavlink.MAVLink_message:
        return mavlink.MAVLink_command_ack_message(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())

    def _command(self, msg) -> list:
        if msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(msg)
            if result == mavlink.MAV_RESULT_ACCEPTED:
                self.counts.interval_accepted += 1
            else:
                self.counts.interval_refused += 1
            return [self._ack(msg, result)]
        if msg.command == mavlink.MAV_CMD_GET_MESSAGE_INTERVAL:
            kind = _message_name(msg.param1)
            interval = self.streams.interval(kind) if kind else OFF
            if not kind or not self.streams.knows(kind):
                us = 0
            elif interval is NATURAL:
                us = 1  # every sample: report the shortest interval
            elif interval == OFF:
                us = -1
            else:
                us = round(interval * 1e6)
            return [mavlink.MAVLink_message_interval_message(int(msg.param1), us),
                    self._ack(msg, mavlink.MAV_RESULT_ACCEPTED)]
        if msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            return self._request_message(msg)
        self.counts.other_commands += 1
        return [self._ack(msg, mavlink.MAV_RESULT_UNSUPPORTED)]

    def _set_interval(self, msg) -> int:
        who = self.who
        if not (math.isfinite(msg.param1) and math.isfinite(msg.param2)):
            return mavlink.MAV_RESULT_FAILED
        if who.name == "px4" and any(math.isfinite(p) and round(p) != 0
                                     for p in (msg.param3, msg.param4, msg.param7)):
            return mavlink.MAV_RESULT_FAILED
        kind = _message_name(msg.param1)
        if kind == "HEARTBEAT":
            return mavlink.MAV_RESULT_FAILED
        if kind is None or not self.streams.knows(kind):
            log.info("%s autopilot: no %s stream, SET_MESSAGE_INTERVAL refused", who.name,
                     kind or f"message id {msg.param1:g}")
            return who.refused_result
        us = msg.param2
        if us < -0.5:
            interval = OFF
        elif us < 0.5:
            interval = self.streams.default_interval(kind)
        else:
            interval = us * 1e-6
            if who.whole_ms:  # ArduPilot keeps whole milliseconds, at least 1
                interval = max(1, int(us // 1000)) * 1e-3
        self.streams.set_interval(kind, interval)
        log.info("%s autopilot: %s every %s", who.name, kind,
                 "sample" if interval is NATURAL else
                 ("(stopped)" if interval == OFF else f"{interval * 1e3:g} ms"))
        return mavlink.MAV_RESULT_ACCEPTED

    def _request_message(self, msg) -> list:
        who = self.who
        kind = _message_name(msg.param1)
        made = self.now_message(kind) if kind is not None and self.now_message else None
        if made is None and kind is not None and self.streams.knows(kind):
            self.streams.request_once(kind)  # goes out with the next candidate
        elif made is None:
            log.info("%s autopilot: no %s stream, REQUEST_MESSAGE refused", who.name,
                     kind or f"message id {msg.param1:g}")
            self.counts.message_refused += 1
            return [self._ack(msg, who.request_refused_result)]
        self.counts.message_accepted += 1
        ack = self._ack(msg, mavlink.MAV_RESULT_ACCEPTED)
        if made is None:
            return [ack]
        return [ack, made] if who.ack_before_requested else [made, ack]

    def _params(self, msg) -> list:
        names = list(self.params)
        if msg.get_type() == "PARAM_REQUEST_LIST":
            picked = names
        else:
            name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode()
            name = name.rstrip("\x00")
            if msg.param_index >= 0:
                picked = names[msg.param_index:msg.param_index + 1]
            else:
                picked = [name] if name in self.params else []
            if not picked:
                log.info("%s autopilot: no parameter %r", self.who.name,
                         name or msg.param_index)
        return [mavlink.MAVLink_param_value_message(
            n.encode(), self.params[n], mavlink.MAV_PARAM_TYPE_REAL32, len(names),
            names.index(n)) for n in picked]


def _message_name(msg_id: float) -> str | None:
    """MAVLink message name of an id (None if unknown)."""
    if not math.isfinite(msg_id):
        return None
    cls = mavlink.mavlink_map.get(int(msg_id))
    return None if cls is None else cls.msgname
