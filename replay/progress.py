"""A one-line text progress bar on stderr, shared by ``tune`` and the corpus replay.

No dependency (no tqdm): it redraws one line in place with ``\\r``, so it also reads
sensibly in a CI log. The corpus replay counts failures too (``advance(failed=True)``),
because a batch that goes on past broken logs should say so while it runs, not only at
the end.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """``[#####     ] 12/200 ..., eta 31.0 s``; with ``count_failed`` also "N failed"."""

    def __init__(self, total: int, stream: TextIO | None = None, width: int = 30,
                 count_failed: bool = False) -> None:
        self.total, self.done, self.failed, self.width = total, 0, 0, width
        self.count_failed = count_failed
        self.stream = stream if stream is not None else sys.stderr
        self.started = time.perf_counter()

    def advance(self, n: int = 1, failed: bool = False) -> None:
        self.done += n
        self.failed += n if failed else 0
        frac = self.done / max(self.total, 1)
        elapsed = time.perf_counter() - self.started
        eta = elapsed / frac - elapsed if frac > 0 else float("nan")
        bar = "#" * int(frac * self.width)
        failures = f" done, {self.failed} failed," if self.count_failed else ""
        self.stream.write(f"\r[{bar:<{self.width}}] {self.done}/{self.total}{failures} "
                          f"{elapsed:6.1f} s, eta {eta:5.1f} s")
        if self.done >= self.total:
            self.stream.write("\n")
        self.stream.flush()

    def interrupt(self) -> None:
        """End the bar's line early (Ctrl-C), so what follows starts on a fresh line."""
        if self.done < self.total:
            self.stream.write("\n")
            self.stream.flush()
