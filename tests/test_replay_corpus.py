"""Corpus replay and cross-validated tuning (issue 21, parts 2 and 3), end to end.

Real files in a temporary folder: synthetic CSV recordings with truth (and one without),
a real PX4 ULog from the development data (a quadrotor with flight phases), a corrupt
.tlog (random bytes) and a truncated .ulg. They go through the real command line
(``bridge.app.cli.main``) on one core, on two local processes and on a real two-process
``dask.distributed.LocalCluster``; the summaries must be identical, the broken logs
reported with the single-file replay's reason, the others scored.

The tests that fork worker processes or start the cluster share one xdist worker (group
"dask") and run in file order there: the forking ones first, before the cluster's
threads exist in the process.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import time
from pathlib import Path

import numpy as np
import pytest
from cli_support import run_cli as cli

from replay import cluster
from replay.crossval import check_groups, cross_validate
from replay.dataset import ReplayInputError
from replay.logpaths import expand, is_corpus
from replay.parallel import run
from replay.progress import Progress
from replay.readers import csv as csv_format
from replay.synthetic import SyntheticConfig, generate
from replay.tune import ParamAxis, Sweep

ESTIMATORS = ["-e", "mahony", "-e", "eskf"]
PX4_LOG = "pyulog_sample_px4_events.ulg"


def write_csv(path: Path, cfg: SyntheticConfig, truth: bool = True) -> Path:
    rec = generate(cfg)
    path.parent.mkdir(parents=True, exist_ok=True)
    csv_format.write(path, rec.t, rec.gyr, rec.acc, rec.mag,
                     rec.reference.q if truth else None)
    return path


@pytest.fixture(scope="module")
def corpus(tmp_path_factory, data_dir) -> Path:
    root = tmp_path_factory.mktemp("corpus")
    write_csv(root / "bench" / "a.csv", SyntheticConfig(duration_s=4.0, rate_hz=100.0, seed=1))
    write_csv(root / "bench" / "b.csv", SyntheticConfig(duration_s=4.0, rate_hz=100.0, seed=2,
                                                        linear_acc=3.0))
    write_csv(root / "bench" / "no_truth.csv",
              SyntheticConfig(duration_s=2.0, rate_hz=100.0, seed=3), truth=False)
    (root / "px4").mkdir()
    shutil.copy(data_dir / "logs" / PX4_LOG, root / "px4" / "events.ulg")
    (root / "bad").mkdir()
    (root / "bad" / "corrupt.tlog").write_bytes(np.random.default_rng(0).bytes(4000))
    (root / "bad" / "truncated.ulg").write_bytes(
        (data_dir / "logs" / PX4_LOG).read_bytes()[:20000])
    (root / "bench" / "notes.txt").write_text("not a log: the folder scan skips it\n")
    return root


@pytest.fixture(scope="module")
def one_core(corpus, tmp_path_factory) -> tuple[dict, str, Path]:
    """The reference run: --jobs 1, with every output (JSON doc, stdout, folder)."""
    out = tmp_path_factory.mktemp("one_core")
    code, stdout, _ = cli(["replay", str(corpus), *ESTIMATORS, "--jobs", "1", "-q",
                           "--json", str(out / "s.json"), "--csv", str(out / "s.csv"),
                           "--report", str(out / "s.html")])
    assert code == 0
    return json.loads((out / "s.json").read_text()), stdout, out


def entry(doc: dict, name: str) -> dict:
    return next(e for e in doc["per_log"] if e["file"].endswith(name))


# --- paths ---------------------------------------------------------------------------


def test_paths_folders_patterns_duplicates(corpus):
    logs = expand([corpus])
    names = [p.relative_to(corpus).as_posix() for p in logs]
    assert names == ["bad/corrupt.tlog", "bad/truncated.ulg", "bench/a.csv", "bench/b.csv",
                     "bench/no_truth.csv", "px4/events.ulg"]  # sorted, notes.txt skipped
    again = expand([corpus / "bench" / "b.csv", str(corpus / "bench" / "*.csv"),
                    corpus / "bench" / "a.csv"])
    assert [p.name for p in again] == ["a.csv", "b.csv", "no_truth.csv"]  # each once
    with pytest.raises(ReplayInputError, match="no file matches"):
        expand([str(corpus / "*.nothing")])
    (corpus.parent / "empty").mkdir(exist_ok=True)
    with pytest.raises(ReplayInputError, match="no logs in this folder"):
        expand([corpus.parent / "empty"])
    assert not is_corpus([corpus / "bench" / "a.csv"]) and not is_corpus(["missing.ulg"])
    assert is_corpus([corpus]) and is_corpus([str(corpus / "*" / "*.csv")])
    assert is_corpus([corpus / "bench" / "a.csv", corpus / "bench" / "b.csv"])


# --- the corpus summary on one core ---------------------------------------------------


def test_corpus_reports_broken_logs_with_the_single_file_reason(one_core, corpus):
    doc, stdout, _ = one_core
    assert (doc["logs"], doc["scored"], doc["not_scored"], doc["failed"]) == (6, 3, 1, 2)
    for name in ("corrupt.tlog", "truncated.ulg"):
        e = entry(doc, name)
        code, _, err = cli(["replay", e["file"]])  # the same log alone
        assert code == 2 and e["status"] == "failed"
        assert err.strip() == f"attitude-bridge replay: error: {e['reason']}"
        assert e["reason"] in stdout
    assert "no IMU samples found" in entry(doc, "corrupt.tlog")["reason"]
    no_truth = entry(doc, "no_truth.csv")
    assert no_truth["status"] == "not scored" and "no reference" in no_truth["reason"]
    assert stdout.startswith("corpus: 6 logs: 3 scored, 1 not scored, 2 failed")


def test_corpus_scores_are_the_single_file_replays(one_core, tmp_path):
    doc, _, _ = one_core
    a = entry(doc, "a.csv")
    out = tmp_path / "a.json"
    assert cli(["replay", a["file"], *ESTIMATORS, "--json", str(out)])[0] == 0
    single = json.loads(out.read_text())["estimators"]
    for label in ("mahony", "eskf"):
        for key in ("total_deg", "heading_deg", "inclination_deg", "phases"):
            assert a["estimators"][label][key] == single[label][key]
    assert "run_s" not in a["estimators"]["mahony"]  # wall time: not part of the summary


def test_aggregates_per_estimator_vehicle_and_phase(one_core):
    doc, stdout, _ = one_core
    scored = [e for e in doc["per_log"] if e["status"] == "scored"]  # ordered by path
    totals = [e["estimators"]["mahony"]["total_deg"] for e in scored]
    agg = doc["by_estimator"]["mahony"]["score"]
    assert agg["logs"] == 3 and agg["mean_deg"] == float(np.mean(totals))
    assert agg["median_deg"] == float(np.median(totals)) and agg["worst_deg"] == max(totals)
    assert agg["worst_file"] == scored[int(np.argmax(totals))]["file"]
    assert set(doc["by_vehicle"]) == {"quadrotor", "unknown"}
    assert doc["by_vehicle"]["quadrotor"]["logs"] == 1
    assert doc["by_vehicle"]["unknown"]["estimators"]["eskf"]["logs"] == 2
    px4 = entry(doc, "events.ulg")["estimators"]["eskf"]["phases"]
    assert {"takeoff", "flight"} <= set(px4) <= set(doc["by_phase"])
    assert doc["by_phase"]["flight"]["estimators"]["eskf"]["mean_deg"] == px4["flight"]["total_deg"]
    ranks = [np.mean([e["estimators"][k]["total_deg"] for k in ("mahony", "eskf")])
             for e in scored]
    assert doc["worst_first"][:3] == [scored[i]["file"] for i in np.argsort(ranks)[::-1]]
    assert "by vehicle type" in stdout and "by flight phase" in stdout


def test_corpus_csv_and_report(one_core):
    doc, _, out = one_core
    rows = (out / "s.csv").read_text().splitlines()
    assert rows[0].startswith("file,status,reason,format,vehicle")
    assert len(rows) == 1 + 6 and rows[1].split(",")[0] == doc["worst_first"][0]
    page = (out / "s.html").read_text()
    assert "attitude-bridge corpus replay" in page and "Bokeh" in page
    assert "corrupt.tlog" in page and "By flight phase" in page


def test_one_file_is_the_single_file_replay(corpus):
    path = corpus / "bench" / "a.csv"
    code, stdout, _ = cli(["replay", str(path), "-e", "mahony"])
    assert code == 0 and stdout.startswith(f"{path}: csv, IMU") and "corpus:" not in stdout


def test_nothing_scored_exits_2(corpus):
    code, stdout, err = cli(["replay", str(corpus / "bad"), "-q", "-e", "mahony", "--jobs", "1"])
    assert code == 2 and "2 failed" in stdout
    assert err.strip().splitlines()[-1] == ("attitude-bridge replay: error: no log was scored "
                                            "(2 failed, 0 not scored)")


def test_single_file_options_are_refused_for_a_corpus(corpus, tmp_path):
    code, _, err = cli(["replay", str(corpus), "--png", str(tmp_path)])
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--png" in err


def test_progress_bar_counts_failures():
    import io

    out = io.StringIO()
    bar = Progress(3, stream=out, count_failed=True)
    bar.advance()
    bar.advance(failed=True)
    bar.advance()
    assert " 3/3 done, 1 failed, " in out.getvalue() and out.getvalue().endswith("\n")


# --- scheduler errors (no cluster needed) ---------------------------------------------


def test_bad_scheduler_addresses_are_one_line_errors(corpus, monkeypatch):
    for bad in ("foo", "http://127.0.0.1:8786", "tcp://127.0.0.1"):
        code, _, err = cli(["replay", str(corpus), "--scheduler", bad])
        assert code == 2 and err.count("\n") == 1 and "expected a Dask scheduler" in err
    with socket.socket() as s:  # a port where nothing listens
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT_S", 1.0)
    began = time.perf_counter()
    code, _, err = cli(["replay", str(corpus), "--scheduler", f"tcp://127.0.0.1:{port}"])
    assert code == 2 and err.count("\n") == 1 and "cannot connect within 1 s" in err
    assert time.perf_counter() - began < 5.0
    with socket.socket() as silent:  # accepts and never answers (it used to hang)
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        began = time.perf_counter()
        code, _, err = cli(["replay", str(corpus), "--scheduler",
                            f"tcp://127.0.0.1:{silent.getsockname()[1]}"])
    assert code == 2 and err.count("\n") == 1, err
    assert "no Dask scheduler answered within 2 s" in err
    assert time.perf_counter() - began < 5.0
    monkeypatch.setattr(cluster.importlib.util, "find_spec", lambda name: None)
    code, _, err = cli(["tune", str(corpus), "-e", "mahony", "-p", "kp=1",
                        "--scheduler", "tcp://127.0.0.1:8786"])
    assert code == 2 and "pip install 'attitude-bridge[cluster]'" in err


# --- cross-validation ------------------------------------------------------------------


def test_cross_validation_arithmetic_on_a_hand_made_sweep():
    """Three logs, three points. In-sample (all logs) the middle point wins; without
    log c, point 0 wins, and it is much worse on c: the held-out choice differs."""
    total = np.array([[1.0, 1.0, 9.0],  # point 0: good on a, b; bad on c
                      [2.0, 2.0, 2.0],  # point 1: mean 2.0, the in-sample best
                      [5.0, 5.0, 1.0]])
    sw = Sweep("mahony", (ParamAxis("kp", np.array([0.1, 1.0, 10.0])),), {"ki": 0.0},
               ("x/a.csv", "x/b.csv", "y/c.csv"), ({"kp": 0.1}, {"kp": 1.0}, {"kp": 10.0}),
               total, total * 0, total * 0.5, 0.0)
    cv = cross_validate(sw)
    assert cv.best == {"ki": 0.0, "kp": 1.0}
    assert [h.chosen for h in cv.logs] == [{"kp": 1.0}, {"kp": 1.0}, {"kp": 0.1}]
    # a held out: b, c -> means (5, 2, 3) -> point 1; c held out: a, b -> point 0
    assert [h.cross_validated_deg for h in cv.logs] == [2.0, 2.0, 9.0]
    assert [h.in_sample_deg for h in cv.logs] == [2.0, 2.0, 2.0]
    assert cv.cross_validated_mean_deg == pytest.approx(13 / 3) and cv.worst.file == "y/c.csv"
    by_folder = cross_validate(sw, "folder")  # x out: c alone -> point 2; y out: point 0
    assert [h.cross_validated_deg for h in by_folder.logs] == [5.0, 5.0, 9.0]
    assert "cross-validated mean 4.333 deg, worst 9.000 (y/c.csv)" in "\n".join(cv.lines())


@pytest.fixture(scope="module")
def tune_logs(tmp_path_factory) -> Path:
    """Two logs shaken hard (linear acceleration: a small kp is best) and one with a
    large gyro bias and a quiet accelerometer (a large kp is best), in two folders."""
    root = tmp_path_factory.mktemp("tune")
    for name, cfg in (("shaken/s1.csv", SyntheticConfig(duration_s=12.0, rate_hz=100.0, seed=1,
                                                         linear_acc=6.0, gyro_bias=(0, 0, 0))),
                      ("shaken/s2.csv", SyntheticConfig(duration_s=12.0, rate_hz=100.0, seed=2,
                                                         linear_acc=6.0, gyro_bias=(0, 0, 0))),
                      ("biased/g.csv", SyntheticConfig(duration_s=12.0, rate_hz=100.0, seed=3,
                                                        gyro_bias=(0.2, -0.2, 0.1),
                                                        acc_noise=0.05))):
        write_csv(root / name, cfg)
    return root


TUNE = ["-e", "mahony", "-p", "kp=0.05:3:8", "--set", "ki=0", "-q"]


def hand_cross_validation(doc: dict) -> list[tuple[dict, float, float]]:
    """(chosen point, held-out score, in-sample score) per log, from the sweep's JSON."""
    matrix = np.array([p["total_deg"] for p in doc["points"]])  # (points, logs)
    params = [p["params"] for p in doc["points"]]
    best = min(range(len(params)), key=lambda i: sum(matrix[i]) / matrix.shape[1])
    out = []
    for f in range(matrix.shape[1]):
        others = [k for k in range(matrix.shape[1]) if k != f]
        p = min(range(len(params)), key=lambda i: sum(matrix[i, others]) / len(others))
        out.append((params[p], matrix[p, f], matrix[best, f]))
    return out


