"""The corpus replay's one summary: per log (worst first), per estimator, per vehicle type
and per flight phase; as text, JSON and CSV.

It is arithmetic over the per-log entries that ``replay.corpus_task.replay_log`` returns
(every number in them comes from ``replay.evaluate``); nothing here runs an estimator.
A log's *score* for an estimator is the one ``tune`` minimises and the single-file
phase table shows: the total error, or the inclination error where heading is not
observable (no magnetometer, or a 6D estimator: BROAD's rule). Aggregates are over the
scored logs: mean, median and the worst log. Entries come ordered by path and every
aggregate is computed in that order, so the same logs give the same summary bit for bit,
whatever ran them.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .corpus_task import FAILED, NOT_SCORED, SCORED
from .flight import PHASES

SCORE_RULE = ("total error, or inclination where heading is not observable (no "
              "magnetometer or a 6D estimator)")
CELL = 9


def score_of(values: dict | None) -> float:
    """The score of one estimator's (or one phase's) numbers (see module docstring)."""
    if not values:
        return math.nan
    v = values.get("inclination_deg" if values.get("six_d") else "total_deg")
    return math.nan if v is None else float(v)


def phase_score(entry: dict, label: str, phase: str) -> float:
    est = entry.get("estimators", {}).get(label)
    if not est or phase not in est.get("phases", {}):
        return math.nan
    return score_of({**est["phases"][phase], "six_d": est.get("six_d")})


def _stats(values: list[tuple[float, str]]) -> dict:
    """mean / median / worst of finite (value, file) pairs, in the entries' order."""
    good = [(v, f) for v, f in values if math.isfinite(v)]
    if not good:
        return {"logs": 0, "mean_deg": None, "median_deg": None, "worst_deg": None,
                "worst_file": None}
    arr = np.array([v for v, _ in good])
    k = int(np.argmax(arr))  # the first of equal worst ones, by path
    return {"logs": len(good), "mean_deg": float(arr.mean()), "median_deg": float(np.median(arr)),
            "worst_deg": float(arr[k]), "worst_file": good[k][1]}


def _fmt(v: float | None, width: int = CELL) -> str:
    return f"{v:>{width}.3f}" if v is not None and math.isfinite(v) else f"{'-':>{width}}"


