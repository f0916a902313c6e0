"""``tune --cross-validate``: leave-one-log-out (or one folder out) over a finished sweep.

The sweep (``replay.tune.Sweep``) already holds every grid point's score on every log.
For each held-out group the grid point is chosen by tune's own rule on the other logs
(lowest mean of the objective: total, or inclination for 6D; the first of equal ones)
and read off the matrix on the held-out logs. Nothing is run again, so the
cross-validated numbers cost nothing beyond the sweep and cannot differ from it.

What it measures: how much of the in-sample error is the choice fitting the logs it is
scored on. It is "cross-validated", not "data never seen": the grid and the estimator's
design were chosen by someone who may have looked at the same logs.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .tune import Sweep

GROUPINGS = ("log", "folder")


@dataclass(frozen=True)
class HeldOut:
    """One held-out log: the point chosen without its group, and both scores [deg]."""

    file: str
    group: str
    chosen: dict[str, float] | None  # None: no point scored finitely on the other logs
    cross_validated_deg: float
    in_sample_deg: float


@dataclass(frozen=True)
class CrossValidation:
    objective: str  # "total" | "inclination"
    group_by: str
    best: dict[str, float]  # the in-sample choice (all logs)
    logs: tuple[HeldOut, ...]

    @property
    def cross_validated_mean_deg(self) -> float:
        return float(np.mean([h.cross_validated_deg for h in self.logs]))

    @property
    def worst(self) -> HeldOut:
        """The held-out log with the largest cross-validated error (NaN counts as worst)."""
        return max(self.logs, key=lambda h: (math.inf if math.isnan(h.cross_validated_deg)
                                             else h.cross_validated_deg))

    @property
    def in_sample_mean_deg(self) -> float:
        return float(np.mean([h.in_sample_deg for h in self.logs]))

    def as_json(self) -> dict:
        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        return {"objective": f"mean {self.objective} RMSE [deg]", "group_by": self.group_by,
                "in_sample_best": self.best,
                "cross_validated_mean_deg": num(self.cross_validated_mean_deg),
                "cross_validated_worst_deg": num(self.worst.cross_validated_deg),
                "cross_validated_worst_file": self.worst.file,
                "in_sample_mean_deg": num(self.in_sample_mean_deg),
                "logs": [{"file": h.file, "group": h.group, "chosen": h.chosen,
                          "cross_validated_deg": num(h.cross_validated_deg),
                          "in_sample_deg": num(h.in_sample_deg)} for h in self.logs]}

    def lines(self) -> list[str]:
        held = "log" if self.group_by == "log" else "folder"
        width = max(3, *(len(h.file) for h in self.logs))
        chosen = [", ".join(f"{k}={v:.6g}" for k, v in h.chosen.items()) if h.chosen
                  else "(none)" for h in self.logs]
        cw = max(6, *(len(c) for c in chosen))
        out = [f"cross-validated (leave one {held} out: the grid point with the lowest mean "
               f"{self.objective} on the other logs, scored on the held-out one) [deg]:",
               f"  {'log':<{width}}  {'chosen':<{cw}}  cross-validated  in-sample"]
        for h, c in zip(self.logs, chosen, strict=True):
            out.append(f"  {h.file:<{width}}  {c:<{cw}}  {h.cross_validated_deg:>15.3f}  "
                       f"{h.in_sample_deg:>9.3f}")
        w = self.worst
        out.append(f"cross-validated mean {self.cross_validated_mean_deg:.3f} deg, worst "
                   f"{w.cross_validated_deg:.3f} ({w.file}); in-sample mean "
                   f"{self.in_sample_mean_deg:.3f} deg (the best point on all logs)")
        return out


def group_of(file: str, group_by: str) -> str:
    if group_by not in GROUPINGS:
        raise ValueError(f"--group-by {group_by!r}: expected one of {GROUPINGS}")
    return file if group_by == "log" else str(Path(file).parent)


def objective_matrix(sweep: Sweep) -> np.ndarray:
    """(P, F) what tune minimises, NaN for the points not done (an interrupted sweep)."""
    m = sweep.inclination if sweep.objective == "inclination" else sweep.total
    return np.where(sweep.done[:, None], m, np.nan)


def choose(matrix: np.ndarray, columns: np.ndarray) -> int | None:
    """tune's rule on a subset of the logs: lowest mean over them, the first of equal
    ones; a point with a NaN on any of them is out. None when no point is left."""
    mean = matrix[:, columns].mean(axis=1)
    if not np.isfinite(mean).any():
        return None
    return int(np.nanargmin(mean))


def _content_digest(path: str) -> str | None:
    """SHA-256 of the file, read once per version of it (tune checks the groups again
    after leaving logs out, and cross_validate once more)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return _digest_of(os.path.realpath(path), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=4096)
def _digest_of(path: str, mtime_ns: int, size: int) -> str | None:
    try:
        with open(path, "rb") as f:
            return hashlib.file_digest(f, "sha256").hexdigest()
    except OSError:
        return None


def identical_logs(files: list[str]) -> list[tuple[str, ...]]:
    """Sets of files with the same content (a log copied under another name)."""
    by_digest: dict[str, list[str]] = {}
    for f in files:
        digest = _content_digest(f)
        if digest is not None:
            by_digest.setdefault(digest, []).append(f)
    return [tuple(same) for same in by_digest.values() if len(same) > 1]


def check_groups(files: list[str], group_by: str) -> list[str]:
    """Each file's group; at least two groups, or there is nothing to hold out.

    Files with the same content share a group (with their groups merged): a copy of
    the held-out log left among the others would make "held out" in-sample."""
    groups = [group_of(f, group_by) for f in files]
    parent = {g: g for g in groups}

    def root(g: str) -> str:
        while parent[g] != g:
            g = parent[g]
        return g

    index = {f: k for k, f in enumerate(files)}
    for same in identical_logs(files):
        first = root(groups[index[same[0]]])
        for f in same[1:]:
            parent[root(groups[index[f]])] = first
    groups = [root(g) for g in groups]
    if len(set(groups)) < 2:
        raise ValueError(f"--cross-validate needs at least two {group_by}s to hold out one "
                         f"at a time (got {len(set(groups))})")
    return groups


def cross_validate(sweep: Sweep, group_by: str = "log") -> CrossValidation:
    groups = check_groups(list(sweep.files), group_by)
    matrix = objective_matrix(sweep)
    best = choose(matrix, np.arange(len(groups)))
    if best is None:
        raise ValueError("no grid point produced a finite score")
    logs = []
    for k, (file, group) in enumerate(zip(sweep.files, groups, strict=True)):
        others = np.array([g != group for g in groups])
        p = choose(matrix, others)
        logs.append(HeldOut(file, group, None if p is None else dict(sweep.points[p]),
                            math.nan if p is None else float(matrix[p, k]),
                            float(matrix[best, k])))
    return CrossValidation(sweep.objective, group_by, {**sweep.fixed, **sweep.points[best]},
                           tuple(logs))
