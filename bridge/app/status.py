"""The bridge's status report: per vehicle and for the connection, once per period.

One dict per served vehicle (rates, drops and refusals by cause, latency, the stream
negotiated, declination, aiding, flight state and the live comparison), with the
connection's counters beside it. The same report goes to MQTT
(``<prefix>/<sysid>/status``), to the status file (``--status-file``, written
atomically) and to whoever watches the service (the live table). The report is what a
user debugging a bad attitude reads first, so every refusal has its cause.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from imu.flight_state import state_name

from ..estimate.compare import compare_all, vehicle_against_truth
from ..estimate.pipeline import Pipeline, SourcePipeline
from ..estimate.session import SessionScores
from ..publish.estimates import source_info, topics_of
from ..publish.mqtt import MqttPublisher
from ..publish.output import AttitudeOutput
from ..publish.record import TlogRecorder
from ..vehicle.ingest import DROP_CAUSES, FLAG_CAUSES, Ingest
from ..vehicle.model import describe, model_of, type_name
from ..vehicle.references import TRUTH, VEHICLE, References
from ..vehicle.vehicle import Vehicle
from ..wire.admission import Admission
from ..wire.links import Link
from ..wire.mav import mavlink
from .config import BridgeConfig
from .health import write_status_file
from .registry import VehicleRegistry
from .watch import StreamWatch

log = logging.getLogger(__name__)

FLIGHT_SWITCHES_SHOWN = 10  # the report lists this many of the latest switches


class StatusReporter:
    """Builds the report from the parts it reads (it changes none of them)."""

    def __init__(self, cfg: BridgeConfig, link: Link, admission: Admission,
                 registry: VehicleRegistry, ingest: Ingest, pipeline: Pipeline,
                 output: AttitudeOutput, watch: StreamWatch,
                 mqtt: MqttPublisher | None) -> None:
        self.cfg = cfg
        self.link = link
        self.admission = admission
        self.registry = registry
        self.ingest = ingest
        self.pipeline = pipeline
        self.output = output
        self.watch = watch
        self.mqtt = mqtt
        self.recorder: TlogRecorder | None = None
        self.web: Any = None  # the live web view (bridge.publish.web), when served
        self.topics = topics_of(pipeline.specs)
        self.started = time.monotonic()
        self.last: dict[int, dict[str, Any]] = {}
        self._last_wall = self.started
        #: per vehicle: the references its session scores were counted on, and the scores
        self._sessions: dict[int, tuple[References, SessionScores]] = {}

    def restart_clock(self) -> None:
        """The service starts now: uptime and rates count from here."""
        self.started = self._last_wall = time.monotonic()

    def publish(self) -> None:
        """Build every vehicle's report; send it to MQTT and the status file."""
        now = time.monotonic()
        elapsed = now - self._last_wall
        self._last_wall = now
        self.admission.tick(elapsed)
        link = self.link_status()
        vehicles = self.registry.vehicles
        for vehicle in list(vehicles.values()):
            status = self.vehicle_status(vehicle, elapsed)
            status["connection"] = link
            self.last[vehicle.sysid] = status
            if self.mqtt is not None:
                self.mqtt.publish(self.mqtt.topic(vehicle.sysid, "status"), status)
        for sysid in [s for s in self.last if s not in vehicles]:
            del self.last[sysid]  # replaced (a provisional vehicle)
        if self.recorder is not None:
            self.recorder.flush()
        if self.cfg.status_file:
            self._write_file(link)

    def vehicle_status(self, vehicle: Vehicle, elapsed: float) -> dict[str, Any]:
        """Rates, drops and refusals by cause, latency and the live comparison of one
        vehicle (``elapsed``: seconds since the last report, for its input rate)."""
        sources = {k: s for k, s in self.ingest.sources.items() if k.sysid == vehicle.sysid}
        samples = sum(s.accepted for s in sources.values())
        if samples < vehicle.samples_at_last_status:  # its state was dropped meanwhile
            vehicle.samples_at_last_status = 0
        rate = (samples - vehicle.samples_at_last_status) / elapsed if elapsed > 0 else 0.0
        vehicle.samples_at_last_status = samples
        drops = dict.fromkeys(DROP_CAUSES, 0)
        flags = dict.fromkeys(FLAG_CAUSES, 0)
        for s in sources.values():
            for cause in DROP_CAUSES:
                drops[cause] += s.counts[cause]
            for cause in FLAG_CAUSES:
                flags[cause] += s.counts[cause]
        seqs = vehicle.sequences.values()
        # datagrams refused over budget never reach the parser: their sequence numbers
        # are gaps, counted as refused (connection.gate.over_budget), not as link loss
        over_budget = self.admission.over_budget_of(vehicle.sysid)
        link = {"lost": max(0, sum(t.lost for t in seqs) - over_budget),
                "late": sum(t.late for t in seqs),
                "repeated": sum(t.duplicate for t in seqs), "over_budget": over_budget}
        src = self.pipeline.sources.get(vehicle.primary) if vehicle.primary else None
        return {
            "sysid": vehicle.sysid, "time_unix": round(time.time(), 3),
            "time_s": src.last_sample.t if src is not None and src.last_sample else None,
            "online": self.watch.online(vehicle), "samples": samples,
            "input_rate_hz": round(rate, 1), "sources": [source_info(k) for k in sources],
            "primary": source_info(vehicle.primary) if vehicle.primary else None,
            "estimator_topics": dict(self.topics),
            "admitted_by": vehicle.admitted_by, "source_switches": vehicle.source_switches,
            "drops": drops, "flags": flags, "link": link, "refused": dict(vehicle.refused),
            "clock_pending": sum(s.clock.pending for s in sources.values()),
            "restarts": src.restarts if src is not None else 0,
            "model_catch_ups": src.caught_up if src is not None else 0,
            "initialising": src.initialising if src is not None else False,
            "sent": self.output.sent.get(vehicle.sysid, 0),
            "held_initialising": self.output.held.get(vehicle.sysid, 0),
            "latency_ms": self.output.latency_percentiles_ms(),
            "sent_late": self.output.sent_late.get(vehicle.sysid, 0),
            **self._comparison(vehicle, src),
            "stream_requests": vehicle.stream_requests,
            "imu_stream": vehicle.negotiation.status(),
            "board": self.ingest.board_of(vehicle.sysid).name,
            "declination": vehicle.declination.status(),
            "px4_magnetometer": (vehicle.px4_mag.status()
                                 if vehicle.autopilot == mavlink.MAV_AUTOPILOT_PX4 else None),
            "imu_delay": vehicle.imu_delay.status(),
            "vehicle": self._vehicle_description(vehicle),
            "aiding": {**vehicle.aiding.status(), "enabled": self.cfg.aiding,
                       "aided_samples": src.aided if src is not None else 0},
            "flight_state": _flight_status(vehicle, src),
        }

    def _comparison(self, vehicle: Vehicle, src: SourcePipeline | None) -> dict[str, Any]:
        """Each estimator against each reference, and the vehicle's own against the
        truth, over the last ``window_s``."""
        compare: dict[str, Any] = {}
        counters: dict[str, Any] = {}
        own = None
        if src is not None:
            for label, est in zip(src.labels, src.estimators, strict=True):
                counters[label] = est.counters.__dict__
            if vehicle.refs is not None:
                for ref, by_label in compare_all(src.history, vehicle.refs,
                                                 self.cfg.window_s).items():
                    compare[ref] = {label: c.to_dict() for label, c in by_label.items()}
        if vehicle.refs is not None:
            c = vehicle_against_truth(vehicle.refs, self.cfg.window_s)
            own = c.to_dict() if c is not None else None
        return {"estimator_counters": counters, "compare": compare, "vehicle_vs_truth": own,
                "session_vs_truth": self._session(vehicle, src)}

    def _session(self, vehicle: Vehicle, src: SourcePipeline | None
                 ) -> dict[str, dict[str, float | int]]:
        """Every estimator and the vehicle's own attitude against the truth since the
        bridge started (:mod:`bridge.estimate.session`)."""
        entry = self._sessions.get(vehicle.sysid)
        refs = vehicle.refs
        if refs is None or src is None:
            return entry[1].to_dict() if entry is not None else {}
        scores = entry[1] if entry is not None else SessionScores()
        if entry is not None and entry[0] is not refs:
            scores.new_timeline()  # a reboot started the references (and the clock) again
        self._sessions[vehicle.sysid] = (refs, scores)
        own = refs.series[VEHICLE]
        scores.update(refs.series[TRUTH], src.history, own if len(own) >= 2 else None)
        return scores.to_dict()

    def _vehicle_description(self, vehicle: Vehicle) -> dict[str, Any]:
        """What the heartbeat says the vehicle is, and what that made of the estimators."""
        model = model_of(vehicle.mav_type)
        autopilot = None
        if vehicle.autopilot is not None:
            entry = mavlink.enums["MAV_AUTOPILOT"].get(vehicle.autopilot)
            autopilot = entry.name if entry is not None else str(vehicle.autopilot)
        return {"autopilot": autopilot, "type": type_name(vehicle.mav_type), "model": model,
                "estimators": {spec.label: describe(spec, model)
                               for spec in self.pipeline.specs}}

    def link_status(self) -> dict[str, Any]:
        """The connection's counters: parsing, signing, peers, the gate, refusals,
        MQTT and the recording."""
        c = self.link.codec.stats
        ls = self.link.stats
        s = {"bytes_in": c.bytes_in, "messages_in": c.messages_in, "bad_crc": c.bad_crc,
             "bad_frame": c.bad_frame, "unsigned_rejected": c.unsigned_rejected,
             "unsigned_accepted": c.unsigned_accepted, "bad_signature": c.bad_signature,
             "replayed": c.replayed, "unknown_message": c.unknown_message,
             "truncated": c.truncated, "send_dropped": ls.send_dropped,
             "send_errors": ls.send_errors, "reconnects": ls.reconnects,
             "idle_timeouts": ls.idle_timeouts, "write_stalls": ls.write_stalls,
             "peers": ls.peers,
             "peers_refused": ls.peers_refused, "peers_expired": ls.peers_expired,
             "handler_failures": ls.handler_failures,
             "outs": {out.name: {"send_errors": out.stats.send_errors,
                                 "send_dropped": out.stats.send_dropped}
                      for out in self.output.links if out is not self.link},
             "gate": self.admission.stats.to_dict(), "refused": dict(self.registry.refused),
             "vehicles": sorted(self.registry.vehicles)}
        if self.mqtt is not None:
            m = self.mqtt.stats
            s["mqtt"] = {"connected": m.connected, "published": m.published,
                         "dropped": m.dropped, "connects": m.connects,
                         "last_error": m.last_error or None, "stopped": m.stopped}
        if self.web is not None:
            s["web"] = self.web.status()
        if self.recorder is not None:
            s["record"] = {"file": str(self.recorder.path), "frames_in":
                           self.recorder.frames_in, "frames_out": self.recorder.frames_out}
        return s

    def _write_file(self, link: dict[str, Any]) -> None:
        status = {"time_unix": round(time.time(), 3),
                  "uptime_s": round(time.monotonic() - self.started, 1),
                  "vehicles": {str(k): {n: v for n, v in st.items() if n != "connection"}
                               for k, st in self.last.items()},
                  "connection": link, "mqtt": link.get("mqtt")}
        try:
            write_status_file(self.cfg.status_file, status)
        except OSError as exc:  # disk full, folder removed: keep serving, say so
            log.warning("cannot write the status file %s: %s", self.cfg.status_file, exc)


def _flight_status(vehicle: Vehicle, src: SourcePipeline | None) -> dict[str, Any]:
    """The vehicle's flight state, where it came from, its last switches (seconds ago)
    and, per estimator, whether its in-flight model (eskf's drag) is running."""
    now = time.monotonic()
    recent = list(vehicle.flight.switches)[-FLIGHT_SWITCHES_SHOWN:]
    return {**vehicle.flight.status(),
            "recent_switches": [{"s_ago": round(now - s.t, 1),
                                 "state": state_name(s.airborne), "source": s.source}
                                for s in recent],
            "air_model": src.air_models() if src is not None else {},
            "board_switches": [[t, state_name(a)] for t, a in vehicle.flight_board_switches]}