def test_tune_cross_validate_matches_a_hand_computation(tune_logs, tmp_path):
    out = tmp_path / "sweep.json"
    code, stdout, _ = cli(["tune", str(tune_logs), *TUNE, "--jobs", "1", "--cross-validate",
                           "--out", str(out)])
    assert code == 0
    doc = json.loads(out.read_text())
    cv = doc["cross_validation"]
    assert [h["file"] for h in cv["logs"]] == doc["files"]
    for h, (chosen, held_out, in_sample) in zip(cv["logs"], hand_cross_validation(doc),
                                                strict=True):
        assert h["chosen"] == chosen
        assert h["cross_validated_deg"] == pytest.approx(held_out, rel=1e-12)
        assert h["in_sample_deg"] == pytest.approx(in_sample, rel=1e-12)
    biased = next(h for h in cv["logs"] if h["file"].endswith("g.csv"))
    assert biased["chosen"]["kp"] != cv["in_sample_best"]["kp"]  # the constructed case
    assert biased["cross_validated_deg"] > biased["in_sample_deg"]
    assert cv["cross_validated_worst_file"] == biased["file"]
    assert cv["cross_validated_mean_deg"] == pytest.approx(
        np.mean([h["cross_validated_deg"] for h in cv["logs"]]), rel=1e-12)
    assert "cross-validated mean" in stdout and "unseen" not in stdout


