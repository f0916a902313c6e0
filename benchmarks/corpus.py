"""Corpus replay speed: 200 short logs on one core, on two local workers and on a
two-worker Dask ``LocalCluster``, with each run's peak memory per worker.

    python benchmarks/corpus.py [--logs 200] [--json corpus_bench.json] [--keep DIR]

The corpus is made in a temporary folder (``--keep DIR`` to keep it there) and mixes
every format the readers know: cuts of the BROAD trials (npz), cuts of the PX4 SIH and
the PX4 / ArduPilot SITL flights (tlog, ``../shared/data/px4_sih`` and ``tests/data/sitl``),
the development ULogs and the 3 Hz dronekit tlog (not scored: too slow to estimate from),
the emulator streaming MAVLink over UDP recorded by the bridge's own ``TlogRecorder``
(tlog) and emulator runs written in the documented CSV format, plus one corrupt tlog and
one truncated ULog (reported, not scored). Each log is a few seconds to about thirty.

Each run is the real command line in a subprocess (``attitude-bridge replay DIR -q
--json ...``, default estimators): ``--jobs 1``, ``--jobs 2`` and ``--scheduler`` on a
``LocalCluster(n_workers=2, threads_per_worker=1)`` started in a process of its own
(``benchmarks/standing_cluster.py``; its start-up is not timed, as a user's cluster
would already be running): once with Dask's defaults, its
workers fresh (the first log on each loads the kernels), and once with the worker
settings README recommends for replay (``REPLAY_WORKERS``: the preload loads the kernels
while the workers start), twice on the same workers (a standing cluster's second run).
It prints logs/s, the speed-up against one core (target >= 1.8x on 2 cores), the peak
RSS of each worker (local: sampled every 20 ms with psutil; Dask: the workers' own
``ru_maxrss``) beside the size of the largest log, and whether the five summaries are
identical (they must be). On a shared machine the times are noisy: run it when nothing
else is.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import resource
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from hil.sitl import shared_folder  # noqa: E402

DATA = shared_folder("data", "ATTITUDE_BRIDGE_DATA")
CUT_S = 15.0  # length of a cut of a long recording [s]
#: What README's `dask worker` line sets: Dask's defaults cost these tasks about a fifth
#: of their CPU (the worker's sampling profiler; the nanny's MALLOC_TRIM_THRESHOLD_ of
#: 64 kB, which hands every log's arrays back to the OS and maps them again for the next;
#: the event loop's health tick, 50 times a second, each one taking the interpreter lock
#: from the thread that runs the log); the preload loads the kernels while the worker
#: starts (replay.dask_preload)
REPLAY_WORKERS = {"distributed.worker.profile.enabled": False,
                  "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": str(16 << 20),
                  "distributed.admin.tick.interval": "1s",
                  "distributed.worker.preload": ["replay.dask_preload"]}


# --- making the corpus ----------------------------------------------------------------


def cut_npz(src: Path, out_dir: Path, limit: int) -> list[Path]:
    """Windows of CUT_S of a BROAD trial where it moves at least a third of the time."""
    d = np.load(src)
    rate = float(d["rate"])
    n = int(CUT_S * rate)
    out = []
    for k, start in enumerate(range(0, d["gyr"].shape[0] - n, n)):
        sl = slice(start, start + n)
        if d["movement"][sl].mean() < 0.33 or len(out) >= limit:
            continue
        path = out_dir / f"{src.stem}_{k:02d}.npz"
        np.savez(path, rate=d["rate"], gyr=d["gyr"][sl], acc=d["acc"][sl], mag=d["mag"][sl],
                 quat_ref=d["quat_ref"][sl], movement=d["movement"][sl])
        out.append(path)
    return out


def tlog_records(data: bytes) -> list[tuple[int, int, int]]:
    """(start, end, arrival µs) of each record: 8-byte big-endian stamp + MAVLink frame."""
    out, i = [], 0
    while i + 10 < len(data):
        stx, length = data[i + 8], data[i + 9]
        if stx == 0xFD:
            size = 12 + length + (13 if data[i + 10] & 0x01 else 0)
        elif stx == 0xFE:
            size = 8 + length
        else:  # not a record boundary: stop (the tlogs here are clean)
            break
        out.append((i, i + 8 + size, int.from_bytes(data[i:i + 8], "big")))
        i += 8 + size
    return out


def cut_tlog(src: Path, out_dir: Path) -> list[Path]:
    """Consecutive CUT_S windows of a tlog (by arrival time), each a tlog of its own."""
    data = src.read_bytes()
    recs = tlog_records(data)
    t0, t1 = recs[0][2], recs[-1][2]
    out = []
    for k, start in enumerate(range(t0, t1 - int(CUT_S * 1e6), int(CUT_S * 1e6))):
        chunk = b"".join(data[a:b] for a, b, t in recs if start <= t < start + CUT_S * 1e6)
        path = out_dir / f"{src.stem}_{k:02d}.tlog"
        path.write_bytes(chunk)
        out.append(path)
    return out


def record_emulator(path: Path, profile: str, duration_s: float, seed: int) -> Path:
    """The HIL emulator streaming MAVLink over loopback UDP, recorded as a tlog by the
    bridge's own recorder (what `run --record` writes)."""
    from bridge.publish.record import TlogRecorder
    from hil import EmulatorConfig
    from hil.link import Emulator

    class Sink(asyncio.DatagramProtocol):
        def __init__(self, rec: TlogRecorder) -> None:
            self.rec = rec

        def datagram_received(self, data: bytes, addr: tuple) -> None:
            self.rec.record(data, incoming=True)

    async def go() -> None:
        rec = TlogRecorder(path)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
        sock.bind(("127.0.0.1", 0))
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(lambda: Sink(rec), sock=sock)
        cfg = EmulatorConfig(profile=profile, rate_hz=250.0, duration_s=duration_s,
                             fast=True, seed=seed)
        await Emulator(cfg).run([("127.0.0.1", sock.getsockname()[1])])
        await asyncio.sleep(0.2)
        transport.close()
        rec.close()

    asyncio.run(go())
    return path


