"""``attitude-bridge warmup``: compile the estimators (the live comparison, the emulator)
ahead of use.

numba compiles each estimator's kernels the first time one is created, about 10–40 s
each on a small machine, and keeps them in its on-disk cache (next to the package, or
in ``NUMBA_CACHE_DIR``). ``install.sh`` and the Docker image run this once so that the
first ``demo`` or ``run`` starts in seconds instead of sitting silent for minutes; the
bridge itself calls :func:`warm_up` for its own estimators before it serves (cheap when
cached) and reports the progress per estimator, so a cold start is never silent.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from estimators import quat
from estimators.spec import EstimatorSpec

#: Called before (seconds None) and after (seconds taken) each item is compiled.
Progress = Callable[[str, float | None], None]


def warm_up(spec: EstimatorSpec) -> None:
    """Compile every kernel of one estimator the bridge and replay call: ``update``
    with and without a magnetometer (compiled when created), the batch loop, and the
    Euler conversion of its output (the bridge's ATTITUDE)."""
    est = spec.create(100.0)
    acc, mag = np.array([0.0, 0.0, -9.8]), np.array([0.2, 0.0, 0.4])
    est.update(np.zeros(3), acc, mag, 0.01)
    est.update(np.zeros(3), acc, None, 0.01, vel=np.zeros(3), vel_age=0.0)
    est.run(np.zeros((2, 3)), np.tile(acc, (2, 1)), np.tile(mag, (2, 1)), 0.01)
    quat.to_euler(est.q)


def warm_up_comparison() -> None:
    """Compile the live comparison's shift search (every bridge with a reference)."""
    from estimators.shifted_error import rms_at_shifts

    t = np.array([0.0, 0.01, 0.02])
    q = np.tile(quat.identity(), (3, 1))
    rms_at_shifts(t, q, t, q, np.array([0.0]), 0.02, 1)


def warm_up_emulator() -> None:
    """Compile the emulated MPU6050's low-pass filter (the HIL emulator's one kernel)."""
    from hil import EmulatorConfig, simulate

    simulate(EmulatorConfig(profile="static", duration_s=0.05, seed=0))


def warm_up_smoother() -> None:
    """Compile the eskf's smoother (``replay --smooth``): its tapped forward driver and
    the backward pass."""
    import estimators

    acc, mag = np.tile([0.0, 0.0, -9.8], (40, 1)), np.tile([0.2, 0.0, 0.4], (40, 1))
    estimators.smooth("eskf", np.zeros((40, 3)), acc, mag, rate_hz=100.0)


def warm_up_all(specs: Iterable[EstimatorSpec], progress: Progress | None = None,
                emulator: bool = False) -> dict[str, float]:
    """Compile each estimator, the live comparison (and optionally the emulator and the
    smoother); seconds taken per item."""
    jobs: list[tuple[str, Callable[[], None]]] = [
        (spec.label, lambda s=spec: warm_up(s)) for spec in specs]
    jobs.append(("comparison", warm_up_comparison))
    if emulator:
        jobs.append(("emulator", warm_up_emulator))
        jobs.append(("smoother", warm_up_smoother))
    taken = {}
    for name, job in jobs:
        if progress is not None:
            progress(name, None)
        start = time.perf_counter()
        job()
        taken[name] = time.perf_counter() - start
        if progress is not None:
            progress(name, taken[name])
    return taken


@contextlib.contextmanager
def interruptible() -> Iterator[None]:
    """SIGINT and SIGTERM raise KeyboardInterrupt inside the block.

    The bridge compiles its estimators inside its event loop, which is blocked until the
    compiler is done, and the loop's own signal handlers only wake the loop: Ctrl-C on a
    cold start waited for the compilation (a minute on a small machine). Python-level
    handlers run between the compiler's bytecodes, so one that raises stops it at once.
    Outside the main thread (no signals there) the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    previous = {sig: signal.signal(sig, interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)


class LineProgress:
    """Progress on one line of a stream: ``preparing estimators: eskf 31.2 s, mahony
    ...``, each name shown before its (possibly long) compilation starts."""

    def __init__(self, title: str, total: int | None = None, stream=None) -> None:
        self.title = title
        self.total = total  # the line ends after this many items (else at done())
        self.stream = stream if stream is not None else sys.stderr
        self.started = False
        self.finished = 0

    def __call__(self, name: str, seconds: float | None) -> None:
        s = self.stream
        if seconds is None:
            s.write(("" if self.started else f"{self.title}: ") +
                    ("" if not self.started else ", ") + f"{name} ")
            self.started = True
        else:
            s.write(f"{seconds:.1f} s")
            self.finished += 1
            if self.finished == self.total:
                self.done()
        s.flush()

    def done(self) -> None:
        """End the line (once), e.g. before log lines follow."""
        if self.started:
            self.stream.write("\n")
            self.stream.flush()
            self.started = False


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "warmup", help="compile the estimators now (numba, cached on disk)",
        description="Compile every estimator's kernels, the live comparison's and the "
                    "emulator's, so the first run starts at once. install.sh runs it; run "
                    "it again after an upgrade or with another NUMBA_CACHE_DIR.")
    p.add_argument("names", nargs="*", metavar="ESTIMATOR",
                   help="only these estimators and the live comparison (default: all, "
                        "the emulator and the smoother)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import estimators

    specs = [EstimatorSpec.parse(n) for n in (args.names or estimators.names())]
    progress = LineProgress("attitude-bridge warmup: compiling",
                            len(specs) + (1 if args.names else 3))
    start = time.perf_counter()
    try:
        warm_up_all(specs, progress, emulator=not args.names)
    finally:
        progress.done()
    print(f"attitude-bridge warmup: {len(specs)} estimator(s) ready in "
          f"{time.perf_counter() - start:.1f} s (cached for later runs)", file=sys.stderr)
    return 0