@pytest.fixture(scope="module")
def tune_logs_with_bad(tune_logs, tmp_path_factory) -> Path:
    """The tune logs and, in a folder of their own, a corrupt log and one with no
    reference attitude."""
    root = tmp_path_factory.mktemp("tune_bad") / "logs"
    shutil.copytree(tune_logs, root)
    (root / "bad").mkdir()
    (root / "bad" / "corrupt.tlog").write_bytes(np.random.default_rng(1).bytes(4000))
    write_csv(root / "bad" / "no_truth.csv",
              SyntheticConfig(duration_s=5.0, rate_hz=100.0, seed=4), truth=False)
    return root


def test_tune_leaves_out_what_it_cannot_tune_on_and_goes_on(tune_logs, tune_logs_with_bad,
                                                            tmp_path):
    good, mixed = tmp_path / "good.json", tmp_path / "mixed.json"
    assert cli(["tune", str(tune_logs), *TUNE, "--jobs", "1", "--out", str(good)])[0] == 0
    code, stdout, err = cli(["tune", str(tune_logs_with_bad), *TUNE, "--jobs", "1",
                             "--out", str(mixed)])
    assert code == 0, err
    lines = err.splitlines()
    assert len(lines) == 2 and all(ln.startswith("attitude-bridge tune: left out ")
                                   for ln in lines), err
    assert "corrupt.tlog" in lines[0] and "no_truth.csv" in lines[1]
    assert "no reference attitude" in lines[1]
    assert "(2 left out" in stdout
    a, b = json.loads(good.read_text()), json.loads(mixed.read_text())
    # the sweep over the others is the sweep over the good logs alone
    assert [Path(f).relative_to(tune_logs_with_bad) for f in b["files"]] == [
        Path(f).relative_to(tune_logs) for f in a["files"]]
    assert b["points"] == a["points"] and b["best"] == a["best"]
    assert a["left_out"] == [] and [r.split(":")[0] for r in b["left_out"]] == [
        str(tune_logs_with_bad / "bad" / n) for n in ("corrupt.tlog", "no_truth.csv")]


