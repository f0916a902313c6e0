"""A compact live view of the bridge (like `top`), and the summary printed at exit."""

from __future__ import annotations

import math
import sys
import time
from typing import TYPE_CHECKING, Any, TextIO

from ..publish.output import euler_zyx

if TYPE_CHECKING:
    from .service import BridgeService

_CLEAR = "\x1b[H\x1b[2J"


def _fmt(x: float | None, spec: str = "6.2f") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-".rjust(int(spec.split(".")[0]) if spec[0].isdigit() else 1)
    return format(x, spec)


def lag_text(entry: dict[str, Any]) -> str:
    """The lag column: milliseconds, or why it is not known (never a grid end shown as
    if it were measured): "> 200" beyond the search, "–" not measurable."""
    lag = entry.get("lag_s")
    if lag is not None:
        return f"{lag * 1e3:5.0f}"
    note = entry.get("lag_note", "")
    if note[:1] in "<>":
        return note.split(" ms")[0].replace(" ", "").rjust(5)
    return "    –"


def _cmp(entry: dict[str, Any] | None) -> str:
    if not entry:
        return "      -        -      -"
    return (f"{entry['total_deg']:6.2f}/{entry['heading_deg']:5.2f}/"
            f"{entry['inclination_deg']:5.2f} {lag_text(entry)}")


def render(service: BridgeService) -> str:
    """The current state of every vehicle and estimator as a few lines of text."""
    link = service.link_status()
    elapsed = time.monotonic() - service.started
    lines = [f"attitude-bridge  {elapsed:7.1f} s  {service.link.name}  "
             f"in {link['messages_in']} msgs, crc {link['bad_crc']}, "
             f"frame {link['bad_frame']}, unsigned {link['unsigned_rejected']}"]
    if "mqtt" in link:
        lines[0] += "  " + mqtt_text(link["mqtt"])
    if "web" in link:
        lines[0] += f"  web {link['web']['url']} ({link['web']['viewers']} viewing)"
    lines.append("")
    lines.append(" SYS   RATE Hz  SAMPLES  OUT      DROPS (dup/reord/jump/back/nan)   "
                 "LOST  LAT p50/p99 ms")
    for sysid, st in sorted(service.last_status.items()):
        d = st["drops"]
        lat = st["latency_ms"]
        lines.append(
            f" {sysid:3d}  {st['input_rate_hz']:8.1f}  {st['samples']:7d}  {st['sent']:6d}  "
            f"{d['duplicate']:5d}/{d['reordered']:d}/{d['jump']:d}/{d['backwards']:d}/"
            f"{d['nonfinite']:d}".ljust(62) +
            f"{st['link']['lost']:5d}  {_fmt(lat.get('p50'), '5.2f')}/"
            f"{_fmt(lat.get('p99'), '5.2f')}")
    for sysid, st in sorted(service.last_status.items()):
        lines.extend(vehicle_lines(sysid, st))
    lines.append("")
    lines.append(" SYS  ESTIMATOR             ROLL   PITCH     YAW   "
                 "TRUTH tot/head/incl lag ms   VEHICLE tot/head/incl off ms")
    for key, src in sorted(service.pipeline.sources.items()):
        st = service.last_status.get(key.sysid, {})
        compare = st.get("compare", {})
        for i, (label, est) in enumerate(zip(src.labels, src.estimators, strict=True)):
            roll, pitch, yaw = (math.degrees(a) for a in euler_zyx(est.q))
            mark = "*" if i == 0 else " "
            lines.append(
                f" {key.sysid:3d}  {(label + mark)[:18]:18s} {roll:7.1f} {pitch:7.1f} "
                f"{yaw:7.1f}   {_cmp(compare.get('truth', {}).get(label))}   "
                f"{_cmp(compare.get('vehicle', {}).get(label))}")
        own = _own_attitude(service, key.sysid)
        if own is not None or st.get("vehicle_vs_truth"):
            roll, pitch, yaw = own if own is not None else (math.nan,) * 3
            lines.append(f" {key.sysid:3d}  {'(vehicle own)':18s} {_fmt(roll, '7.1f')} "
                         f"{_fmt(pitch, '7.1f')} {_fmt(yaw, '7.1f')}   "
                         f"{_cmp(st.get('vehicle_vs_truth'))}   {_cmp(None)}")
    lines.append("")
    lines.append(" * = primary (sent as ATTITUDE_QUATERNION/ATTITUDE); errors are rolling RMS "
                 f"over {service.cfg.window_s:g} s")
    return "\n".join(lines)


def mqtt_text(m: dict[str, Any]) -> str:
    """MQTT state in a few words: live (up / DOWN and why), or after the bridge stopped
    it (what the session did: a clean stop is not an outage)."""
    counts = f"{m['published']} sent {m['dropped']} dropped"
    why = f" ({m['last_error']})" if m.get("last_error") else ""
    if m.get("stopped"):
        if m["connects"] == 0:
            return f"mqtt never connected{why}, {counts}"
        return f"mqtt ok ({m['connects']} connection(s)), {counts}"
    return f"mqtt {'up' if m['connected'] else 'DOWN' + why} {counts}"


def _own_attitude(service: BridgeService, sysid: int) -> tuple[float, ...] | None:
    """The vehicle's latest own attitude (roll, pitch, yaw in degrees), if it sends one."""
    vehicle = service.vehicles.get(sysid)
    if vehicle is None or vehicle.refs is None:
        return None
    _, q = vehicle.refs.series["vehicle"].snapshot(vehicle.refs.series["vehicle"].last_t)
    if not len(q):
        return None
    return tuple(math.degrees(a) for a in euler_zyx(q[-1]))


