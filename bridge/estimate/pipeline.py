"""Estimators per IMU source: every accepted sample goes through all of them.

The first estimator spec is the primary one: its attitude is what the bridge sends
over MAVLink. All of them keep a short history for the live comparison and are
published on MQTT.

What the estimators are told about the vehicle comes per vehicle (:class:`VehicleSetup`):
its magnetic declination (the output's true north) and its model (a multirotor runs
``eskf`` with the rotor-drag model, :mod:`bridge.vehicle.model`). Either may only become known
after the first samples (a parameter answered, the first position, the heartbeat):

* a new declination turns every estimator's output in place
  (``Estimator.set_declination``): the estimate itself lives in magnetic north and is
  kept, so nothing re-converges;
* a new model rebuilds the estimators (another filter structure). Learned soon after
  the estimate started (an autopilot's first heartbeat comes after its first IMU
  samples), the samples so far run again through the rebuilt estimators, so the estimate
  is the one the model would have given from the first sample (a replay of the same
  log knows the model from the start, and says the same). Learned later, the estimate
  restarts like after a reboot, its output held while it settles: running minutes of
  samples again would stall the service.

A sample marked ``restart`` (the vehicle rebooted, or came back after an outage) resets
every estimator through its public API: the old attitude is stale and must not be
published as if it were current. The estimate then counts as initialising until the
estimator has initialised and ``settle_s`` of board time has passed.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

import estimators
from estimators.spec import EstimatorSpec

from ..vehicle.ingest import ImuSample, SourceKey
from ..vehicle.model import UNKNOWN, model_defaults
from ..vehicle.ring import TimeRing

log = logging.getLogger(__name__)


@dataclass
class VehicleSetup:
    """What the estimators of one vehicle are told about it."""

    declination_rad: float = 0.0
    model: str = UNKNOWN
    airborne: bool | None = None  # what the vehicle says it is doing (imu.flight_state)
    imu_delay_s: float = 0.0  # how old its IMU samples are (imu.filter_delay)


@dataclass(slots=True)
class Estimate:
    """The primary estimator's output for one sample, ready to publish."""

    key: SourceKey
    t: float  # board time [s]
    time_boot_ms: int
    q: np.ndarray  # [w, x, y, z] body FRD -> NED
    rates: np.ndarray  # bias-corrected body rates [rad/s]
    arrival: float  # perf_counter() when the IMU packet was read
    initialising: bool = False  # re-converging after a restart: not to be trusted yet


#: How much of a (re)started estimate a new model runs again through the rebuilt
#: estimators: an autopilot's heartbeat (1 Hz) comes within its first second; the
#: sample cap bounds the memory and the stall of the catch-up at fast IMU rates.
CATCH_UP_S = 3.0
CATCH_UP_SAMPLES = 6000


@dataclass(slots=True)
class _Given:
    """One sample as the estimators were given it (kept to run it again)."""

    sample: ImuSample
    vel: np.ndarray | None
    vel_age: float
    airborne: bool | None


