"""Speed: µs per sample of every estimator's ``update`` and ``batch``, vs imufusion and vqf.

    python benchmarks/speed.py [--trial 01] [--samples 20000] [--repeat 5]

All on the same BROAD trial. ``update`` is timed from a Python loop (one call per sample,
as the bridge does); ``batch`` is one compiled run over the trial repeated to at least
``--batch-samples`` samples. Times are this thread's CPU time (the machine is shared:
wall time would add whatever other processes take), best of ``--repeat`` interleaved
rounds. Compilation is excluded (warm-up first).

Targets (issue 2): per-sample ``update`` no slower than 1.5× imufusion called from a
Python loop; ``batch`` at least 10 M samples/s for mahony 6D.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: use this checkout's estimators
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import estimators

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "broad"
G = 9.80665
UPDATE_TARGET_RATIO = 1.5
BATCH_TARGET_MSPS = 10.0


@dataclass(frozen=True)
class Timing:
    label: str
    update_us: float  # per sample, Python loop; nan if not offered
    batch_us: float  # per sample, one call; nan if not offered


@dataclass
class Candidate:
    """Something to time: a per-sample loop and/or a batch call, with their sizes."""

    label: str
    loop: Callable[[], object] | None
    loop_samples: int
    batch: Callable[[], object] | None
    batch_samples: int
    best_loop: float = float("inf")
    best_batch: float = float("inf")


def cpu_seconds(fn: Callable[[], object]) -> float:
    """CPU time of this thread spent in ``fn()``: on a shared machine wall time also
    counts the time other processes hold the core."""
    t = time.thread_time()
    fn()
    return time.thread_time() - t


def measure(candidates: list[Candidate], repeat: int) -> list[Timing]:
    """Best of ``repeat`` rounds, rounds interleaved so load changes hit all alike."""
    for _ in range(repeat):
        for c in candidates:
            if c.loop is not None:
                c.best_loop = min(c.best_loop, cpu_seconds(c.loop))
            if c.batch is not None:
                c.best_batch = min(c.best_batch, cpu_seconds(c.batch))
    nan = float("nan")
    return [Timing(c.label,
                   c.best_loop / c.loop_samples * 1e6 if c.loop else nan,
                   c.best_batch / c.batch_samples * 1e6 if c.batch else nan)
            for c in candidates]


def estimator_candidate(name: str, gyr: np.ndarray, acc: np.ndarray,
                        mag: np.ndarray | None, rate: float, n_update: int,
                        big: tuple) -> Candidate:
    def loop() -> None:
        est = estimators.create(name, rate_hz=rate)
        update = est.update
        if mag is None:
            for i in range(n_update):
                update(gyr[i], acc[i])
        else:
            for i in range(n_update):
                update(gyr[i], acc[i], mag[i])

    G_, A_, M_ = big

    def batch() -> None:
        estimators.batch(name, G_, A_, None if mag is None else M_, rate_hz=rate)

    # Warm-up: compile (or load from the cache) both kernels before timing.
    estimators.create(name, rate_hz=rate).update(gyr[0], acc[0], None if mag is None else mag[0])
    estimators.batch(name, gyr[:10], acc[:10], None if mag is None else mag[:10], rate_hz=rate)
    return Candidate(f"{name} {'6D' if mag is None else '9D'}", loop, n_update, batch, len(G_))


def imufusion_candidate(gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None,
                        rate: float, n_update: int) -> Candidate:
    import imufusion

    gyr_deg, acc_g = np.degrees(gyr), acc / G

    def loop() -> None:
        ahrs = imufusion.Ahrs()
        settings = imufusion.AhrsSettings()
        # imufusion 1.3 ignores AhrsSettings(convention=...) given to the constructor.
        settings.convention = imufusion.CONVENTION_NED
        settings.sample_rate = rate
        ahrs.set_settings(settings)
        if mag is None:
            for i in range(n_update):
                ahrs.update_no_magnetometer(gyr_deg[i], acc_g[i])
        else:
            for i in range(n_update):
                ahrs.update(gyr_deg[i], acc_g[i], mag[i])

    return Candidate(f"imufusion {'6D' if mag is None else '9D'}", loop, n_update, None, 1)


def vqf_candidate(gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None, rate: float,
                  n_update: int, big: tuple) -> Candidate:
    import vqf

    def loop() -> None:
        f = vqf.VQF(1.0 / rate)
        if mag is None:
            for i in range(n_update):
                f.update(gyr[i], acc[i])
        else:
            for i in range(n_update):
                f.update(gyr[i], acc[i], mag[i])

    G_, A_, M_ = big

    def batch() -> None:
        f = vqf.VQF(1.0 / rate)
        if mag is None:
            f.updateBatch(G_, A_)
        else:
            f.updateBatch(G_, A_, M_)

    return Candidate(f"vqf {'6D' if mag is None else '9D'}", loop, n_update, batch, len(G_))


def format_table(rows: list[Timing], reference_us: dict[str, float]) -> str:
    head = (f"{'':<16}{'update µs':>11}{'vs imufusion':>14}{'batch µs':>10}"
            f"{'batch MS/s':>12}")
    lines = [head]
    for r in rows:
        ref = reference_us.get(r.label.split()[-1], float("nan"))
        ratio = r.update_us / ref if np.isfinite(ref) else float("nan")
        msps = 1.0 / r.batch_us if np.isfinite(r.batch_us) else float("nan")
        lines.append(f"{r.label:<16}{r.update_us:>11.2f}{ratio:>13.2f}×{r.batch_us:>10.4f}"
                     f"{msps:>12.2f}")
    return "\n".join(lines).replace(" nan×", "  - ").replace("nan", "  -")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--trial", default="01", help="trial number or name prefix")
    ap.add_argument("--samples", type=int, default=20000, help="samples for update loops")
    ap.add_argument("--batch-samples", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--estimator", action="append", help="limit to these estimators")
    args = ap.parse_args(argv)

    files = sorted(args.data.glob(f"{args.trial}*.npz"))
    if not files:
        print(f"speed.py: no trial {args.trial!r} in {args.data}", file=sys.stderr)
        return 2
    with np.load(files[0]) as d:
        rate = float(d["rate"])
        gyr, acc, mag = (np.ascontiguousarray(d[k], dtype=float) for k in ("gyr", "acc", "mag"))
    n_update = min(args.samples, len(gyr))
    reps = -(-args.batch_samples // len(gyr))
    big = tuple(np.ascontiguousarray(np.tile(x, (reps, 1))) for x in (gyr, acc, mag))
    names = args.estimator or estimators.names()

    print(f"{files[0].stem}: {len(gyr)} samples at {rate:.1f} Hz; update loops over "
          f"{n_update} samples, batch over {len(big[0])}; best of {args.repeat}")
    candidates: list[Candidate] = []
    for use_mag in (False, True):
        m = mag if use_mag else None
        candidates.append(imufusion_candidate(gyr, acc, m, rate, n_update))
        candidates.append(vqf_candidate(gyr, acc, m, rate, n_update, big))
        candidates += [estimator_candidate(n, gyr, acc, m, rate, n_update, big)
                       for n in names]
    rows = measure(candidates, args.repeat)
    reference = {r.label.split()[-1]: r.update_us for r in rows if r.label.startswith("imuf")}
    print(format_table(rows, reference))

    worst = max((r for r in rows if r.label.split()[0] in names),
                key=lambda r: r.update_us / reference[r.label.split()[-1]])
    ratio = worst.update_us / reference[worst.label.split()[-1]]
    verdict = "met" if ratio <= UPDATE_TARGET_RATIO else "MISSED"
    print(f"\nslowest update vs imufusion: {worst.label} {ratio:.2f}× "
          f"(target <= {UPDATE_TARGET_RATIO}×: {verdict})")
    mahony6 = next((r for r in rows if r.label == "mahony 6D"), None)
    if mahony6 is not None:
        msps = 1.0 / mahony6.batch_us
        print(f"mahony 6D batch: {msps:.1f} M samples/s (target >= {BATCH_TARGET_MSPS}: "
              f"{'met' if msps >= BATCH_TARGET_MSPS else 'MISSED'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
