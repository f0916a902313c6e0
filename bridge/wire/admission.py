"""Which datagrams are worth parsing at all: refuse floods for the price of a header peek.

Parsing and estimating cost microseconds per message; a flood of 100 k messages/s from
one sender would take the whole CPU and starve the vehicle the bridge is there for.
So before a UDP datagram is parsed, its first frame's header is peeked (the sender's
system id and the message id sit at fixed offsets, MAVLink 1 and 2 alike):

* a sender that is not admitted — another system id, or another component of a served
  vehicle once its autopilot's component is known — gets only its HEARTBEATs through (a
  ground station or a peer bridge announces itself with them and so earns our output;
  anything else it sends is of no use to us) — refused as ``not_vehicle``;
* every sender — (system id, component id) — has its own token bucket of ``rate``
  messages per second (burst ``burst``): a sender over budget is refused as
  ``over_budget`` and cannot use up the time of another, not even of another component
  of the same vehicle. Buckets are indexed by the two header bytes, so their number is
  bounded (65,536) whatever the sender claims;
* bytes that are no MAVLink frame at all share one small bucket (they are parsed only
  to be counted).

The header is not authenticated at this point: a flood that claims the vehicle's own
system and component id shares the vehicle's budget (signing is the defence against
impersonation); everything admitted is still checked in full by the parser.

Until a vehicle is admitted (learning the first autopilot heard), every system id may
send anything within its budget, so that the service can see who is there.

Under a flood (more than ``flood_rate`` refusals per second) even the peek is too
expensive — the socket buffer overflows and the kernel drops the vehicle's packets with
the flood's — so the link attaches the same rule as a kernel socket filter
(:mod:`bridge.wire.kernelfilter`); it passes a 1/SAMPLE sample of what it refuses, counted
here as ``kernel_refused_est`` (SAMPLE each). The filter comes off after ``FILTER_HOLD_S``
once the sampled refusals fall below the flood rate.
"""

from __future__ import annotations

import logging
import time
from array import array
from collections.abc import Callable
from dataclasses import dataclass

from .kernelfilter import MARK_LEN, SAMPLE, Senders

MAGIC_V1, MAGIC_V2 = 0xFE, 0xFD
HEARTBEAT_ID = 0
#: Budget of datagrams that are not MAVLink frames, and of heartbeats from non-vehicles.
JUNK_RATE, JUNK_BURST = 200.0, 200.0
OTHER_RATE, OTHER_BURST = 20.0, 20.0
#: Refusals per second that count as a flood (the kernel filter goes on).
FLOOD_RATE = 2000.0
FLOOD_WINDOW_S = 0.1
FILTER_HOLD_S = 10.0
#: At most one warning about senders over their budget in this long [s].
OVER_BUDGET_WARN_S = 10.0

log = logging.getLogger(__name__)


@dataclass
class AdmissionStats:
    """Datagrams refused before parsing, by cause."""

    not_vehicle: int = 0
    over_budget: int = 0
    junk_over_budget: int = 0
    kernel_refused_est: int = 0  # refused by the kernel filter (SAMPLE per sampled one)
    kernel_filter: bool = False  # the kernel filter is on now
    floods: int = 0  # times the kernel filter went on

    def to_dict(self) -> dict[str, int | bool]:
        return {"not_vehicle": self.not_vehicle, "over_budget": self.over_budget,
                "junk_over_budget": self.junk_over_budget,
                "kernel_refused_est": self.kernel_refused_est,
                "kernel_filter": self.kernel_filter, "floods": self.floods}