def emulator_csv(path: Path, profile: str, duration_s: float, seed: int) -> Path:
    """An emulator run (no sockets) in the documented CSV format, with its truth."""
    from replay.emulator import simulate
    from replay.readers import csv as csv_format

    rec = simulate(profile, rate_hz=250.0, duration_s=duration_s, seed=seed)
    csv_format.write(path, rec.t, rec.gyr, rec.acc, rec.mag, rec.reference.q)
    return path


def make_corpus(root: Path, n_logs: int) -> list[Path]:
    """About ``n_logs`` logs in sub-folders of ``root`` (see module docstring)."""
    folders = {name: root / name for name in ("broad", "sitl", "ulog", "emulator_tlog",
                                              "emulator_csv", "broken")}
    for f in folders.values():
        f.mkdir(parents=True, exist_ok=True)
    logs: list[Path] = []
    for src in sorted((REPO / "tests" / "data" / "sitl").glob("*.tlog")) + sorted(
            (DATA / "px4_sih").glob("*.tlog")):
        logs += cut_tlog(src, folders["sitl"])
    for src in sorted((DATA / "logs").glob("*")):
        if src.suffix in (".ulg", ".tlog"):
            shutil.copy(src, folders["ulog"] / src.name)
            logs.append(folders["ulog"] / src.name)
    (folders["broken"] / "corrupt.tlog").write_bytes(np.random.default_rng(0).bytes(8000))
    ulog = DATA / "logs" / "pyulog_sample_px4_events.ulg"
    (folders["broken"] / "truncated.ulg").write_bytes(ulog.read_bytes()[:30000])
    logs += sorted(folders["broken"].iterdir())
    profiles = ("flight", "gentle", "tilt", "handheld_flight", "aggressive")
    n_emulated = max(0, (n_logs - len(logs)) * 2 // 5)
    for k in range(n_emulated // 2):
        logs.append(record_emulator(folders["emulator_tlog"] / f"emu_{k:03d}.tlog",
                                    profiles[k % len(profiles)], 8.0 + 2.0 * (k % 8), seed=k))
    for k in range(n_emulated - n_emulated // 2):
        logs.append(emulator_csv(folders["emulator_csv"] / f"emu_{k:03d}.csv",
                                 profiles[k % len(profiles)], 6.0 + 2.0 * (k % 8), seed=100 + k))
    per_trial = -(-(n_logs - len(logs)) // 9)
    for src in sorted((DATA / "broad").glob("*.npz")):
        logs += cut_npz(src, folders["broad"], max(0, min(per_trial, n_logs - len(logs))))
    k = n_emulated - n_emulated // 2
    while len(logs) < n_logs:  # BROAD had fewer moving windows than asked: more emulator
        logs.append(emulator_csv(folders["emulator_csv"] / f"emu_{k:03d}.csv",
                                 profiles[k % len(profiles)], 6.0 + 2.0 * (k % 8), seed=100 + k))
        k += 1
    return logs


# --- running it -----------------------------------------------------------------------


class PeakRss:
    """Samples the RSS of a process and its descendants every 20 ms; the peak per pid.
    The descendants are listed again every LIST_EVERY_S: walking /proc for them every
    20 ms took 4 % of a core, which two busy workers on two cores would lose."""

    LIST_EVERY_S = 0.25

    def __init__(self, root_pid: int) -> None:
        import psutil

        self.psutil, self.root = psutil, root_pid
        self.peak: dict[int, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _procs(self) -> list:
        ps = self.psutil
        try:
            root = ps.Process(self.root)
            return [root, *root.children(recursive=True)]
        except ps.Error:
            return []

    def _run(self) -> None:
        procs: list = []
        listed = -math.inf
        while not self._stop.is_set():
            if time.monotonic() - listed > self.LIST_EVERY_S:  # listing them costs most
                procs, listed = self._procs(), time.monotonic()
            for p in procs:
                try:
                    rss = p.memory_info().rss
                except self.psutil.Error:
                    continue
                self.peak[p.pid] = max(self.peak.get(p.pid, 0), rss)
            time.sleep(0.02)

    def stop(self) -> dict[int, int]:
        self._stop.set()
        self._thread.join()
        return self.peak


def replay(folder: Path, extra: list[str], out_json: Path) -> tuple[float, dict[int, int], int]:
    """Wall time, sampled peak RSS per process (the CLI first) and the CLI's exit code."""
    cmd = [sys.executable, "-m", "bridge.app.cli", "replay", str(folder), "-q",
           "--json", str(out_json), *extra]
    began = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    sampler = PeakRss(proc.pid)
    _, err = proc.communicate()
    seconds = time.perf_counter() - began
    peaks = sampler.stop()
    if proc.returncode != 0:
        print(err, file=sys.stderr)
    return seconds, {proc.pid: peaks.pop(proc.pid, 0), **peaks}, proc.returncode


@contextmanager
def standing_cluster(config: dict) -> Iterator[str]:
    """The address of a two-worker LocalCluster with this Dask configuration, running in
    a process of its own (benchmarks/standing_cluster.py) until the block ends."""
    proc = subprocess.Popen([sys.executable, str(REPO / "benchmarks" / "standing_cluster.py"),
                             json.dumps(config)], cwd=REPO, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        address = proc.stdout.readline().strip()
        if not address:
            raise SystemExit("benchmarks/standing_cluster.py did not start a cluster")
        yield address
    finally:
        proc.stdin.close()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def max_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: kB


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=int, default=200, help="corpus size (default 200)")
    ap.add_argument("--json", type=Path, help="save the numbers here")
    ap.add_argument("--keep", type=Path, help="make the corpus in this folder and keep it")
    args = ap.parse_args()
    os.environ.setdefault("MAVLINK20", "1")
    root = args.keep or Path(tempfile.mkdtemp(prefix="corpus_bench_"))
    began = time.perf_counter()
    logs = make_corpus(root, args.logs)
    sizes = sorted(((p.stat().st_size, p) for p in logs), reverse=True)
    print(f"corpus: {len(logs)} logs, {sum(s for s, _ in sizes) / 1e6:.0f} MB in {root} "
          f"(made in {time.perf_counter() - began:.0f} s); largest {sizes[0][1].name} "
          f"{sizes[0][0] / 1e6:.1f} MB", flush=True)
    results: dict[str, dict] = {}
    mb = 1 / 2**20

    def report(name: str, seconds: float, workers: list[int], client: int, code: int) -> None:
        results[name] = {"seconds": seconds, "logs_per_s": len(logs) / seconds,
                         "exit_code": code, "peak_rss_mb_per_worker": [w * mb for w in workers],
                         "peak_rss_mb_client": client * mb}
        print(f"{name:<28} {seconds:6.1f} s  {len(logs) / seconds:6.2f} logs/s  peak RSS "
              f"per worker {', '.join(f'{w * mb:.0f}' for w in workers)} MB"
              + (f" (client {client * mb:.0f} MB)" if client else ""), flush=True)

    out = root.parent / f"{root.name}_summaries"
    out.mkdir(exist_ok=True)
    # numba's on-disk kernel cache is per source file and goes stale when an estimator
    # changes: compile every input kind once here, untimed (not what is measured)
    warm = [next(f.iterdir()) for f in sorted(root.iterdir()) if f.name != "broken"]
    began = time.perf_counter()
    subprocess.run([sys.executable, "-m", "bridge.app.cli", "replay", *map(str, warm), "-q",
                    "--jobs", "1"], cwd=REPO, stdout=subprocess.DEVNULL, check=False)
    print(f"warm-up (kernels compiled or loaded from numba's cache): "
          f"{time.perf_counter() - began:.1f} s", flush=True)
    seconds, peaks, code = replay(root, ["--jobs", "1"], out / "jobs1.json")
    report("one core (--jobs 1)", seconds, [next(iter(peaks.values()))], 0, code)
    seconds, peaks, code = replay(root, ["--jobs", "2"], out / "jobs2.json")
    cli_pid, *workers = peaks
    report("2 local workers (--jobs 2)", seconds, [peaks[p] for p in workers], peaks[cli_pid],
           code)
    from distributed import Client

    runs = (("Dask LocalCluster, 2 workers", "dask.json", {}, 1),
            ("Dask, workers set as README", "dask_tuned.json", REPLAY_WORKERS, 2))
    for name, json_name, config, repeats in runs:
        with standing_cluster(config) as address:
            for k in range(repeats):  # again: the same workers, as a standing cluster's
                label, summary = ((name, json_name) if k == 0 else
                                  (f"{name}, again", json_name.replace(".json", "_again.json")))
                seconds, peaks, code = replay(root, ["--scheduler", address], out / summary)
                with Client(address) as client:  # the workers' own peak, since they started
                    exact = client.run(max_rss_bytes)
                report(label, seconds, list(exact.values()), next(iter(peaks.values())), code)
    base = results["one core (--jobs 1)"]["seconds"]
    for name in list(results)[1:]:
        results[name]["speedup"] = base / results[name]["seconds"]
        print(f"speed-up {name}: {results[name]['speedup']:.2f}x (target >= 1.8x on 2 cores)")
    docs = [json.loads((out / f).read_text())
            for f in ("jobs1.json", "jobs2.json", "dask.json", "dask_tuned.json",
                      "dask_tuned_again.json")]
    same = all(doc == docs[0] for doc in docs)
    d = docs[0]
    print(f"summaries identical: {'yes' if same else 'NO'}; {d['scored']} scored, "
          f"{d['not_scored']} not scored, {d['failed']} failed")
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} "
          f"(shared machine: noisy)")
    if args.json:
        args.json.write_text(json.dumps({
            "logs": len(logs), "corpus_mb": sum(s for s, _ in sizes) / 1e6,
            "largest_log_mb": sizes[0][0] / 1e6, "runs": results,
            "summaries_identical": same, "scored": d["scored"], "failed": d["failed"],
            "not_scored": d["not_scored"], "cores": os.cpu_count()}, indent=1))
        print(f"json: {args.json}")
    if args.keep is None:
        shutil.rmtree(root, ignore_errors=True)
    shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
