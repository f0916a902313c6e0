"""What the bridge keeps about one vehicle it serves, and who may speak for it.

The bridge serves only admitted vehicles: the system ids given with ``--vehicle``, or
else the first autopilot heard (a HEARTBEAT whose autopilot is not
MAV_AUTOPILOT_INVALID). Before any autopilot is heard, the first system id that sends
an IMU stream is admitted provisionally, and gives way to the first real autopilot
heartbeat from another system id (a bare sensor stream cannot hold the slot against
an autopilot). Everything else is refused and counted, so spoofed system ids cost no
state.

Per vehicle, exactly one IMU stream is the primary source (estimated, published): the
first one heard from the vehicle's autopilot component (with ``imu_id``, only that IMU
index), replaced by a stream of the requested message type when one appears, or by
another stream once the primary has been silent for ``source_timeout_s``. Other IMU
streams of the vehicle are refused (``not_primary``): two IMUs interleaved into one
estimate would make it jump between them.

References for the live comparison count only from the vehicle's autopilot component
(truth from the configured source, by default that same component): an attitude
injected by another sender must not decide what the bridge reports as its error.

The object is also the home of the vehicle's other inputs: what its heartbeat says it
is (autopilot, MAV_TYPE: the vehicle model), its velocity for aiding
(:mod:`bridge.vehicle.aiding`), which magnetometer of a PX4 to use
(:mod:`bridge.vehicle.magnetometer`).
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from imu.flight_state import FlightStateTracker

from ..wire.sequence import SequenceTracker
from .address import AddressLock
from .aiding import VelocityAiding
from .clock import ArrivalClock
from .declination import Declination
from .imu_delay import ImuDelay
from .ingest import SourceKey
from .magnetometer import Px4Magnetometer
from .negotiate import StreamNegotiation
from .references import References

log = logging.getLogger(__name__)

#: Per-vehicle sequence trackers (one per sending component) kept at most.
MAX_COMPONENTS = 16
CONFIGURED, HEARTBEAT, PROVISIONAL = "configured", "heartbeat", "imu"

#: Counters of what one vehicle's traffic had refused.
#: IMU samples of other ids, and none of the one --imu-id asks, before that is told.
WRONG_IMU_SAMPLES = 500
REFUSALS = ("not_primary", "other_component", "refs_refused", "refs_invalid",
            "components_untracked", "other_address")


@dataclass
class Vehicle:
    """State of one admitted vehicle."""

    sysid: int
    admitted_by: str = CONFIGURED
    autopilot_compid: int | None = None
    autopilot: int | None = None  # MAV_AUTOPILOT_* of its heartbeat
    mav_type: int | None = None  # MAV_TYPE_* of its heartbeat
    heartbeats: int = 0
    last_heartbeat: float = 0.0  # monotonic
    link: Any = None  # where it talks from: the link and address of its last message
    address: tuple | None = None
    #: the one link and address its autopilot may talk from (others refused)
    talks_from: AddressLock = field(default_factory=AddressLock)
    primary: SourceKey | None = None
    primary_heard: float = 0.0  # monotonic time of the primary's last sample
    source_switches: int = 0
    last_imu: float = 0.0  # monotonic time of the last accepted IMU sample
    last_heard: float = 0.0  # monotonic time of any admitted message
    stream_requests: int = 0
    next_request: float = 0.0
    request_backoff: float = 2.0
    command_acks: int = 0
    boot_hint: tuple[float, float] | None = None  # SYSTEM_TIME: (board s, perf_counter)
    #: board time of unstamped references (a simulator's truth) from their arrival
    arrival_clock: ArrivalClock = field(default_factory=ArrivalClock)
    refs: References | None = None
    aiding: VelocityAiding = field(default_factory=VelocityAiding)
    declination: Declination = field(default_factory=lambda: Declination(0))
    imu_delay: ImuDelay = field(default_factory=lambda: ImuDelay(0))
    negotiation: StreamNegotiation = field(  # the service gives each its settings
        default_factory=lambda: StreamNegotiation(0, 250.0))
    #: a PX4's magnetometer: HIGHRES_IMU's, or the raw SCALED_IMU one (imu.px4_mag)
    px4_mag: Px4Magnetometer = field(default_factory=lambda: Px4Magnetometer(0))
    #: armed / landed state from its own HEARTBEAT and EXTENDED_SYS_STATE (imu.flight_state)
    flight: FlightStateTracker = field(default_factory=FlightStateTracker)
    #: (board time of the last sample before it or None, airborne) of each switch given
    #: to the estimators
    flight_board_switches: deque = field(default_factory=lambda: deque(maxlen=64))
    sequences: dict[int, SequenceTracker] = field(default_factory=dict)
    mqtt_sent_t: dict[Any, float] = field(default_factory=dict)
    samples_at_last_status: int = 0
    refused: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REFUSALS, 0))
    imu_ids_seen: set[int] = field(default_factory=set)  # IMU ids refused for --imu-id
    wrong_imu_told: bool = False

    def __post_init__(self) -> None:
        self.flight.label = f"vehicle {self.sysid}"
        self.talks_from.label = f"vehicle {self.sysid}"
        self.px4_mag.sysid = self.sysid

    def references(self) -> References:
        """The comparison references, created on first use (they are the bulk of the
        per-vehicle memory)."""
        if self.refs is None:
            self.refs = References()
        return self.refs

    def observe_sequence(self, compid: int, seq: int) -> None:
        tracker = self.sequences.get(compid)
        if tracker is None:
            if len(self.sequences) >= MAX_COMPONENTS:
                self.refused["components_untracked"] += 1
                return
            tracker = self.sequences[compid] = SequenceTracker()
        tracker.observe(seq)

    def reference_compid(self) -> int | None:
        """The component whose attitude counts as the vehicle's own."""
        if self.autopilot_compid is not None:
            return self.autopilot_compid
        return self.primary.compid if self.primary is not None else None

    def _other_imu(self, imu: int, wanted: int) -> None:
        """An IMU sample of another id than ``--imu-id`` asks: once many came and none of
        the id asked, say which ids the vehicle sends (each refused sample is counted,
        but a typo in the id would otherwise serve nothing without a word)."""
        self.imu_ids_seen.add(imu)  # at most 256: the id is one byte
        if self.primary is not None or self.wrong_imu_told:
            return
        if self.refused["not_primary"] >= WRONG_IMU_SAMPLES:
            self.wrong_imu_told = True
            log.warning("vehicle %d: no IMU with id %d (--imu-id) in %d samples; it sends "
                        "id(s) %s", self.sysid, wanted, self.refused["not_primary"],
                        ", ".join(map(str, sorted(self.imu_ids_seen))))

    def choose_source(self, key: SourceKey, now: float, imu_id: int | None,
                      preferred_msg: int, source_timeout_s: float) -> tuple[bool, bool]:
        """(use this sample, it starts a new primary) for an IMU sample of ``key``."""
        if self.autopilot_compid is not None and key.compid != self.autopilot_compid:
            self.refused["other_component"] += 1
            return False, False
        if imu_id is not None and key.imu != imu_id:
            self.refused["not_primary"] += 1
            self._other_imu(key.imu, imu_id)
            return False, False
        primary = self.primary
        if primary == key:
            self.primary_heard = now
            return True, False
        replace = primary is None or now - self.primary_heard > source_timeout_s or (
            key.msg == preferred_msg and primary.msg != preferred_msg)
        if not replace:
            self.refused["not_primary"] += 1
            return False, False
        if primary is not None:
            self.source_switches += 1
        self.primary = key
        self.primary_heard = now
        return True, True
