"""A compact live view of the bridge (like `top`), and the summary printed at exit."""

from __future__ import annotations

import math
import sys
import time
from typing import TYPE_CHECKING, Any, TextIO

from .output import euler_zyx

if TYPE_CHECKING:
    from .service import BridgeService

_CLEAR = "\x1b[H\x1b[2J"


def _fmt(x: float | None, spec: str = "6.2f") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-".rjust(int(spec.split(".")[0]) if spec[0].isdigit() else 1)
    return format(x, spec)


def _cmp(entry: dict[str, Any] | None) -> str:
    if not entry:
        return "      -        -      -"
    return (f"{entry['total_deg']:6.2f}/{entry['heading_deg']:5.2f}/"
            f"{entry['inclination_deg']:5.2f} {entry['lag_s'] * 1e3:5.0f}")


def render(service: BridgeService) -> str:
    """The current state of every vehicle and estimator as a few lines of text."""
    link = service.link_status()
    elapsed = time.monotonic() - service.started
    lines = [f"attitude-bridge  {elapsed:7.1f} s  {service.link.name}  "
             f"in {link['messages_in']} msgs, crc {link['bad_crc']}, "
             f"frame {link['bad_frame']}, unsigned {link['unsigned_rejected']}"]
    if "mqtt" in link:
        m = link["mqtt"]
        lines[0] += (f"  mqtt {'up' if m['connected'] else 'DOWN'} "
                     f"{m['published']} sent {m['dropped']} dropped")
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
    lines.append("")
    lines.append(" SYS  ESTIMATOR             ROLL   PITCH     YAW   "
                 "TRUTH tot/head/incl lag ms   VEHICLE tot/head/incl off ms")
    for key, src in sorted(service.pipeline.sources.items()):
        compare = service.last_status.get(key.sysid, {}).get("compare", {})
        for i, (label, est) in enumerate(zip(src.labels, src.estimators, strict=True)):
            roll, pitch, yaw = (math.degrees(a) for a in euler_zyx(est.q))
            mark = "*" if i == 0 else " "
            lines.append(
                f" {key.sysid:3d}  {(label + mark)[:18]:18s} {roll:7.1f} {pitch:7.1f} "
                f"{yaw:7.1f}   {_cmp(compare.get('truth', {}).get(label))}   "
                f"{_cmp(compare.get('vehicle', {}).get(label))}")
    lines.append("")
    lines.append(" * = primary (sent as ATTITUDE_QUATERNION/ATTITUDE); errors are rolling RMS "
                 f"over {service.cfg.window_s:g} s")
    return "\n".join(lines)


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
                     f"held while initialising)")
    link = service.link_status()
    causes = {k: link[k] for k in ("bad_crc", "bad_frame", "truncated", "unsigned_rejected",
                                   "unsigned_accepted", "bad_signature", "replayed",
                                   "peers_refused", "peers_expired", "idle_timeouts",
                                   "write_stalls", "reconnects") if link[k]}
    causes.update({f"gate_{k}": v for k, v in link["gate"].items() if v})
    causes.update({k: v for k, v in link["refused"].items() if v})
    lines.append(f" connection: {link['peers']} peers answered, refused/dropped "
                 f"{causes or 'nothing'}")
    return "\n".join(lines)