def vehicle_lines(sysid: int, st: dict[str, Any]) -> list[str]:
    """What the bridge learned about a vehicle and made of it: the autopilot and vehicle
    model, the IMU stream negotiated, the declination and its source, the aiding."""
    v = st.get("vehicle", {})
    models = ", ".join(f"{k} {d}" for k, d in v.get("estimators", {}).items() if d != "-")
    ap = (v.get("autopilot") or "no heartbeat").removeprefix("MAV_AUTOPILOT_")
    line = f" {sysid:3d}  {ap} {v.get('type') or ''} ({v.get('model', 'unknown')}"
    line += f": {models})" if models else ")"
    s = st.get("imu_stream", {})
    achieved = _fmt(s.get("achieved_hz"), ".0f").strip()
    flag = "  BELOW REQUEST" if s.get("below_request") else ""
    refused = f", refused {'; '.join(s['refused'])}" if s.get("refused") else ""
    jitter = s.get("jitter_ms")
    jitter_text = f" ±{jitter:.2f} ms" if jitter is not None else ""
    asked = s.get("asked_hz", s.get("requested_hz", 0))
    imu = (f"       IMU {s.get('message') or '-'} {achieved}/{asked:.4g} Hz{jitter_text} "
           f"({s.get('state', '-')}{refused})"
           f"{', board ' + st.get('board', '-') if s.get('message') == 'RAW_IMU' else ''}{flag}")
    delay = st.get("imu_delay") or {}
    if delay.get("ms"):
        imu += f", {delay['ms']:.1f} ms late ({delay.get('source', '')})"
    d = st.get("declination", {})
    a = st.get("aiding", {})
    if not a.get("enabled", True):
        aid = "aiding off"
    elif a.get("source"):
        aid = (f"aiding {a['source']} {_fmt(a.get('rate_hz'), '.1f').strip()} Hz, age "
               f"{_fmt(a.get('median_age_ms'), '.0f').strip()} ms"
               f"{' (by arrival)' if a.get('stamp') == 'arrival' else ''}")
    else:
        aid = "no velocity aiding (none received)"
    decl = (f"       declination {d.get('deg', 0.0):+.2f}° ({d.get('source', 'none')}"
            f"{': ' + d['detail'] if d.get('detail') else ''}), {aid}")
    return [line, imu, decl, flight_text(st.get("flight_state"))]


def flight_text(f: dict[str, Any] | None) -> str:
    """The flight state line: state (source), switches, and which estimators run their
    in-flight model (eskf's rotor drag) now."""
    if not f:
        return "       flight state unknown"
    text = f"       flight: {f['state']} ({f['source']}), {f['switches']} switch(es)"
    if f.get("recent_switches"):
        last = f["recent_switches"][-1]
        text += f", last {last['s_ago']:.0f} s ago to {last['state']}"
    if f.get("flap_fallbacks"):
        text += f", landed state unreliable {f['flap_fallbacks']}x"
    air = [k for k, on in f.get("air_model", {}).items() if on]
    return text + (f"; in-flight model: {', '.join(air)}" if air else "; no in-flight model")


class LiveTable:
    """Redraws the table on each status update (clears the screen on a terminal)."""

    def __init__(self, stream: TextIO = sys.stdout) -> None:
        self.stream = stream
        self.tty = stream.isatty()

    def __call__(self, service: BridgeService) -> None:
        text = render(service)
        self.stream.write((_CLEAR if self.tty else "\n") + text + "\n")
        self.stream.flush()


def summary(service: BridgeService) -> str:
    """Final report: the table plus totals of everything dropped or flagged."""
    lines = ["", "=== attitude-bridge summary ===", render(service), ""]
    for sysid, st in sorted(service.last_status.items()):
        drops = {k: v for k, v in st["drops"].items() if v}
        flags = {k: v for k, v in st["flags"].items() if v}
        refused = {k: v for k, v in st["refused"].items() if v}
        lat = st["latency_ms"]
        lines.append(f" vehicle {sysid}: {st['samples']} samples, {st['sent']} estimates "
                     f"sent (latency p50 {_fmt(lat.get('p50'), '.2f')} ms, p99 "
                     f"{_fmt(lat.get('p99'), '.2f')} ms), "
                     f"drops {drops or 'none'}, flags {flags or 'none'}, "
                     f"link lost {st['link']['lost']}, refused {refused or 'none'}, "
                     f"restarts {st['restarts']} ({st['held_initialising']} estimates "
                     f"held while initialising), model catch-ups "
                     f"{st['model_catch_ups']}")
        lines.extend(vehicle_lines(sysid, st))
        session = st.get("session_vs_truth")
        if session:
            lines.append("       against the truth over the whole session, tot/head/incl: " +
                         ", ".join(f"{label} {e['total_deg']:.2f}/{e['heading_deg']:.2f}/"
                                   f"{e['inclination_deg']:.2f}"
                                   for label, e in session.items()))
    link = service.link_status()
    causes = {k: link[k] for k in ("bad_crc", "bad_frame", "truncated", "unsigned_rejected",
                                   "unsigned_accepted", "bad_signature", "replayed",
                                   "peers_refused", "peers_expired", "idle_timeouts",
                                   "write_stalls", "reconnects", "handler_failures")
              if link[k]}
    causes.update({f"gate_{k}": v for k, v in link["gate"].items() if v})
    causes.update({k: v for k, v in link["refused"].items() if v})
    lines.append(f" connection: {link['peers']} peers answered, refused/dropped "
                 f"{causes or 'nothing'}")
    for name, counts in link["outs"].items():
        failed = {k: v for k, v in counts.items() if v}
        if failed:
            lines.append(f" output {name}: {failed}")
    if service.recorder is not None:
        lines.append(f" {service.recorder.summary()}")
    return "\n".join(lines)
