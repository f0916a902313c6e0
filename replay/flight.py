"""The vehicle's flight state over a recording, and the phases it is scored by.

The replay follows the same policy as the live bridge (``imu.flight_state``): the log's
own HEARTBEAT / EXTENDED_SYS_STATE (tlog) or arming state and land detector (ULog) are
fed through a ``FlightStateTracker`` in time order, and its belief at each IMU sample
goes to the estimators (``Estimator.run(airborne=...)``). Without any report the belief
is "unknown" and ``eskf`` decides from the data.

Phases (for scoring every part of a recording, not only the flight): what the vehicle
reported, not what the estimator believed —
``ground`` (on the ground, still), ``handling`` (disarmed or on the ground and moving:
carried by hand, bench checks), ``takeoff`` (TAKEOFF, or the first ``EDGE_S`` in the air),
``flight`` (in the air), ``landing`` (LANDING), ``touchdown`` (``EDGE_S`` either side of
the report that it is on the ground again), ``unknown`` (no report).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from imu.flight_state import (
    AIRBORNE_LANDED_STATES,
    LANDED_LANDING,
    LANDED_ON_GROUND,
    LANDED_TAKEOFF,
    SOURCE_DATA,
    FlightStateTracker,
    Switch,
    state_name,
)

from .dataset import Recording

PHASES = ("ground", "handling", "takeoff", "flight", "landing", "touchdown", "unknown")
EDGE_S = 2.0  # take-off / touchdown windows around the reported transitions
MOVING_RAD_S = 0.1  # |gyro| above this on the ground (smoothed): being handled
MOVING_SMOOTH_S = 0.5


@dataclass(frozen=True)
class FlightTrack:
    """Per-sample flight state of a recording."""

    airborne: np.ndarray  # (N,) 1 / 0 / NaN: the belief given to the estimators
    phase: np.ndarray  # (N,) index into PHASES
    source: str  # what the belief mostly came from
    switches: tuple[Switch, ...]
    flap_fallbacks: int
    events_source: str

    @property
    def known(self) -> bool:
        return bool(np.isfinite(self.airborne).any())

    def note(self) -> str:
        """One line for the replay summary."""
        if not self.known:
            return ("no flight state in the log: eskf decides from the data when its "
                    "in-flight model applies")
        air = np.nan_to_num(self.airborne) > 0
        text = (f"from {self.events_source} ({self.source}): airborne {100 * air.mean():.0f} % "
                f"of the samples, {len(self.switches)} switch(es)")
        if self.flap_fallbacks:
            text += f"; landed state unreliable {self.flap_fallbacks}x (data decided then)"
        return text

    def bands(self, t: np.ndarray) -> list[tuple[float, float, str]]:
        """Stretches of constant belief (start, end, state name) for a time-axis band."""
        code = np.where(np.isnan(self.airborne), 2, self.airborne).astype(int)
        cuts = [0, *(np.flatnonzero(np.diff(code)) + 1).tolist(), len(code)]
        names = {0: state_name(False), 1: state_name(True), 2: state_name(None)}
        return [(float(t[a]), float(t[b - 1]), names[code[a]])
                for a, b in itertools.pairwise(cuts) if b > a]

    def phase_names(self) -> np.ndarray:
        return np.asarray(PHASES)[self.phase]


def track(rec: Recording) -> FlightTrack:
    """Run the flight-state policy over the recording's own reports."""
    n = rec.n
    airborne = np.full(n, np.nan)
    landed = np.full(n, np.nan)  # reported landed state (for the phases)
    armed = np.full(n, np.nan)
    tracker = FlightStateTracker(label=str(rec.path.name))
    events = sorted(rec.state_events, key=lambda e: e.t)
    times = [e.t for e in events]
    idx = np.searchsorted(rec.t, np.asarray(times, dtype=float), side="left")
    sources: dict[str, int] = {}
    k_prev = 0
    belief, rep_landed, rep_armed = np.nan, np.nan, np.nan
    for e, k in zip(events, idx.tolist(), strict=True):
        k = min(k, n)
        airborne[k_prev:k], landed[k_prev:k], armed[k_prev:k] = belief, rep_landed, rep_armed
        if e.kind == "heartbeat":
            tracker.on_heartbeat(e.t, e.value, e.autopilot)
        elif e.kind == "landed_state":
            tracker.on_extended_sys_state(e.t, e.value)
        elif e.kind == "land_detector":
            tracker.on_land_detector(e.t, bool(e.value))
        elif e.kind == "armed":
            tracker.on_armed(e.t, bool(e.value))
        belief = np.nan if tracker.airborne is None else float(tracker.airborne)
        if tracker.landed_state is not None:
            rep_landed = float(tracker.landed_state)
        if tracker.armed is not None:
            rep_armed = float(tracker.armed)
        sources[tracker.source] = sources.get(tracker.source, 0) + max(k - k_prev, 0)
        k_prev = max(k, k_prev)
    airborne[k_prev:], landed[k_prev:], armed[k_prev:] = belief, rep_landed, rep_armed
    sources[tracker.source] = sources.get(tracker.source, 0) + n - k_prev
    source = max(sources, key=sources.get) if events else SOURCE_DATA
    return FlightTrack(airborne, phases(rec.t, rec.gyr, landed, armed), source,
                       tuple(tracker.switches), tracker.flap_fallbacks,
                       rec.state_events_source or "no reports")


def phases(t: np.ndarray, gyr: np.ndarray, landed: np.ndarray, armed: np.ndarray
           ) -> np.ndarray:
    """Phase index per sample from the reported landed state and arming (see module)."""
    n = len(t)
    out = np.full(n, PHASES.index("unknown"), dtype=np.int8)
    on_ground = (armed == 0) | (landed == LANDED_ON_GROUND)
    in_air = ~on_ground & np.isin(landed, list(AIRBORNE_LANDED_STATES))
    moving = _smoothed_rate(t, gyr) > MOVING_RAD_S
    out[on_ground] = PHASES.index("ground")
    out[on_ground & moving] = PHASES.index("handling")
    out[in_air] = PHASES.index("flight")
    out[in_air & (landed == LANDED_LANDING)] = PHASES.index("landing")
    # the first EDGE_S in the air and the TAKEOFF report: take-off
    air_code = in_air.astype(np.int8)
    starts = np.flatnonzero(np.diff(air_code) == 1) + 1
    ends = np.flatnonzero(np.diff(air_code) == -1) + 1
    if in_air.size and in_air[0]:
        starts = np.concatenate(([0], starts))
    out[in_air & (landed == LANDED_TAKEOFF)] = PHASES.index("takeoff")
    for s in starts:
        out[(t >= t[s]) & (t < t[s] + EDGE_S) & in_air] = PHASES.index("takeoff")
    for e in ends:  # the report "on the ground again": touchdown either side of it
        out[(t >= t[e] - EDGE_S) & (t < t[e] + EDGE_S)] = PHASES.index("touchdown")
    return out


def _smoothed_rate(t: np.ndarray, gyr: np.ndarray) -> np.ndarray:
    """|gyro| averaged over MOVING_SMOOTH_S (a moving mean on the sample grid)."""
    with np.errstate(over="ignore", invalid="ignore"):  # a corrupt 1e308: "moving" (inf)
        rate = np.linalg.norm(gyr, axis=1)
    if len(t) < 2:
        return rate
    step = float(np.median(np.diff(t)))
    # (no wider than the recording: "same" returns the longer of the two)
    w = min(len(rate), max(1, round(MOVING_SMOOTH_S / max(step, 1e-6))))
    return np.convolve(rate, np.ones(w) / w, mode="same")
