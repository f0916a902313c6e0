"""``dask worker tcp://HOST:8786 --preload replay.dask_preload``: workers that are ready
before their first log.

A fresh Dask worker imports the log readers and loads the estimators' compiled kernels
when the first replay task reaches it, about a second per worker that the first
``replay --scheduler`` sent to a new cluster pays (on two cores, a tenth of a 200-log
run). A worker started with this preload does it while it starts, like the local pool's
workers, which fork from a parent that has done it (``replay.parallel``). Later runs on
the same workers never pay it either way: the kernels stay loaded in the worker.

It warms replay's default estimators and the smoother; others load on first use.
"""

from __future__ import annotations

import logging
import time
from typing import Any

log = logging.getLogger(__name__)

#: Seconds the warm-up took in this process (None: not run here).
warmed_seconds: float | None = None


def dask_setup(worker: Any = None) -> None:
    """Dask's preload hook: called once in each worker process as it starts."""
    from .corpus_task import warm

    global warmed_seconds
    began = time.perf_counter()
    warm()
    warmed_seconds = time.perf_counter() - began
    log.info("attitude-bridge: replay kernels loaded in %.1f s", warmed_seconds)