class SourcePipeline:
    """All estimators of one source, with a short history of each one's attitude."""

    def __init__(self, key: SourceKey, specs: list[EstimatorSpec], rate_hz: float,
                 history: int, declination_rad: float = 0.0, settle_s: float = 1.0,
                 model: str = UNKNOWN, airborne: bool | None = None,
                 imu_delay_s: float = 0.0) -> None:
        self.key = key
        self.airborne = airborne
        self.specs = specs
        self.rate_hz = rate_hz
        self.settle_s = settle_s
        self.restarts = 0
        self._settle_until: float | None = None
        self._restart_pending = False
        self.labels = [s.label for s in specs]
        self.declination_rad = declination_rad
        self.imu_delay_s = imu_delay_s
        self.model = model
        self.estimators = self._create()
        self.history = {label: TimeRing(history, 4) for label in self.labels}
        self.last_sample: ImuSample | None = None
        self.samples = 0
        self.aided = 0  # samples that carried a velocity measurement
        self.caught_up = 0  # model changes applied by running the samples again
        # the samples since the estimate (re)started, while CATCH_UP_* allow; None after
        self._since_start: list[_Given] | None = []

    def _create(self) -> list[estimators.Estimator]:
        # The estimators turn their magnetic-north attitude to true north themselves.
        created = [s.create(self.rate_hz, declination=self.declination_rad,
                            imu_delay=self.imu_delay_s, **model_defaults(s, self.model))
                   for s in self.specs]
        for est in created:
            est.set_flight_state(self.airborne)
        return created

    def set_flight_state(self, airborne: bool | None) -> None:
        """The vehicle's flight state from the next sample on (eskf's drag model runs
        only while it is airborne; None: the estimator decides from the data)."""
        self.airborne = airborne
        self._tell_flight_state(airborne)

    def _tell_flight_state(self, airborne: bool | None) -> None:
        for est in self.estimators:
            est.set_flight_state(airborne)

    def air_models(self) -> dict[str, bool]:
        """Per estimator: whether its last sample ran the in-flight model."""
        return {label: est.air_model for label, est in zip(self.labels, self.estimators,
                                                            strict=True)}

    def set_declination(self, declination_rad: float) -> None:
        """Report true north with another declination from now on, estimate kept; not
        for an estimator whose declination the user set (``-e NAME:declination_deg=``):
        the vehicle's parameter or the World Magnetic Model overrode it without a word."""
        self.declination_rad = declination_rad
        for spec, est in zip(self.specs, self.estimators, strict=True):
            if "declination" not in spec.params:
                est.set_declination(declination_rad)

    def set_imu_delay(self, delay_s: float) -> None:
        """Carry the output forward by another IMU delay from now on, estimate kept;
        not for an estimator whose ``imu_delay`` the user set (``-e NAME:imu_delay=``)."""
        self.imu_delay_s = delay_s
        for spec, est in zip(self.specs, self.estimators, strict=True):
            if "imu_delay" not in spec.params:
                est.set_imu_delay(delay_s)

    def set_model(self, model: str) -> None:
        """Rebuild the estimators for another vehicle model: caught up on the samples
        since the estimate started when there are few, else restarted with the next
        sample (held while it settles)."""
        if model == self.model:
            return
        self.model = model
        self.estimators = self._create()
        if self._since_start is None:
            self._restart_pending = True
            log.info("vehicle %d: estimators rebuilt for a %s model; the estimate restarts",
                     self.key.sysid, model)
            return
        self._catch_up(self._since_start)
        log.info("vehicle %d: estimators rebuilt for a %s model, caught up on the %d "
                 "samples so far", self.key.sysid, model, len(self._since_start))

    def _catch_up(self, given: list[_Given]) -> None:
        """Run the samples given so far through the (new) estimators, with the flight
        state each came with, and rewrite the history with their attitudes."""
        for ring in self.history.values():
            ring.clear()
        airborne = self.airborne
        for g in given:
            if g.airborne != airborne:
                airborne = g.airborne
                self._tell_flight_state(airborne)
            self._update_all(g.sample, g.vel, g.vel_age)
        if airborne != self.airborne:
            self._tell_flight_state(self.airborne)
        self.caught_up += 1

    @property
    def initialising(self) -> bool:
        """Re-converging after a restart (its output is not to be trusted yet)."""
        return self._settle_until is not None

    def restart(self, t: float) -> None:
        """Start every estimator over (from the next usable sample)."""
        for est in self.estimators:
            est.reset()
        for ring in self.history.values():
            ring.clear()
        self.restarts += 1
        self._since_start = []
        self._settle_until = t + self.settle_s

    def process(self, sample: ImuSample, vel: np.ndarray | None = None,
                vel_age: float = 0.0) -> Estimate:
        """All estimators on one sample; ``vel``/``vel_age``: a velocity measurement
        (NED, true north) that arrived with it and how old it is (see bridge.aiding)."""
        if sample.restart is not None or self._restart_pending:
            self._restart_pending = False
            self.restart(sample.t)
        if vel is not None:
            self.aided += 1
        self._remember(sample, vel, vel_age)
        primary_q = self._update_all(sample, vel, vel_age)
        self.samples += 1
        self.last_sample = sample
        primary = self.estimators[0]
        rates = sample.gyr - primary.bias
        initialising = False
        if self._settle_until is not None:
            initialising = sample.t < self._settle_until or primary.status.initialising
            if not initialising:
                self._settle_until = None
        return Estimate(self.key, sample.t, sample.time_boot_ms, primary_q, rates,
                        sample.arrival, initialising)

    def _update_all(self, sample: ImuSample, vel: np.ndarray | None,
                    vel_age: float) -> np.ndarray:
        """Every estimator on one sample, into its history; the primary's attitude."""
        primary_q = None
        for label, est in zip(self.labels, self.estimators, strict=True):
            q = est.update(sample.gyr, sample.acc, sample.mag, sample.dt, vel=vel,
                           vel_age=vel_age)
            self.history[label].push(sample.t, q)
            if primary_q is None:
                primary_q = q
        return primary_q

    def _remember(self, sample: ImuSample, vel: np.ndarray | None, vel_age: float) -> None:
        """Keep the sample for a catch-up (nothing is made once it is too late for one:
        this runs on every sample)."""
        kept = self._since_start
        if kept is None:
            return
        if len(kept) >= CATCH_UP_SAMPLES or (
                kept and sample.t - kept[0].sample.t > CATCH_UP_S):
            self._since_start = None  # too late to catch up: a new model restarts
            return
        kept.append(_Given(sample, vel, vel_age, self.airborne))

    def status(self, label: str) -> estimators.EstimatorStatus:
        return self.estimators[self.labels.index(label)].status


