"""``--scheduler tcp://HOST:PORT``: run replay / tune tasks on an existing Dask cluster.

Someone who outgrows one machine starts ``dask scheduler`` on one host and ``dask worker
tcp://HOST:8786`` on each of the others (every one with attitude-bridge installed and
the logs at the same path, e.g. a shared folder); ``--scheduler tcp://HOST:8786`` sends
the tasks there. A task carries a path and the options, never a log's samples: workers
read the logs themselves, so the client's memory and the network carry only scores.

Dask is the optional extra ``cluster`` (``pip install 'attitude-bridge[cluster]'``).
Every way of not getting a working cluster is a one-line error within a few seconds
(``CONNECT_TIMEOUT_S``): Dask missing, an address that is not one, nothing listening, a
host that does not resolve, something other than a Dask scheduler answering, or a
scheduler without workers. The address is probed with one raw request before a
``Client`` is made: a ``Client`` whose connection failed complains again, with
tracebacks, when it is garbage-collected.
"""

from __future__ import annotations

import asyncio
import importlib.util
import logging
import os
import sys
from collections import deque
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from typing import Any
from urllib.parse import SplitResult, urlsplit

from .dataset import ReplayInputError
from .parallel import OnCrash, OnDone, Outcome, Task

CONNECT_TIMEOUT_S = 5.0
EXTRA = "cluster"
SCHEME = "tcp"  # tls:// would need Dask security settings (certificates) not taken here


def require_dask() -> None:
    if importlib.util.find_spec("distributed") is None:
        raise ReplayInputError(f"--scheduler needs dask.distributed: pip install "
                               f"'attitude-bridge[{EXTRA}]'")


def _split(address: str) -> tuple[SplitResult, int | None] | None:
    """The address's parts and port; None for what urlsplit refuses outright (an
    unclosed ``[`` of an IPv6 host). A port that is no number is None."""
    try:
        parts = urlsplit(address)
    except ValueError:
        return None
    try:
        return parts, parts.port
    except ValueError:
        return parts, None


def check_address(address: str) -> None:
    """``tcp://HOST:PORT``, before any connection is tried; every refusal names the
    option. ``tls://`` is refused as such: without the certificates Dask's TLS needs,
    its connection fails in a way that looks like a foreign server."""
    split = _split(address)
    if split is not None and split[0].scheme == "tls":
        raise ReplayInputError(f"--scheduler {address!r}: only tcp:// is supported "
                               f"(tls:// needs Dask security settings this option does "
                               f"not take)")
    parts, port = split or (None, None)
    if (parts is None or parts.scheme != SCHEME or not parts.hostname or port is None
            or parts.path):
        raise ReplayInputError(f"--scheduler {address!r}: expected a Dask scheduler's "
                               f"address, tcp://HOST:PORT (e.g. tcp://10.0.0.5:8786)")


async def _identity(address: str, timeout: float) -> dict:
    """The scheduler's answer to one identity request (TimeoutError if none comes): Dask's
    own connect timeout covers the TCP connection, retried until ``timeout``, but not
    its handshake, so a listener that accepts and stays silent would hold it for ever.
    The whole exchange gets a second more than the connection, so that a refused or
    unreachable address still fails as Dask says it."""
    from distributed.comm import connect

    async def ask() -> dict:
        comm = await connect(address, timeout=timeout)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    return await asyncio.wait_for(ask(), timeout + 1.0)


@contextmanager
def _quiet_dask():
    """Dask logs its connection retries and shutdown chatter; the one-line error says it."""
    log = logging.getLogger("distributed")
    level = log.level
    log.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        log.setLevel(level)


def connect(address: str, timeout: float | None = None):
    """A ``distributed.Client`` on a scheduler that answers and has workers."""
    require_dask()
    check_address(address)
    timeout = CONNECT_TIMEOUT_S if timeout is None else timeout
    from distributed import Client

    where = f"--scheduler {address}"
    with _quiet_dask():
        try:
            reply = asyncio.run(_identity(address, timeout))
        except TimeoutError:  # nothing connected, or a listener that does not answer
            raise ReplayInputError(f"{where}: no Dask scheduler answered within "
                                   f"{timeout + 1.0:g} s") from None
        except OSError as exc:  # refused, unreachable, unknown host
            raise ReplayInputError(f"{where}: cannot connect within {timeout:g} s "
                                   f"({' '.join(str(exc).split()) or type(exc).__name__})"
                                   ) from None
        except Exception as exc:  # something answered, not in Dask's protocol
            raise ReplayInputError(f"{where}: what answers there is not a Dask scheduler "
                                   f"({type(exc).__name__})") from None
        if not isinstance(reply, dict) or reply.get("type") != "Scheduler":
            raise ReplayInputError(f"{where}: what answers there is not a Dask scheduler")
        try:
            client = Client(address, timeout=timeout, set_as_default=False)
        except Exception as exc:
            raise ReplayInputError(f"{where}: cannot connect ({exc})") from None
        try:
            client.wait_for_workers(1, timeout=timeout)
        except Exception:
            client.close()
            raise ReplayInputError(f"{where}: the scheduler has no workers (start some: "
                                   f"dask worker {address})") from None
    return client


#: An event-loop tick more frequent than this costs a replay task CPU (Dask's default is
#: 20 ms: each tick takes the interpreter lock from the thread that runs the log).
SLOW_TICK_S = 0.5
#: glibc told to return freed memory above this hands each log's arrays back to the
#: system and maps them again for the next (Dask's nanny sets 64 kB).
MIN_TRIM_BYTES = 1 << 20