def test_corpus_smooth_is_the_single_file_smooth(tune_logs_with_bad, tmp_path):
    """--smooth over several logs: the smoothed row is the single-file replay's, and a
    log without a truth is scored against it, labelled."""
    folder = tmp_path / "logs"
    folder.mkdir()
    shutil.copy(tune_logs_with_bad / "shaken" / "s1.csv", folder)
    shutil.copy(tune_logs_with_bad / "bad" / "no_truth.csv", folder)
    out = tmp_path / "corpus.json"
    code, _, err = cli(["replay", str(folder), "-e", "eskf", "--smooth", "--jobs", "1", "-q",
                        "--json", str(out)])
    assert code == 0, err
    doc = json.loads(out.read_text())
    for name in ("s1.csv", "no_truth.csv"):
        single_out = tmp_path / f"{name}.json"
        assert cli(["replay", str(folder / name), "-e", "eskf", "--smooth",
                    "--json", str(single_out)])[0] == 0
        single = json.loads(single_out.read_text())
        e = entry(doc, name)
        assert set(e["estimators"]) == {"eskf", "eskf smoothed"}
        for label in e["estimators"]:
            for key in ("total_deg", "inclination_deg"):
                assert e["estimators"][label][key] == single["estimators"][label][key]
        if name == "no_truth.csv":
            assert e["vs_smoothed"]["reference"] == "eskf smoothed (not truth)"
            assert e["vs_smoothed"]["estimators"]["eskf"]["total_deg"] == (
                single["vs_smoothed"]["estimators"]["eskf"]["total_deg"])
            assert e["vs_smoothed"]["estimators"]["eskf"]["total_deg"] > 0.0
        else:
            assert "vs_smoothed" not in e
            assert e["estimators"]["eskf smoothed"]["total_deg"] > 0.0


