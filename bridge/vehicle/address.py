"""Where a vehicle's autopilot talks from: one link and address at a time.

MAVLink's header is not authenticated (signing is the defence): anyone who can reach
the bridge's port can send frames with the vehicle's own system and component id. From
another address such frames would otherwise go into the estimate (a forged gyro turns
the published attitude), take over where stream requests are sent, and claim the
vehicle is armed or in the air. So the autopilot is heard from the link and address
its first message came from; the same ids from elsewhere are refused and counted
(``refused.other_address``) while that address is alive.

A vehicle does move: an autopilot restarted on a new UDP port, a reconnected serial or
TCP link. Once its address has been silent for ``silence_s`` (the IMU source timeout),
the next address it is heard from becomes its own, and the move is logged. A forger can
therefore take over only a vehicle that has stopped talking.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)

#: At most one warning per vehicle in this long [s] about frames from another address.
WARN_EVERY_S = 10.0


def _where(link: Any, address: tuple | None) -> str:
    name = getattr(link, "name", "?")
    return f"{address[0]}:{address[1]} on {name}" if address else str(name)


@dataclass
class AddressLock:
    """The link and address a vehicle's autopilot is heard from (see module docstring)."""

    label: str = "vehicle"
    link: Any = None
    address: tuple | None = None
    heard: float = -math.inf  # monotonic time of its last frame from there
    _refused_since_warning: int = 0
    _warned: float = -math.inf

    def admits(self, link: Any, address: tuple | None, now: float, silence_s: float) -> bool:
        """True for a frame from the vehicle's own link and address (the first one, or a
        new one after ``silence_s`` of silence from the old one); False for one from
        elsewhere while that is alive (warned about, at most every WARN_EVERY_S)."""
        if link is self.link and address == self.address:
            self.heard = now
            return True
        if self.link is None or now - self.heard > silence_s:
            if self.link is not None:
                log.warning("%s now talks from %s (silent for %.1f s at %s)", self.label,
                            _where(link, address), now - self.heard,
                            _where(self.link, self.address))
            self.link, self.address, self.heard = link, address, now
            return True
        self._refused_since_warning += 1
        if now - self._warned >= WARN_EVERY_S:
            log.warning("%s: its system and component id also come from %s while it talks "
                        "from %s: %d frame(s) refused (a forger, or a second link to it; "
                        "MAVLink signing authenticates the vehicle)", self.label,
                        _where(link, address), _where(self.link, self.address),
                        self._refused_since_warning)
            self._warned, self._refused_since_warning = now, 0
        return False