def worker_costs() -> list[str]:
    """Run on a worker (``Client.run``): which of Dask's defaults that cost a replay task
    CPU this worker runs (README's ``export`` line for ``dask worker`` turns each off)."""
    import dask
    from dask.utils import parse_timedelta

    costs = []
    if dask.config.get("distributed.worker.profile.enabled", False):
        costs.append("the sampling profiler")
    tick = parse_timedelta(dask.config.get("distributed.admin.tick.interval", "1s"))
    if tick is not None and tick < SLOW_TICK_S:
        costs.append(f"an event-loop tick every {tick * 1000:g} ms")
    trim = os.environ.get("MALLOC_TRIM_THRESHOLD_", "")
    if trim.isdigit() and int(trim) < MIN_TRIM_BYTES:
        costs.append(f"glibc returning memory above {int(trim) // 1024} kB")
    return costs


def advise_on_workers(client) -> str | None:
    """One line for the user when the cluster's workers run settings that slow replay
    (None when they do not, or cannot say: it is advice, and a worker that cannot
    answer shows in the tasks anyway)."""
    try:
        found = client.run(worker_costs)
    except Exception:
        return None
    slow = [costs for costs in found.values() if costs]
    if not slow:
        return None
    names = sorted({cost for costs in slow for cost in costs})
    return (f"note: --scheduler: {len(slow)} of {len(found)} worker(s) run "
            f"{', '.join(names)}, which cost replay 10-20 % more CPU per log; README's "
            f"`export` line for `dask worker` turns them off")


#: A batch holds 1/(BATCH_SHARE × workers) of the work not yet sent.
BATCH_SHARE = 3


class GuidedBatches:
    """The tasks in ``order`` cut into batches as they are sent, each about
    1/(BATCH_SHARE·workers) of the weight not yet sent (``workers``: the cluster's threads
    at that moment), and at least one task (guided self-scheduling).

    Why batches: every Dask task costs the worker, the scheduler and the client several
    milliseconds of CPU, and a short log's replay takes a few tens of them, so one task
    per log spends a fair share of a small cluster's cores on bookkeeping. Why shrinking
    ones: the first batches are large (few tasks to schedule), the last hold one task
    each, so the workers run out of work together instead of one waiting for another's
    large last batch. The number of tasks grows with the logarithm of their count.
    """

    def __init__(self, order: Sequence[int], weights: Sequence[float]):
        self._left = deque(order)
        self._weights = weights
        self._weight_left = float(sum(weights[i] for i in order))

    def __bool__(self) -> bool:
        return bool(self._left)

    def next(self, workers: int) -> list[int]:
        target = self._weight_left / (max(1, workers) * BATCH_SHARE)
        batch: list[int] = []
        taken = 0.0
        while self._left and (not batch or taken < target):
            batch.append(self._left.popleft())
            taken += self._weights[batch[-1]]
        self._weight_left -= taken
        return batch


def run_batch(fn: Callable[..., Any], batch: Sequence[Task]) -> list[Any]:
    """One Dask task: ``fn`` over several of the caller's tasks, one after the other (a
    worker's memory holds one log at a time, and only the small results pile up)."""
    return [fn(*task) for task in batch]


def _threads(client) -> int:
    """Threads the cluster's workers offer now (asked again after every batch: a worker
    that joins later gets the next one)."""
    return max(1, sum(client.nthreads().values()))


def run_on_cluster(fn: Callable[..., Any], tasks: Sequence[Task], address: str,
                   on_crash: OnCrash, notify: OnDone, order: Sequence[int],
                   weights: Sequence[float] | None = None) -> Outcome:
    """Every task on the cluster; results in task order (see ``replay.parallel.run``).

    Tasks go in batches (``GuidedBatches``, cut by ``weights``: e.g. each log's size;
    equal without), one batch per worker thread at a time: a batch queued behind a
    worker's running one would wait there while another worker idles. A batch that
    fails on the cluster (its worker died, the worker lacks attitude-bridge, a task
    raised) is sent again one task at a time, so that only the task that fails gets
    ``on_crash`` with Dask's reason; the others go on.
    """
    from distributed import as_completed

    client = connect(address)
    advice = advise_on_workers(client)
    if advice:
        print(advice, file=sys.stderr)
    out = Outcome([None] * len(tasks))
    sent: dict[str, tuple[Any, list[int]]] = {}
    pending = as_completed(loop=client.loop)

    batches = GuidedBatches(order, [1.0] * len(tasks) if weights is None else weights)

    def send(batch: list[int]) -> None:
        future = client.submit(run_batch, fn, [tasks[i] for i in batch], pure=False)
        sent[future.key] = (future, batch)
        pending.add(future)

    def top_up() -> None:
        threads = _threads(client)
        while batches and len(sent) < threads:
            send(batches.next(threads))

    try:
        top_up()
        for future in pending:
            _, batch = sent.pop(future.key)
            try:
                results = future.result()
            except Exception as exc:
                if len(batch) > 1:  # find the one that fails: each again, alone
                    for i in batch:
                        send([i])
                    continue
                why = " ".join(f"{type(exc).__name__}: {exc}".split())
                results = [on_crash(tasks[batch[0]], f"on the Dask cluster: {why}")]
            finally:
                future.release()  # the worker may forget it now
            top_up()
            for i, result in zip(batch, results, strict=True):
                out.results[i] = result
                notify(i, result)
    except KeyboardInterrupt:
        out.interrupted = True
        client.cancel([future for future, _ in sent.values()])
    finally:
        with _quiet_dask():
            client.close()
    return out