def test_tune_with_nothing_usable_is_one_line_and_exit_2(tune_logs_with_bad):
    code, _, err = cli(["tune", str(tune_logs_with_bad / "bad"), *TUNE, "--jobs", "1"])
    assert code == 2 and err.count("\n") == 1 and "no log to tune on" in err
    assert "corrupt.tlog" in err and "no_truth.csv" in err
    code, _, err = cli(["tune", str(tune_logs_with_bad / "bad" / "corrupt.tlog"), *TUNE])
    assert code == 2 and err.count("\n") == 1 and "no log to tune on" not in err


def test_cross_validate_needs_two_groups(tune_logs):
    code, _, err = cli(["tune", str(tune_logs / "shaken"), *TUNE, "--cross-validate",
                        "--group-by", "folder"])
    assert code == 2 and "at least two folders" in err and err.count("\n") == 1


# --- processes and the cluster (one xdist worker, in this order) ------------------------


def _double_or_die(x: int) -> int:
    if x == 3:
        os._exit(1)  # the worker process dies, as if killed by the OOM killer
    return 2 * x


@pytest.mark.xdist_group("dask")
def test_a_dead_worker_costs_only_its_task():
    done = []
    out = run(_double_or_die, [(x,) for x in range(6)], jobs=2,
              on_crash=lambda task, why: f"crashed: {why}",
              on_done=lambda i, r: done.append(i))
    assert out.results[:3] == [0, 2, 4] and out.results[4:] == [8, 10]
    assert out.results[3].startswith("crashed: worker process died")
    assert sorted(done) == list(range(6))