class Admission:
    """The gate in front of a UDP link's parser (see module docstring)."""

    def __init__(self, rate: float | None, burst: float | None = None,
                 flood_rate: float = FLOOD_RATE) -> None:
        """``rate`` None: no budget (a trusted in-process source running faster than
        real time, like the built-in emulator's --fast)."""
        self.budget = rate is not None
        rate = 1.0 if rate is None else float(rate)
        self.rate = rate
        self.flood_rate = flood_rate
        #: Called with the admitted senders when a flood starts / with None when the
        #: filter may come off (the link attaches / detaches the kernel filter).
        self.on_flood: Callable[[Senders | None], bool] | None = None
        self.burst = float(burst if burst is not None else max(rate * 0.25, 64.0))
        #: Admitted system ids -> the component ids that may send everything (None: any).
        self.vehicles: dict[int, frozenset[int] | None] = {}
        self.stats = AdmissionStats()
        now = time.monotonic()
        self._tokens = array("d", [self.burst]) * 65536  # by sysid << 8 | compid
        self._stamp = array("d", [now]) * 65536
        self._other_tokens = array("d", [OTHER_BURST]) * 256  # by sysid
        self._other_stamp = array("d", [now]) * 256
        self._junk = (JUNK_BURST, now)
        #: datagrams refused over budget, by sysid << 8 | compid: they never reach the
        #: parser, so the sender's sequence numbers show them as gaps (not link loss)
        self.over_budget_by = array("q", [0]) * 65536
        self._over_budget_told = 0
        self._over_budget_warned = -OVER_BUDGET_WARN_S
        self._last_over_budget = 0
        self._window_start = now
        self._window_refused = 0
        self._filter_since = 0.0
        self._sampled_since_tick = 0

    def admit_vehicle(self, sysid: int, compids: frozenset[int] | None = None) -> None:
        """From now on only admitted senders send more than heartbeats (``compids``: the
        vehicle's components that may, None: any of them)."""
        self.vehicles[sysid] = compids
        self._refilter()

    def forget_vehicle(self, sysid: int) -> None:
        self.vehicles.pop(sysid, None)
        self._refilter()

    def _refilter(self) -> None:
        if self.stats.kernel_filter and self.on_flood is not None:
            self.stats.kernel_filter = self.on_flood(dict(self.vehicles) or None)

    def _refused(self) -> None:
        """Count one refusal of a non-vehicle; start the kernel filter under a flood."""
        self.stats.not_vehicle += 1
        self._window_refused += 1
        if self.stats.kernel_filter or self._window_refused < self.flood_rate * FLOOD_WINDOW_S:
            return
        now = time.monotonic()
        if now - self._window_start > FLOOD_WINDOW_S:
            self._window_start, self._window_refused = now, 0
            return
        if self.on_flood is not None and self.vehicles and self.on_flood(dict(self.vehicles)):
            self.stats.kernel_filter = True
            self.stats.floods += 1
            self._filter_since = now
            self._sampled_since_tick = 0

    def over_budget_of(self, sysid: int) -> int:
        """Datagrams of this system id (any component) refused over budget."""
        return sum(self.over_budget_by[sysid << 8:(sysid + 1) << 8])

    def _warn_over_budget(self) -> None:
        """A sender over its budget is told about (at most every OVER_BUDGET_WARN_S)."""
        now = time.monotonic()
        new = self.stats.over_budget - self._over_budget_told
        if new <= 0 or now - self._over_budget_warned < OVER_BUDGET_WARN_S:
            return
        key = self._last_over_budget
        log.warning("%d datagram(s) refused: over --max-source-rate (%g/s per sender), the "
                    "last from system %d component %d (raise it for a sender this fast)",
                    new, self.rate, key >> 8, key & 0xFF)
        self._over_budget_told, self._over_budget_warned = self.stats.over_budget, now

    def tick(self, elapsed: float) -> None:
        """Called about once a second: say if a sender went over budget; take the kernel
        filter off once the flood ended."""
        self._warn_over_budget()
        if not self.stats.kernel_filter or elapsed <= 0:
            self._window_start, self._window_refused = time.monotonic(), 0
            return
        rate = self._sampled_since_tick * SAMPLE / elapsed
        self._sampled_since_tick = 0
        if rate < self.flood_rate and \
                time.monotonic() - self._filter_since > FILTER_HOLD_S and \
                self.on_flood is not None:
            self.on_flood(None)
            self.stats.kernel_filter = False

    def __call__(self, data: bytes) -> bool:
        n = len(data)
        if n == MARK_LEN and self.stats.kernel_filter:  # the kernel filter's sample
            self.stats.kernel_refused_est += SAMPLE
            self._sampled_since_tick += 1
            return False
        magic = data[0] if n else 0
        if magic == MAGIC_V2 and n >= 10:
            sysid, compid = data[5], data[6]
            msg_id = data[7] | data[8] << 8 | data[9] << 16
        elif magic == MAGIC_V1 and n >= 6:
            sysid, compid = data[3], data[4]
            msg_id = data[5]
        else:
            return self._junk_ok()
        vehicles = self.vehicles
        if vehicles and (sysid not in vehicles or (
                (comps := vehicles[sysid]) is not None and compid not in comps)):
            if msg_id != HEARTBEAT_ID:
                self._refused()
                return False
            return self._take(sysid, self._other_tokens, self._other_stamp, OTHER_RATE,
                              OTHER_BURST)
        if not self.budget:
            return True
        key = sysid << 8 | compid
        if self._take(key, self._tokens, self._stamp, self.rate, self.burst):
            return True
        self.over_budget_by[key] += 1
        self._last_over_budget = key
        return False

    def _take(self, key: int, tokens: array, stamps: array, rate: float,
              burst: float) -> bool:
        now = time.monotonic()
        have = tokens[key] + (now - stamps[key]) * rate
        stamps[key] = now
        if have > burst:
            have = burst
        if have < 1.0:
            tokens[key] = have
            self.stats.over_budget += 1
            return False
        tokens[key] = have - 1.0
        return True

    def _junk_ok(self) -> bool:
        have, stamp = self._junk
        now = time.monotonic()
        have = min(JUNK_BURST, have + (now - stamp) * JUNK_RATE)
        if have < 1.0:
            self._junk = (have, now)
            self.stats.junk_over_budget += 1
            return False
        self._junk = (have - 1.0, now)
        return True
