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


def run_on_cluster(fn: Callable[..., Any], tasks: Sequence[Task], address: str,
                   on_crash: OnCrash, notify: OnDone, order: Sequence[int]) -> Outcome:
    """Every task on the cluster; results in task order (see ``replay.parallel.run``).

    A task that fails on the cluster (its worker died, the worker lacks attitude-bridge)
    gets ``on_crash`` with Dask's reason; the others go on.
    """
    from distributed import as_completed

    client = connect(address)
    out = Outcome([None] * len(tasks))
    futures = []
    try:
        # submitted in ``order``: Dask runs earlier submissions first
        futures = [client.submit(fn, *tasks[i], pure=False) for i in order]
        index = {f.key: i for f, i in zip(futures, order, strict=True)}
        for fut in as_completed(futures, loop=client.loop):
            i = index[fut.key]
            try:
                out.results[i] = fut.result()
            except Exception as exc:
                why = " ".join(f"{type(exc).__name__}: {exc}".split())
                out.results[i] = on_crash(tasks[i], f"on the Dask cluster: {why}")
            fut.release()  # the worker may forget it now
            notify(i, out.results[i])
    except KeyboardInterrupt:
        out.interrupted = True
        client.cancel(futures)
    finally:
        with _quiet_dask():
            client.close()
    return out
