"""Says when the attitudes the bridge sends are late: the machine does not keep up.

A consumer takes ATTITUDE_QUATERNION as the vehicle's attitude now. One sent a large
part of a second after its IMU sample arrived is a past attitude presented as current,
and nothing else would tell: the estimate itself stays right, only late. It happens
when the bridge does not get the CPU it needs (a busy companion computer, more
estimators than the input rate allows), and the user can act on it. So once per status
period: when more than ``LATE_SHARE`` of the attitudes sent since the last check left
``LATE_S`` (``bridge.publish.output``) or more after their sample arrived, a warning,
once until they are on time again (said at INFO). A single late attitude (a scheduling
hiccup) is counted in the status (``sent_late``), not warned about.
"""

from __future__ import annotations

import logging

from ..publish.output import LATE_S, LateWindow

log = logging.getLogger(__name__)

#: Share of the attitudes sent in a status period that must be late for a warning.
LATE_SHARE = 0.1


class LatenessWatch:
    """Warns once when the attitudes go out late, and says when they are on time again."""

    def __init__(self) -> None:
        self.late_since: float | None = None  # monotonic time the warning was given
        self.warnings = 0

    def check(self, window: LateWindow, period_s: float, now: float) -> None:
        """``window``: what was sent over the last ``period_s`` (monotonic ``now``)."""
        if not window.sent:
            return
        if self.late_since is None and window.late > LATE_SHARE * window.sent:
            self.late_since = now
            self.warnings += 1
            log.warning("attitudes sent late: %d of %d in the last %.0f s left %.0f ms or "
                        "more after their IMU sample arrived (worst %.0f ms); the bridge "
                        "does not get the CPU it needs: fewer estimators (-e) or a less "
                        "busy machine", window.late, window.sent, period_s, LATE_S * 1e3,
                        window.worst_s * 1e3)
        elif self.late_since is not None and not window.late:
            log.info("attitudes on time again (late for %.1f s)", now - self.late_since)
            self.late_since = None
