"""The text summary of one replayed file: where the data came from, then a compact table.

Every cell is a number or a footnote mark; each footnote says in one line why that
number does not exist (static log, no magnetometer, no overlap...), once for all the
estimators it applies to. The table stays within 80 columns for short labels.
"""

from __future__ import annotations

import math
import sys
from typing import TextIO

from .evaluate import Evaluation, amount, vehicle_note
from .flight import PHASES

#: (Score field, header, scale, format)
COLUMNS = (("total_deg", "total°", 1.0, "{:.3f}"), ("heading_deg", "heading°", 1.0, "{:.3f}"),
           ("inclination_deg", "incl°", 1.0, "{:.3f}"), ("lag_s", "lag ms", 1e3, "{:.1f}"),
           ("convergence_s", "conv s", 1.0, "{:.2f}"))
CELL = 9


def header_lines(ev: Evaluation) -> list[str]:
    """Source, reference, declination, aiding, notes and warnings: one line each."""
    rec, prep = ev.recording, ev.prepared
    ref = rec.reference
    lines = [f"{rec.path}: {rec.format}, IMU {rec.source}, {rec.n} samples, "
             f"{amount(rec.duration)} s at {amount(rec.rate_hz)} Hz (mean; jitter "
             f"{amount(rec.jitter_ms, 2, tiny=False)} ms)"]
    if ref is None:
        lines.append("  reference:   none (nothing to score against)")
    else:
        timing = f"; {ref.timing}" if ref.timing else ""
        lines.append(f"  reference:   {ref.kind} ({ref.source}, {ref.north} north{timing})")
    lines.append(f"  declination: {prep.declination.describe()}")
    if prep.imu_delay.seconds > 0.0:
        lines.append(f"  IMU delay:   {prep.imu_delay.ms:.1f} ms ({prep.imu_delay.source}): "
                     f"the estimates are carried forward by it (-e NAME:imu_delay= "
                     f"overrides)")
    lines.append(f"  aiding:      {prep.aid_note}")
    lines.append(f"  vehicle:     {vehicle_note(prep.recording)}")
    if prep.flight is not None:
        lines.append(f"  flight:      {prep.flight.note()}")
    lines += [f"  note: {n}" for n in rec.notes]
    if rec.cleanup.dropped:
        lines.append(f"  note: dropped IMU samples: {rec.cleanup}")
    lines += [f"  note: {label}: {ref.note}" for label, ref in ev.references.items()
              if ref.note]
    lines += [f"  warning: {w}" for w in rec.warnings]
    return lines


def table_lines(ev: Evaluation, scores: dict | None = None) -> list[str]:
    """The scores table (default: against the file's reference)."""
    if ev.not_run:
        return [f"not scored: {ev.not_run}; estimators not run"]
    scores = ev.scores if scores is None else scores
    labels = list(scores)
    width = max(9, *(len(k) for k in labels)) if labels else 9
    lines = [f"{'estimator':<{width}}" + "".join(f"{h:>{CELL}}" for _, h, _, _ in COLUMNS)]
    notes: dict[tuple[str, str], list[str]] = {}  # (header, reason) -> estimators
    for label, s in scores.items():
        cells = []
        for name, head, scale, fmt in COLUMNS:
            v = getattr(s, name)
            if math.isfinite(v):
                cells.append(fmt.format(v * scale))
                continue
            key = (head, s.reasons.get(name, "not available"))
            notes.setdefault(key, []).append(label)
            cells.append(f"({list(notes).index(key) + 1})")
        lines.append(f"{label:<{width}}" + "".join(f"{c:>{CELL}}" for c in cells))
    for k, ((head, reason), who) in enumerate(notes.items(), start=1):
        scope = "" if len(who) == len(labels) else f" [{', '.join(who)}]"
        lines.append(f"  ({k}) {head}{scope}: {reason}")
    return lines


def skipped_lines(ev: Evaluation) -> list[str]:
    """The samples each estimator could not use at all (said once, under the scores)."""
    skipped = {label: s.skipped for label, s in ev.scores.items() if s.skipped}
    if not skipped:
        return []
    return ["  note: samples skipped (gyro not finite or beyond twice its full scale, or a "
            "bad time step): " + ", ".join(f"{label} {n}" for label, n in skipped.items())]


def phase_lines(ev: Evaluation) -> list[str]:
    """Error per flight phase (total°, inclination° when 6D): every part of the recording
    is scored, and the worst phase is the one to look at."""
    present = [p for p in PHASES if any(p in s.phases for s in ev.scores.values())]
    if len(present) < 2:
        return []
    labels = list(ev.scores)
    width = max(9, *(len(k) for k in labels))
    lines = ["by phase (total°, or incl° without magnetometer):",
             f"{'estimator':<{width}}" + "".join(f"{p:>{CELL + 1}}" for p in present)]
    for label, sc in ev.scores.items():
        key = "inclination_deg" if sc.six_d else "total_deg"
        cells = [f"{sc.phases[p][key]:.3f}" if p in sc.phases and
                 math.isfinite(sc.phases[p][key]) else "-" for p in present]
        lines.append(f"{label:<{width}}" + "".join(f"{c:>{CELL + 1}}" for c in cells))
    return lines


def smoothed_lines(ev: Evaluation) -> list[str]:
    """Without a truth: everything against the smoothed eskf, which is no truth."""
    if not ev.vs_smoothed:
        return []
    return [f"against {ev.smoothed_label} (the best estimate this log allows, NOT truth):",
            *table_lines(ev, ev.vs_smoothed)]


def print_summary(ev: Evaluation, stream: TextIO | None = None) -> None:
    out = stream if stream is not None else sys.stdout
    for line in (header_lines(ev) + table_lines(ev) + skipped_lines(ev) + phase_lines(ev)
                 + smoothed_lines(ev)):
        print(line, file=out)