@dataclass(frozen=True)
class CorpusSummary:
    """Per-log entries (ordered by path) and the estimators' labels (order given)."""

    logs: tuple[dict, ...]
    labels: tuple[str, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "logs", tuple(sorted(self.logs, key=lambda e: e["file"])))

    def with_status(self, status: str) -> list[dict]:
        return [e for e in self.logs if e["status"] == status]

    @property
    def scored(self) -> list[dict]:
        return self.with_status(SCORED)

    def score(self, entry: dict, label: str) -> float:
        return score_of(entry.get("estimators", {}).get(label))

    def rank_key(self, entry: dict) -> float:
        """A scored log's place in the worst-first list: its mean score over the
        estimators (those with a score)."""
        values = [self.score(entry, label) for label in self.labels]
        good = [v for v in values if math.isfinite(v)]
        return float(np.mean(good)) if good else math.nan

    def worst_first(self) -> list[dict]:
        """Scored logs by decreasing mean score (ties by path), then the not scored and
        the failed ones by path."""
        scored = sorted(self.scored, key=lambda e: (-np.nan_to_num(self.rank_key(e),
                                                                   nan=-np.inf), e["file"]))
        return scored + self.with_status(NOT_SCORED) + self.with_status(FAILED)

    def by_estimator(self) -> dict[str, dict]:
        out = {}
        for label in self.labels:
            out[label] = {
                "score": _stats([(self.score(e, label), e["file"]) for e in self.scored]),
                "inclination": _stats([(_value(e, label, "inclination_deg"), e["file"])
                                       for e in self.scored])}
        return out

    def _grouped(self, groups: dict[str, list[dict]], phase: str | None = None
                 ) -> dict[str, dict]:
        out = {}
        for name, entries in groups.items():
            per = {}
            for label in self.labels:
                values = [(phase_score(e, label, phase) if phase else self.score(e, label),
                           e["file"]) for e in entries]
                st = _stats(values)
                per[label] = {"logs": st["logs"], "mean_deg": st["mean_deg"]}
            logs = max((v["logs"] for v in per.values()), default=0)
            if logs:
                out[name] = {"logs": logs, "estimators": per}
        return out

    def by_vehicle(self) -> dict[str, dict]:
        """Per vehicle type the log says (HEARTBEAT / MAV_TYPE; "unknown" without)."""
        groups: dict[str, list[dict]] = {}
        for e in self.scored:
            groups.setdefault(e.get("vehicle", "unknown"), []).append(e)
        return self._grouped(dict(sorted(groups.items())))

    def by_phase(self) -> dict[str, dict]:
        """Per flight phase (``replay.flight.PHASES``), over the logs that have it."""
        out = {}
        for phase in PHASES:
            out.update(self._grouped({phase: self.scored}, phase))
        return out

    def as_json(self) -> dict:
        counts = {s: len(self.with_status(s)) for s in (SCORED, NOT_SCORED, FAILED)}
        return {
            "logs": len(self.logs), **{k.replace(" ", "_"): v for k, v in counts.items()},
            "estimators": list(self.labels), "score": SCORE_RULE,
            "by_estimator": self.by_estimator(), "by_vehicle": self.by_vehicle(),
            "by_phase": self.by_phase(),
            "worst_first": [e["file"] for e in self.worst_first()],
            "per_log": list(self.logs),
        }

    def lines(self) -> list[str]:
        """The text summary (stdout)."""
        counts = {s: len(self.with_status(s)) for s in (SCORED, NOT_SCORED, FAILED)}
        lines = [f"corpus: {len(self.logs)} logs: {counts[SCORED]} scored, "
                 f"{counts[NOT_SCORED]} not scored, {counts[FAILED]} failed",
                 f"score [deg]: {SCORE_RULE}"]
        heads = [f"{lab:>{max(CELL, len(lab) + 1)}}" for lab in self.labels]
        widths = [len(h) for h in heads]
        if self.scored:
            name_w = max(len("log"), *(len(e["file"]) for e in self.scored))
            lines.append("per log, worst first:")
            lines.append(f"{'log':<{name_w}} {'vehicle':<10}" + "".join(heads))
            for e in self.worst_first()[:counts[SCORED]]:
                lines.append(f"{e['file']:<{name_w}} {e.get('vehicle', ''):<10}"
                             + "".join(_fmt(self.score(e, lab), w)
                                       for lab, w in zip(self.labels, widths, strict=True)))
            lines += self._estimator_lines()
            lines += self._group_lines("by vehicle type (mean score, logs):",
                                       self.by_vehicle(), heads, widths)
            lines += self._group_lines("by flight phase (mean score over the logs with that "
                                       "phase):", self.by_phase(), heads, widths)
        for status in (NOT_SCORED, FAILED):
            entries = self.with_status(status)
            if entries:
                lines.append(f"{status}:")
                lines += [f"  {_named(e)}" for e in entries]
        return lines

    def _estimator_lines(self) -> list[str]:
        width = max(9, *(len(lab) for lab in self.labels))
        lines = ["by estimator (score over the scored logs; inclination beside it):",
                 f"{'estimator':<{width}}{'logs':>6}{'mean':>{CELL}}{'median':>{CELL}}"
                 f"{'worst':>{CELL}}{'incl mean':>{CELL + 2}}  worst log"]
        for label, agg in self.by_estimator().items():
            s, i = agg["score"], agg["inclination"]
            lines.append(f"{label:<{width}}{s['logs']:>6}{_fmt(s['mean_deg'])}"
                         f"{_fmt(s['median_deg'])}{_fmt(s['worst_deg'])}"
                         f"{_fmt(i['mean_deg'], CELL + 2)}  {s['worst_file'] or '-'}")
        return lines

    @staticmethod
    def _group_lines(title: str, groups: dict[str, dict], heads: list[str],
                     widths: list[int]) -> list[str]:
        if not groups:
            return []
        name_w = max(10, *(len(n) for n in groups))
        lines = [title, f"{'':<{name_w}}{'logs':>6}" + "".join(heads)]
        for name, g in groups.items():
            cells = "".join(_fmt(v["mean_deg"], w)
                            for v, w in zip(g["estimators"].values(), widths, strict=True))
            lines.append(f"{name:<{name_w}}{g['logs']:>6}{cells}")
        return lines

    def write_csv(self, path: str | Path) -> None:
        """One row per log, worst first: status and reason, what the log is, and per
        estimator its score, total and inclination [deg]."""
        cols = [(lab, key) for lab in self.labels
                for key in ("score_deg", "total_deg", "inclination_deg")]
        with Path(path).open("w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(["file", "status", "reason", "format", "vehicle", "duration_s",
                        "samples", "reference", *(f"{k}[{lab}]" for lab, k in cols)])
            for e in self.worst_first():
                row = [e["file"], e["status"], e.get("reason") or "", e.get("format", ""),
                       e.get("vehicle", ""), e.get("duration_s", ""), e.get("samples", ""),
                       e.get("reference") or ""]
                for lab, key in cols:
                    v = (self.score(e, lab) if key == "score_deg"
                         else _value(e, lab, key))
                    row.append("" if not math.isfinite(v) else repr(v))
                w.writerow(row)


def _named(entry: dict) -> str:
    """The reason, after the log's name unless the reason starts with it (the readers'
    errors do)."""
    reason = entry.get("reason") or ""
    return reason if reason.startswith(entry["file"]) else f"{entry['file']}: {reason}"


def _value(entry: dict, label: str, key: str) -> float:
    v = entry.get("estimators", {}).get(label, {}).get(key)
    return math.nan if v is None else float(v)


def summarise(entries: Sequence[dict], labels: Sequence[str]) -> CorpusSummary:
    return CorpusSummary(tuple(entries), tuple(labels))
