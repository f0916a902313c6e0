"""The per-sample path: an IMU message of a served vehicle -> its attitude on the wire.

Synchronous from the datagram callback to the send, so nothing queues between reading
an IMU packet and sending its attitude: choose the vehicle's primary source, turn the
message into samples (:class:`~bridge.vehicle.ingest.Ingest`), keep the vehicle's
clocks and stream rate, take the matching velocity for aiding, run every estimator,
and offer the primary's estimate to the MAVLink output (held while it settles) and to
MQTT.
"""

from __future__ import annotations

import logging

from imu.px4_mag import CALIBRATED, RAW

from ..estimate.pipeline import Pipeline
from ..publish.estimates import EstimatePublisher
from ..publish.output import AttitudeOutput
from ..vehicle.imu_sample import ID_HIGHRES_IMU, ID_SCALED_IMU
from ..vehicle.ingest import ImuSample, Ingest, SourceKey
from ..vehicle.vehicle import Vehicle
from ..wire.links import Link
from ..wire.mav import MAVLinkMessage, mavlink
from .config import BridgeConfig
from .registry import STREAM_SILENCE_S

log = logging.getLogger(__name__)

PX4 = mavlink.MAV_AUTOPILOT_PX4


class SampleFlow:
    """Owns nothing but the order of the steps; the state lives in the parts."""

    def __init__(self, cfg: BridgeConfig, ingest: Ingest, pipeline: Pipeline,
                 output: AttitudeOutput, estimates: EstimatePublisher | None) -> None:
        self.cfg = cfg
        self.ingest = ingest
        self.pipeline = pipeline
        self.output = output
        self.estimates = estimates

    def forget_source(self, key: SourceKey) -> None:
        """Drop one IMU source's clock, estimators and output state."""
        self.ingest.forget(key)
        self.pipeline.forget(key)
        self.output.forget(key)

    def on_imu(self, vehicle: Vehicle, msg: MAVLinkMessage, link: Link, arrival: float,
               now: float) -> None:
        """One IMU message of ``vehicle`` (``arrival``: perf_counter, ``now``: monotonic)."""
        key = self.ingest.key_of(msg)
        assert key is not None
        if self._raw_magnetometer(vehicle, key, msg, arrival, now):
            return
        old = vehicle.primary
        use, new = vehicle.choose_source(key, now, self.cfg.imu_id,
                                         vehicle.negotiation.preferred_id,
                                         self.cfg.source_timeout_s)
        if not use:
            return
        if new:
            for stale in (old, key):
                if stale is not None:
                    self.forget_source(stale)
        state = self.ingest.sources.get(key)
        if state is not None:
            state.clock.boot_hint = vehicle.boot_hint
        samples = self.ingest.handle_all(msg, arrival, key)
        if not samples:  # refused (counted by its source) or held as clock evidence
            state = self.ingest.sources.get(key)
            if state is not None:
                vehicle.negotiation.note_dropped(state.dropped)
            return
        vehicle.last_imu = now
        vehicle.request_backoff = STREAM_SILENCE_S
        if vehicle.autopilot_compid is None or key.compid == vehicle.autopilot_compid:
            vehicle.link, vehicle.address = link, link.last_addr
        px4_highres = key.msg == ID_HIGHRES_IMU and vehicle.autopilot == PX4
        for sample in samples:
            if px4_highres:
                self._px4_field(vehicle, sample)
            self._estimate(vehicle, sample)

    def _raw_magnetometer(self, vehicle: Vehicle, key: SourceKey, msg: MAVLinkMessage,
                          arrival: float, now: float) -> bool:
        """A PX4's SCALED_IMU while its HIGHRES_IMU is the primary: only its raw field
        is wanted (imu.px4_mag). True when the message was taken for that."""
        primary = vehicle.primary
        if (vehicle.autopilot != PX4 or key.msg != ID_SCALED_IMU or primary is None
                or primary.msg != ID_HIGHRES_IMU or key.compid != primary.compid
                or now - vehicle.primary_heard > self.cfg.source_timeout_s):
            return False
        mag = self.ingest.scaled_mag(msg)
        if mag is not None:
            vehicle.px4_mag.chooser.offer_raw(mag, arrival)
        return True

    @staticmethod
    def _px4_field(vehicle: Vehicle, sample: ImuSample) -> None:
        """HIGHRES_IMU's field, or the raw one where that is PX4's calibrated field."""
        chooser = vehicle.px4_mag.chooser
        before = chooser.state
        sample.mag = chooser.choose(sample.mag, sample.arrival)
        if chooser.state == before:
            return
        if chooser.state == RAW:
            log.info("vehicle %d: %s", vehicle.sysid, chooser.describe())
        elif chooser.state == CALIBRATED and before == RAW:
            log.warning("vehicle %d: its raw magnetometer no longer agrees with the "
                        "calibrated one; %s from now on", vehicle.sysid, chooser.describe())
        elif chooser.state == CALIBRATED:
            log.info("vehicle %d: %s", vehicle.sysid, chooser.describe())

    def _estimate(self, vehicle: Vehicle, sample: ImuSample) -> None:
        vehicle.negotiation.observe(sample.key.msg, sample.t)
        if sample.restart is not None:
            self._log_restart(vehicle, sample)
            vehicle.arrival_clock.reset()
        vehicle.arrival_clock.observe(sample.t, sample.arrival)
        if sample.restart == "reboot":
            vehicle.refs = None  # the references' clock restarted too
            vehicle.px4_mag.plan(vehicle.autopilot)  # its calibration may have changed
            if vehicle.autopilot is not None:
                # a rebooted autopilot has forgotten every interval it was asked for
                log.info("vehicle %d: asking again for its streams", vehicle.sysid)
                vehicle.negotiation.start(vehicle.autopilot)
        vel, vel_age = None, 0.0
        if self.cfg.aiding:
            if sample.restart is not None:
                vehicle.aiding.forget_pending()
            vel, vel_age = vehicle.aiding.take(sample.t, sample.arrival)
        est = self.pipeline.process(sample, vel, vel_age)
        if est.initialising:
            self.output.hold(est)
        else:
            self.output.offer(est)
        if self.estimates is not None:
            self.estimates.offer(est, vehicle.mqtt_sent_t)

    def _log_restart(self, vehicle: Vehicle, sample: ImuSample) -> None:
        """A reboot or an outage restarts the estimate: say so, with the board times."""
        src = self.pipeline.sources.get(sample.key)
        before = src.last_sample.t if src is not None and src.last_sample is not None else None
        was = f"{before:.3f} s" if before is not None else "unknown"
        if sample.restart == "reboot":
            log.warning("vehicle %d rebooted (board time went back from %s to %.3f s); "
                        "estimators restarted, output held %g s while they settle",
                        vehicle.sysid, was, sample.t, self.cfg.reinit_settle_s)
        else:
            log.warning("vehicle %d: IMU data resumed after a gap (board time %s -> %.3f s); "
                        "estimators restarted, output held %g s while they settle",
                        vehicle.sysid, was, sample.t, self.cfg.reinit_settle_s)
