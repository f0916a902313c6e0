"""Asking an autopilot for one parameter: PARAM_REQUEST_READ, retried a few times.

A parameter read over a lossy link may go unanswered; it is asked again after
``PARAM_TIMEOUT_S``, at most ``PARAM_TRIES`` times, and never again once answered
(until ``restart``: a reboot, an arming or a disarm may have changed it; or
``ask_again``: a value the autopilot has not set yet, or may still change).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

PARAM_TIMEOUT_S = 1.0
PARAM_TRIES = 3


@dataclass
class ParamQuery:
    """One parameter to read (``name`` None: nothing to ask)."""

    name: str | None = None
    tries: int = 0
    sent_at: float = -math.inf
    answered: bool = False
    routine: bool = False  # an ``ask_again``: worth a debug line, not an info one

    def restart(self, name: str | None) -> None:
        """Ask for ``name`` from scratch (None: stop asking)."""
        self.name, self.tries, self.sent_at, self.answered = name, 0, -math.inf, False
        self.routine = False

    def ask_again(self, now: float, after_s: float) -> None:
        """Ask for the same name once more, ``after_s`` seconds from monotonic ``now``."""
        if self.name is not None:
            self.tries, self.answered, self.routine = 0, False, True
            self.sent_at = now + after_s - PARAM_TIMEOUT_S

    def to_send(self, now: float) -> str | None:
        """The name to ask for at monotonic ``now`` (first try or a retry), else None."""
        if self.name is None or self.answered or self.tries >= PARAM_TRIES:
            return None
        if now - self.sent_at < PARAM_TIMEOUT_S:
            return None
        self.tries += 1
        self.sent_at = now
        return self.name

    def answer(self, name: str) -> bool:
        """True (and no more asking) when a PARAM_VALUE named ``name`` is the one asked."""
        if self.name is None or name != self.name:
            return False
        self.answered = True
        return True