class Pipeline:
    """Creates a :class:`SourcePipeline` the first time a source is heard."""

    def __init__(self, specs: list[EstimatorSpec], rate_hz: float = 1000.0,
                 history_s: float = 10.0, declination_deg: float = 0.0,
                 settle_s: float = 1.0) -> None:
        if not specs:
            raise ValueError("at least one estimator is needed")
        labels = [s.label for s in specs]
        if len(set(labels)) != len(labels):
            raise ValueError(f"estimators listed twice: {labels}")
        # (BridgeService.run compiles the estimators before it serves: bridge.warmup.)
        self.specs = specs
        self.declination_rad = math.radians(declination_deg)  # until a vehicle's is known
        self.vehicles: dict[int, VehicleSetup] = {}
        self.rate_hz = rate_hz
        self.settle_s = settle_s
        # Sized for the faster of the nominal rate and 2 kHz: the nominal rate is only
        # what was requested, the stream may well be faster.
        self.history = max(16, math.ceil(history_s * max(rate_hz, 2000.0) * 1.25))
        self.sources: dict[SourceKey, SourcePipeline] = {}

    @property
    def primary_label(self) -> str:
        return self.specs[0].label

    def setup(self, sysid: int) -> VehicleSetup:
        setup = self.vehicles.get(sysid)
        if setup is None:
            setup = self.vehicles[sysid] = VehicleSetup(self.declination_rad)
        return setup

    def configure(self, sysid: int, *, declination_rad: float | None = None,
                  model: str | None = None, imu_delay_s: float | None = None) -> None:
        """Tell a vehicle's estimators (present and future) its declination / model /
        IMU delay."""
        setup = self.setup(sysid)
        if declination_rad is not None:
            setup.declination_rad = declination_rad
        if imu_delay_s is not None:
            setup.imu_delay_s = imu_delay_s
        if model is not None:
            setup.model = model
        for key, src in self.sources.items():
            if key.sysid != sysid:
                continue
            if src.declination_rad != setup.declination_rad:
                src.set_declination(setup.declination_rad)
            if src.imu_delay_s != setup.imu_delay_s:
                src.set_imu_delay(setup.imu_delay_s)
            src.set_model(setup.model)

    def set_flight_state(self, sysid: int, airborne: bool | None) -> None:
        """Tell a vehicle's estimators (present and future) whether it flies."""
        self.setup(sysid).airborne = airborne
        for key, src in self.sources.items():
            if key.sysid == sysid:
                src.set_flight_state(airborne)

    def process(self, sample: ImuSample, vel: np.ndarray | None = None,
                vel_age: float = 0.0) -> Estimate:
        src = self.sources.get(sample.key)
        if src is None:
            setup = self.setup(sample.key.sysid)
            src = SourcePipeline(sample.key, self.specs, self.rate_hz, self.history,
                                 setup.declination_rad, self.settle_s, setup.model,
                                 setup.airborne, setup.imu_delay_s)
            self.sources[sample.key] = src
        return src.process(sample, vel, vel_age)

    def forget(self, key: SourceKey) -> None:
        """Drop a source's estimators and history (it is no longer a primary)."""
        self.sources.pop(key, None)