@pytest.mark.xdist_group("dask")
def test_two_local_processes_give_the_one_core_summary(corpus, one_core, tmp_path):
    doc, stdout, _ = one_core
    code, stdout2, _ = cli(["replay", str(corpus), *ESTIMATORS, "--jobs", "2", "-q",
                            "--json", str(tmp_path / "s.json")])
    assert code == 0 and json.loads((tmp_path / "s.json").read_text()) == doc
    assert stdout2.split("json:")[0] == stdout.split("json:")[0]


#: README's worker line: ``dask worker ... --preload replay.dask_preload``
PRELOAD = {"distributed.worker.preload": ["replay.dask_preload"]}
#: Dask's own defaults for what README's ``export`` line changes, stated so that a shell
#: that has run that line does not change the tests
DASK_DEFAULTS = {"distributed.worker.profile.enabled": True,
                 "distributed.admin.tick.interval": "20ms",
                 "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": 65536}


@pytest.fixture(scope="module")
def dask_cluster():
    distributed = pytest.importorskip("distributed")
    import dask

    with pytest.MonkeyPatch.context() as env:
        # the workers get the nanny's 64 kB, whatever this shell exports
        env.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
        with dask.config.set({**DASK_DEFAULTS, **PRELOAD}):
            cluster_ = distributed.LocalCluster(n_workers=2, threads_per_worker=1,
                                                processes=True, dashboard_address=":0")
    with cluster_:
        yield cluster_.scheduler_address


def _worker_readiness() -> dict:
    """What a worker has loaded (run on the worker by Client.run)."""
    import sys

    import estimators.smoother

    preload = sys.modules.get("replay.dask_preload")
    return {"warmed_s": preload.warmed_seconds if preload else None,
            "smoother": estimators.smoother._tapped is not None,
            "readers": {"pyulog", "pymavlink.dialects.v20.ardupilotmega"} <= set(sys.modules)}


@pytest.mark.xdist_group("dask")
def test_preloaded_workers_are_ready_before_their_first_log(dask_cluster):
    """The preload ran in every worker as it started (only dask_setup sets warmed_s):
    the readers are imported and the kernels, the smoother's too, are loaded."""
    from distributed import Client

    with Client(dask_cluster, set_as_default=False) as client:
        states = client.run(_worker_readiness)
    assert len(states) == 2
    for state in states.values():
        assert state["warmed_s"] is not None and state["warmed_s"] > 0, states
        assert state["smoother"] and state["readers"], states


@pytest.mark.xdist_group("dask")
def test_dask_scheduler_gives_the_one_core_summary(corpus, one_core, dask_cluster, tmp_path):
    doc, _, _ = one_core
    code, stdout, err = cli(["replay", str(corpus), *ESTIMATORS, "--scheduler", dask_cluster,
                             "--json", str(tmp_path / "s.json")])
    assert code == 0 and json.loads((tmp_path / "s.json").read_text()) == doc
    assert "6/6 done, 2 failed" in err  # the progress bar (not -q)
    assert "corrupt.tlog" in stdout
    # the fixture's workers keep Dask's defaults: the user is told what they cost
    assert ("note: --scheduler: 2 of 2 worker(s) run an event-loop tick every 20 ms, glibc "
            "returning memory above 64 kB, the sampling profiler" in err), err


def _readme_worker_environment() -> dict[str, str]:
    """The variables of README's ``export`` line for ``dask worker``."""
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    line = next(x for x in readme.splitlines() if x.startswith("export DASK_DISTRIBUTED__"))
    return dict(word.split("=", 1) for word in line.split()[1:])


