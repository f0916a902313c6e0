"""A two-worker Dask ``LocalCluster`` in a process of its own, as a user's standing
cluster would be (``dask scheduler`` and ``dask worker`` started beforehand, elsewhere).

    python benchmarks/standing_cluster.py '{"distributed.worker.profile.enabled": false}'

The argument is Dask configuration as JSON (``{}``: Dask's defaults). It prints the
scheduler's address on one line and runs until its standard input closes.

Why a process of its own: a cluster started inside the benchmark shares that process's
interpreter lock with the benchmark's own threads (its memory sampler polls every 20 ms),
which slows the scheduler's answers, and with them the replay that is being measured.
"""

from __future__ import annotations

import json
import sys

import dask
from distributed import LocalCluster


def main() -> None:
    config = json.loads(sys.argv[1]) if len(sys.argv) > 1 else {}
    with dask.config.set(config), LocalCluster(n_workers=2, threads_per_worker=1,
                                               processes=True, dashboard_address=":0"
                                               ) as cluster:
        print(cluster.scheduler_address, flush=True)
        sys.stdin.read()


if __name__ == "__main__":
    main()