def test_readme_worker_settings_leave_nothing_that_slows_replay(monkeypatch):
    """What ``worker_costs`` finds on a worker with Dask's defaults (the nanny's 64-kB
    trim threshold in its environment), and that README's line turns all of it off."""
    import dask

    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "65536")
    with dask.config.set(DASK_DEFAULTS):
        assert cluster.worker_costs() == ["the sampling profiler",
                                          "an event-loop tick every 20 ms",
                                          "glibc returning memory above 64 kB"]
    env = _readme_worker_environment()
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    with dask.config.set(dask.config.collect_env(env)):
        assert cluster.worker_costs() == []


def test_cluster_batches_shrink_to_single_tasks_and_cover_every_task_once():
    """Guided batches: every task once, in the order given; the first batch a sixth of
    the work on two workers, the last ones single tasks; far fewer Dask tasks than logs."""
    order = list(range(200))[::-1]
    batches = cluster.GuidedBatches(order, [1.0] * 200)
    cut = []
    while batches:
        cut.append(batches.next(workers=2))
    assert [i for batch in cut for i in batch] == order
    sizes = [len(batch) for batch in cut]
    assert sizes[0] == -(-200 // (2 * cluster.BATCH_SHARE))  # ceil: at least the share
    assert sizes == sorted(sizes, reverse=True) and sizes[-3:] == [1, 1, 1]
    assert len(cut) <= 40
    # by weight: one heavy task is a batch of its own, light ones are grouped
    weighted = cluster.GuidedBatches([0, 1, 2, 3, 4, 5], [50.0, 1, 1, 1, 1, 1])
    assert weighted.next(workers=1) == [0] and len(weighted.next(workers=1)) > 1
    # more workers (one joined): smaller batches from then on
    grown = cluster.GuidedBatches(range(120), [1.0] * 120)
    assert len(grown.next(workers=1)) == 40 and len(grown.next(workers=4)) == 7


@pytest.mark.xdist_group("dask")
def test_a_task_that_fails_on_the_cluster_costs_only_itself(dask_cluster):
    """A batch that fails is sent again one task at a time: only the failing task is
    reported (with Dask's reason), every other one is done, each announced once."""
    import math

    done: list[int] = []
    values = [float(x) for x in range(40)]
    values[7] = -1.0  # math.sqrt raises ValueError on the worker
    out = cluster.run_on_cluster(math.sqrt, [(v,) for v in values], dask_cluster,
                                 on_crash=lambda task, why: f"failed: {why}",
                                 notify=lambda i, r: done.append(i), order=range(40))
    assert out.results[7] == "failed: on the Dask cluster: ValueError: math domain error"
    assert [r for i, r in enumerate(out.results) if i != 7] == [
        math.sqrt(v) for i, v in enumerate(values) if i != 7]
    assert sorted(done) == list(range(40)) and not out.interrupted


@pytest.mark.xdist_group("dask")
def test_dask_tune_cross_validated_equals_local(tune_logs_with_bad, dask_cluster, tmp_path):
    docs = []
    for where in (["--jobs", "1"], ["--scheduler", dask_cluster]):
        out = tmp_path / f"{where[0]}.json"
        assert cli(["tune", str(tune_logs_with_bad), *TUNE, *where, "--cross-validate",
                    "--out", str(out)])[0] == 0
        doc = json.loads(out.read_text())
        doc.pop("seconds")
        docs.append(doc)
    assert docs[0] == docs[1] and docs[0]["cross_validation"]["logs"]
    assert len(docs[0]["left_out"]) == 2  # the unusable logs, left out alike


def test_copies_of_one_log_are_held_out_together(tmp_path, corpus):
    """A log copied under another name left its twin among the others when held out, so
    the cross-validated score was the in-sample one (a new-user sweep)."""
    a, b = corpus / "bench" / "a.csv", corpus / "bench" / "b.csv"
    copy = tmp_path / "other" / "copy_of_a.csv"
    copy.parent.mkdir()
    shutil.copy(a, copy)
    files = [str(a), str(b), str(copy)]
    groups = check_groups(files, "log")
    assert groups[0] == groups[2] != groups[1]
    with pytest.raises(ValueError, match="at least two folders"):  # other/ joins bench/
        check_groups(files, "folder")
    code, _, err = cli(["tune", *files, "-e", "mahony", "-p", "kp=0.1,1", "--cross-validate",
                        "-q"])
    assert code == 0
    assert f"{a}, {copy} have the same content: held out together" in err
