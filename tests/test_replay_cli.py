"""`attitude-bridge replay` / `tune` end to end, and clear errors for bad input."""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import pytest

from bridge.app.cli import main
from replay import ReplayInputError, load
from replay.readers import csv as csv_format
from replay.synthetic import SyntheticConfig, generate

os.environ["MAVLINK20"] = "1"


def test_replay_json_per_spec(data_dir, tmp_path, capsys):
    out = tmp_path / "r.json"
    path = data_dir / "logs" / "pyulog_sample_logging_tagged_and_default_params.ulg"
    code = main(["replay", str(path), "--estimator", "mahony:kp=0.5,ki=0.01",
                 "--estimator", "quaternion", "--json", str(out)])
    assert code == 0
    doc = json.loads(out.read_text())
    assert doc["file"] == str(path) and doc["reference"] == "truth"
    # beside the estimators, the autopilot's own attitude against the truth
    assert set(doc["estimators"]) == {"mahony:kp=0.5,ki=0.01", "quaternion", "autopilot"}
    for scores in doc["estimators"].values():
        for key in ("total_deg", "heading_deg", "inclination_deg", "lag_s"):
            assert key in scores
        assert scores["total_deg"] >= scores["inclination_deg"] > 0
    assert "mahony:kp=0.5,ki=0.01" in capsys.readouterr().out


def test_tune_cli_writes_sweep(tmp_path, capsys):
    rec = generate(SyntheticConfig(duration_s=10.0, seed=5))
    path = tmp_path / "s.csv"
    csv_format.write(path, rec.t, rec.gyr, rec.acc, rec.mag, rec.reference.q)
    out = tmp_path / "sweep.csv"
    code = main(["tune", str(path), "--estimator", "mahony", "--param", "kp=0.05:5:4",
                 "--set", "ki=0", "--jobs", "1", "--out", str(out), "-q"])
    assert code == 0
    lines = out.read_text().splitlines()
    assert lines[0].startswith("kp,mean_total_deg") and len(lines) == 5
    totals = [float(line.split(",")[1]) for line in lines[1:]]
    best_kp = float(lines[1 + int(np.argmin(totals))].split(",")[0])
    assert f"best mahony: ki=0, kp={best_kp:.6g}" in capsys.readouterr().out


def test_tune_takes_fixed_parameters_in_e_as_replay_does(tmp_path, capsys):
    """`-e mahony:ki=0` fixes ki like `--set ki=0` (it used to fail: "got '0:'"); a
    parameter both swept and fixed is one line, not an internal error."""
    rec = generate(SyntheticConfig(duration_s=4.0, seed=5))
    path = tmp_path / "s.csv"
    csv_format.write(path, rec.t, rec.gyr, rec.acc, rec.mag, rec.reference.q)
    grid = ["--param", "kp=0.05:5:3", "--jobs", "1", "-q"]
    assert main(["tune", str(path), "-e", "mahony", "--set", "ki=0", *grid]) == 0
    with_set = capsys.readouterr().out.splitlines()[1]
    assert main(["tune", str(path), "-e", "mahony:ki=0", *grid]) == 0
    assert capsys.readouterr().out.splitlines()[1] == with_set
    for argv, expected in ((["-e", "mahony", "--set", "kp=1"], "kp: both swept (-p) and fixed"),
                           (["-e", "mahony:kp=1"], "kp: both swept (-p) and fixed"),
                           (["-e", "mahony:ki=0", "--set", "ki=0.1"], "ki: given in -e and in"),
                           (["-e", "mahony", "--param", "ki=0:1:100000000"],
                            "100,000,000 values (at most 1,000,000"),
                           (["-e", "mahony", "--param", "ki=0:1:1000000"],
                            "a grid of 3,000,000 points")):
        assert main(["tune", str(path), *argv, *grid]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and expected in err, err


def test_tune_leaves_out_a_log_no_estimator_runs_on(tmp_path, capsys):
    """A log whose gyro is NaN throughout loads, but no grid point scores on it: it used
    to fail the whole corpus ("no grid point produced a finite score", no log named)."""
    rec = generate(SyntheticConfig(duration_s=4.0, seed=5))
    csv_format.write(tmp_path / "good.csv", rec.t, rec.gyr, rec.acc, rec.mag, rec.reference.q)
    n = len(rec.t)
    np.savez(tmp_path / "dead.npz", rate=100.0, gyr=np.full((n, 3), np.nan),
             acc=np.tile([0.0, 0.0, 9.81], (n, 1)), quat_ref=np.tile([1.0, 0, 0, 0], (n, 1)),
             movement=np.ones(n, dtype=bool))
    grid = ["-e", "mahony", "--param", "kp=0.5,1", "--jobs", "1", "-q"]
    assert main(["tune", str(tmp_path), *grid]) == 0
    out, err = capsys.readouterr()
    assert f"left out {tmp_path / 'dead.npz'}: mahony never ran on a scored sample" in err
    assert "2 parameter sets x 1 file(s)" in out and "good.csv: total" in out
    assert main(["tune", str(tmp_path / "dead.npz"), *grid]) == 2  # nothing left: one line
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "dead.npz: mahony never ran" in err, err


def test_csv_round_trip_and_time_cleanup(tmp_path):
    rec = generate(SyntheticConfig(duration_s=1.0, seed=6))
    path = tmp_path / "x.csv"
    csv_format.write(path, rec.t, rec.gyr, rec.acc, rec.mag, rec.reference.q, world="NED")
    rows = path.read_text().splitlines()
    # duplicate row 10 and put row 20 (earlier time) after row 30
    body = rows[3:]
    body = [*body[:11], body[10], *body[11:31], body[20], *body[31:]]
    path.write_text("\n".join(rows[:3] + body) + "\n")
    back = load(path)
    assert back.n == rec.n
    assert back.cleanup.duplicates == 1 and back.cleanup.backwards == 1
    np.testing.assert_allclose(back.gyr, rec.gyr, rtol=1e-8)
    np.testing.assert_allclose(back.reference.q, rec.reference.q, rtol=1e-8, atol=1e-9)


def test_missing_file_is_a_clear_error(tmp_path, capsys):
    assert main(["replay", str(tmp_path / "nope.ulg")]) == 2
    assert "no such file" in capsys.readouterr().err


def test_unknown_format_is_a_clear_error(tmp_path, capsys):
    path = tmp_path / "data.bin"
    path.write_bytes(bytes(range(256)) * 4)
    assert main(["replay", str(path)]) == 2
    assert "unknown log format" in capsys.readouterr().err


def test_unknown_estimator_lists_valid_names(data_dir, capsys):
    path = data_dir / "logs" / "pyulog_sample_log_small.ulg"
    assert main(["replay", str(path), "-e", "kalmann"]) == 2
    err = capsys.readouterr().err
    assert "unknown estimator 'kalmann'" in err and "mahony" in err
    assert main(["replay", str(path), "-e", "mahony:gain=2"]) == 2
    assert "kp" in capsys.readouterr().err


def test_tlog_without_imu(tmp_path):
    from pymavlink.dialects.v20 import common

    mav = common.MAVLink(None, srcSystem=1, srcComponent=1)
    path = tmp_path / "heartbeats.tlog"
    with path.open("wb") as f:
        for i in range(5):
            msg = common.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3)
            f.write(int(1e6 * (1000 + i)).to_bytes(8, "big") + msg.pack(mav))
    with pytest.raises(ReplayInputError, match="no IMU samples found"):
        load(path)


def test_csv_and_npz_without_imu(tmp_path):
    csv_path = tmp_path / "att.csv"
    csv_path.write_text("t,qw,qx,qy,qz\n0,1,0,0,0\n0.1,1,0,0,0\n")
    with pytest.raises(ReplayInputError, match="no IMU samples found"):
        load(csv_path)
    npz_path = tmp_path / "x.npz"
    np.savez(npz_path, quat_ref=np.zeros((3, 4)))
    with pytest.raises(ReplayInputError, match="no IMU samples found"):
        load(npz_path)


@pytest.mark.filterwarnings("error")  # a numpy RuntimeWarning leaking out fails the test
@pytest.mark.parametrize(("key", "rows"), [("acc", 1993), ("quat_ref", 100)])
def test_npz_arrays_of_different_lengths_name_the_file(data_dir, tmp_path, capsys, key, rows):
    """A real BROAD trial whose arrays no longer have one row per sample: one line naming
    the file and both lengths, exit 2, before any arithmetic on the arrays."""
    trial = np.load(data_dir / "broad" / "10_undisturbed_slow_translation_A.npz")
    arrays = {k: trial[k][:2000] for k in ("gyr", "acc", "mag", "quat_ref", "movement")}
    arrays[key] = arrays[key][:rows]
    path = tmp_path / "cut.npz"
    np.savez(path, rate=trial["rate"], **arrays)
    assert main(["replay", str(path), "-e", "mahony"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"attitude-bridge replay: error: {path}: ")
    assert f"{key} is ({rows}," in err and "gyr has 2000" in err


def cut_copy(src, dst, size: int):
    """The first ``size`` bytes of a real log: a recording stopped mid-write."""
    dst.write_bytes(src.read_bytes()[:size])
    return dst


def test_ulog_damaged_inside_is_noted_not_silent(data_dir, tmp_path, capsys):
    """5000 random bytes in the middle of a real ULog: pyulog resynchronises and loses
    some samples, which used to go without a note (and pyulog's own notice went to
    stdout, into the replay's output)."""
    src = data_dir / "logs" / "pyulog_sample_px4_events.ulg"
    data = bytearray(src.read_bytes())
    data[200_000:205_000] = np.random.default_rng(3).bytes(5000)
    path = tmp_path / "garbled.ulg"
    path.write_bytes(bytes(data))
    rec = load(path)
    assert 0 < rec.n < load(src).n
    assert [n for n in rec.notes if n.startswith("ULog damaged inside: pyulog skipped")]
    assert main(["replay", str(path), "-e", "mahony"]) == 0
    out = capsys.readouterr().out
    assert "note: ULog damaged inside" in out and "File corruption detected" not in out


def test_ulog_cut_inside_a_message_is_noted(data_dir, tmp_path):
    src = data_dir / "logs" / "pyulog_sample_log_small.ulg"
    rec = load(cut_copy(src, tmp_path / "cut.ulg", 600_000))
    assert rec.n < load(src).n
    cut = [n for n in rec.notes if n.startswith("ULog ends inside a message")]
    assert len(cut) == 1, rec.notes
    ignored = int(cut[0].split("last ")[1].split(" bytes")[0])
    assert cut == [f"ULog ends inside a message: last {ignored} bytes ignored"] and ignored > 0
    # Cut where that message starts instead: a whole file, the same samples, no note.
    whole = load(cut_copy(src, tmp_path / "whole.ulg", 600_000 - ignored))
    assert whole.n == rec.n and not [n for n in whole.notes if "ends inside" in n]


def test_tlog_cut_mid_record_is_noted(tmp_path):
    src = Path(__file__).parent / "data" / "sitl" / "px4_sih_dashes.tlog"
    rec = load(cut_copy(src, tmp_path / "cut.tlog", 400_000))
    cut = [n for n in rec.notes if n.startswith("file ends mid-record")]
    assert len(cut) == 1, rec.notes
    ignored = int(cut[0].split("last ")[1].split(" bytes")[0])
    assert cut == [f"file ends mid-record: last {ignored} bytes ignored"] and ignored > 0
    assert not [n for n in rec.notes if "unreadable" in n]  # the cut is no bad record
    whole = load(cut_copy(src, tmp_path / "whole.tlog", 400_000 - ignored))
    assert whole.n == rec.n and not [n for n in whole.notes if "mid-record" in n]


def garble(path, lines: list[int]) -> None:
    """Make one cell of each of these (1-based) lines no number."""
    text = path.read_text().splitlines()
    for number in lines:
        cells = text[number - 1].split(",")
        cells[4] = "1.2.x"
        text[number - 1] = ",".join(cells)
    path.write_text("\n".join(text) + "\n")


def test_csv_rows_with_non_numeric_cells_are_dropped_and_counted(data_dir, tmp_path, capsys):
    path = tmp_path / "trial.csv"
    broad_as_csv(data_dir, path, rows=3000)
    garble(path, [17, 100, 2500])  # lines 1-3 are the settings and the header
    assert load(path).n == 2997
    assert main(["replay", str(path), "-e", "mahony"]) == 0
    assert "note: CSV: 3 rows with non-numeric cells dropped (first at line 17)" in \
        capsys.readouterr().out


def test_a_corrupt_gyro_value_is_skipped_and_noted_not_integrated(data_dir, tmp_path, capsys):
    """One gyro cell of 1e20 rad/s (a corrupt number, not a saturated sensor) used to turn
    mahony's attitude by up to 150° with exit 0 and no word."""
    clean, bad = tmp_path / "clean.csv", tmp_path / "bad.csv"
    broad_as_csv(data_dir, clean, rows=3000)
    text = clean.read_text().splitlines()
    cells = text[1500].split(",")
    cells[1] = "1e20"  # gx of a sample mid-way through the movement
    text[1500] = ",".join(cells)
    bad.write_text("\n".join(text) + "\n")
    scores = {}
    for path in (clean, bad):
        assert main(["replay", str(path), "-e", "mahony", "--json", str(path) + ".json"]) == 0
        doc = json.loads(Path(str(path) + ".json").read_text())
        scores[path.name] = doc["estimators"]["mahony"]["total_deg"]
    out = capsys.readouterr().out
    assert "note: samples skipped (gyro not finite or beyond twice its full scale, or a " \
           "bad time step): mahony 1" in out
    assert scores["bad.csv"] == pytest.approx(scores["clean.csv"], abs=0.05)


@pytest.mark.parametrize(("kind", "expected"), [
    ("rate vector", "rate must be one number"),
    ("rate text", "not a BROAD-style .npz"),
    ("object gyro", "not a BROAD-style .npz"),
    ("lone .npy", "not a .npz archive"),
])
def test_npz_with_wrong_contents_is_one_line_naming_the_file(tmp_path, capsys, kind, expected):
    """These four used to end in an internal error (a TypeError) or a message without the
    file's name."""
    path = tmp_path / "trial.npz"
    gyr, acc = np.zeros((100, 3)), np.tile([0.0, 0.0, 9.81], (100, 1))
    if kind == "lone .npy":
        with path.open("wb") as f:
            np.save(f, gyr)
    else:
        rate = {"rate vector": np.array([100.0, 200.0]), "rate text": np.array("abc")}.get(
            kind, np.array(100.0))
        g = np.array([[None] * 3] * 100, dtype=object) if kind == "object gyro" else gyr
        np.savez(path, rate=rate, gyr=g, acc=acc)
    assert main(["replay", str(path), "-e", "mahony"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"attitude-bridge replay: error: {path}: ")
    assert expected in err


@pytest.mark.parametrize("damage", ["dead accelerometer", "gyro 1e308"])
def test_damaged_samples_leak_no_numpy_warnings(data_dir, tmp_path, capsys, damage):
    """numpy's RuntimeWarnings ("All-NaN slice", "overflow encountered in multiply") used
    to reach the user's terminal; the damage is said in the replay's own words."""
    path = tmp_path / "trial.csv"
    broad_as_csv(data_dir, path, rows=600)
    text = path.read_text().splitlines()
    first = next(i for i, line in enumerate(text) if line.startswith("t,")) + 1
    for i in range(first, len(text)):
        cells = text[i].split(",")
        if damage == "dead accelerometer":
            cells[4:7] = ["0", "0", "0"]
        elif i == first + 300:
            cells[1] = "1e308"
        text[i] = ",".join(cells)
    path.write_text("\n".join(text) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert main(["replay", str(path), "-e", "eskf"]) == 0
    out = capsys.readouterr().out
    assert ("|acc| at rest is 0.00 m/s²" in out if damage == "dead accelerometer"
            else "samples skipped" in out)


@pytest.mark.parametrize(("damage", "reason"), [
    ("gyro all NaN", "the estimator skipped every sample (gyro not finite"),
    ("accelerometer all zero", "the estimator never started: no usable accelerometer sample"),
])
def test_an_estimator_that_never_starts_says_why(tmp_path, capsys, damage, reason):
    """It used to say only "never started on a scored sample", whatever the cause."""
    n = 400
    gyr, acc = np.zeros((n, 3)), np.tile([0.0, 0.0, 9.81], (n, 1))
    if damage == "gyro all NaN":
        gyr[:] = np.nan
    else:
        acc[:] = 0.0
    path = tmp_path / "trial.npz"
    np.savez(path, rate=100.0, gyr=gyr, acc=acc, quat_ref=np.tile([1.0, 0, 0, 0], (n, 1)))
    assert main(["replay", str(path), "-e", "mahony"]) == 0
    assert f"(1) total°: {reason}" in capsys.readouterr().out


@pytest.mark.parametrize("rows", [2, 50, 150])
def test_a_log_shorter_than_the_handling_window_replays(data_dir, tmp_path, capsys, rows):
    """Under 0.5 s of samples (the phases' gyro smoothing window) used to fail with numpy's
    "operands could not be broadcast together" and no file name."""
    path = tmp_path / "short.csv"
    broad_as_csv(data_dir, path, rows=rows)
    assert main(["replay", str(path), "-e", "eskf"]) == 0
    assert "eskf " in capsys.readouterr().out


def test_csv_rows_with_a_wrong_number_of_cells_are_dropped_and_counted(data_dir, tmp_path,
                                                                       capsys):
    """A CSV cut mid-row (or with a short row inside) used to be refused whole: "malformed
    CSV (Some errors were detected ! Line #1154 ...)"."""
    path = tmp_path / "trial.csv"
    broad_as_csv(data_dir, path, rows=3000)
    text = path.read_text().splitlines()
    text[99] = ",".join(text[99].split(",")[:5])  # line 100: five cells of fifteen
    text[-1] = text[-1][:17]  # and the file cut inside its last row
    path.write_text("\n".join(text))
    rec = load(path)
    assert rec.n == 2998
    assert rec.notes == ("CSV: 2 rows with a wrong number of cells dropped (first at line "
                         "100)",)
    assert main(["replay", str(path), "-e", "mahony"]) == 0
    assert "note: CSV: 2 rows with a wrong number of cells dropped" in capsys.readouterr().out


def test_csv_written_by_excel_with_a_byte_order_mark_reads(data_dir, tmp_path):
    path = tmp_path / "trial.csv"
    broad_as_csv(data_dir, path, rows=300)
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    assert load(path).n == 300


@pytest.mark.parametrize("kind", ["ulog", "tlog", "csv"])
def test_damaged_file_with_nothing_usable_left_is_one_line(data_dir, tmp_path, capsys, kind):
    if kind == "ulog":  # cut before the first sensor_combined sample
        path = cut_copy(data_dir / "logs" / "pyulog_sample_log_small.ulg",
                        tmp_path / "cut.ulg", 60_000)
        damage = "ULog ends inside a message: last "
    elif kind == "tlog":  # cut after the first IMU sample
        path = cut_copy(Path(__file__).parent / "data" / "sitl" / "px4_sih_dashes.tlog",
                        tmp_path / "cut.tlog", 100)
        damage = "file ends mid-record: last "
    else:
        path = tmp_path / "trial.csv"
        broad_as_csv(data_dir, path, rows=20)
        garble(path, list(range(4, 24)))
        damage = "CSV: 20 rows with non-numeric cells dropped (first at line 4)"
    assert main(["replay", str(path), "-e", "mahony"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"attitude-bridge replay: error: {path}: ")
    assert damage in err


def test_corrupt_ulog_is_a_clear_error(tmp_path):
    path = tmp_path / "broken.ulg"
    path.write_bytes(b"ULog\x01\x12\x35" + b"\x00" * 40)
    with pytest.raises(ReplayInputError, match=r"broken\.ulg"):
        load(path)


def test_asking_for_missing_truth_is_an_error(data_dir, capsys):
    path = data_dir / "logs" / "pyulog_sample_log_small.ulg"  # real flight: no groundtruth
    assert main(["replay", str(path), "--reference", "truth", "-e", "mahony"]) == 2
    assert "no truth attitude in this file (references it has: autopilot)" in \
        capsys.readouterr().err


def broad_as_csv(data_dir, path, rows: int = 3000) -> None:
    """The start of a real BROAD trial in the CSV format (optical reference = truth)."""
    trial = np.load(data_dir / "broad" / "10_undisturbed_slow_translation_A.npz")
    t = np.arange(rows) / float(trial["rate"])
    csv_format.write(path, t, trial["gyr"][:rows], trial["acc"][:rows], trial["mag"][:rows],
                     trial["quat_ref"][:rows], world="ENU")


@pytest.mark.parametrize("command", ["replay", "tune"])
@pytest.mark.parametrize("suffix", [".npz", ".csv"])
def test_asking_for_a_reference_the_file_lacks_names_those_it_has(data_dir, tmp_path, capsys,
                                                                  command, suffix):
    """BROAD trials (npz, or as CSV) hold optical truth only: --reference autopilot used to
    score or tune against that truth without a word."""
    path = data_dir / "broad" / "10_undisturbed_slow_translation_A.npz"
    if suffix == ".csv":
        path = tmp_path / "trial.csv"
        broad_as_csv(data_dir, path)
    extra = ["-p", "kp=0.5,1", "-q"] if command == "tune" else []
    assert main([command, str(path), "--reference", "autopilot", "-e", "mahony", *extra]) == 2
    assert capsys.readouterr().err == (f"attitude-bridge {command}: error: {path}: no "
                                       f"autopilot attitude in this file (references it "
                                       f"has: truth)\n")


@pytest.mark.parametrize("option", ["--report", "--json", "--csv"])
def test_output_into_a_missing_folder_fails_before_the_replay(data_dir, tmp_path, capsys,
                                                              option):
    path = data_dir / "logs" / "pyulog_sample_log_small.ulg"
    target = tmp_path / "no" / "such" / "dir" / "x.out"
    assert main(["replay", str(path), "-e", "mahony", option, str(target)]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and f"{option} {target}: folder" in err[0]
    assert "does not exist" in err[0] and "Traceback" not in captured.err
    assert captured.out == ""  # refused before reading the log, not after the whole replay


def test_tune_output_into_a_missing_folder_fails_first(tmp_path, capsys):
    rec = generate(SyntheticConfig(duration_s=2.0, seed=5))
    path = tmp_path / "s.csv"
    csv_format.write(path, rec.t, rec.gyr, rec.acc, rec.mag, rec.reference.q)
    assert main(["tune", str(path), "-e", "mahony", "-p", "kp=1,2", "--out",
                 str(tmp_path / "missing" / "sweep.csv"), "-q"]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_replay_writes_csv_json_and_report(tmp_path, capsys):
    rec = generate(SyntheticConfig(duration_s=4.0, seed=7))
    path = tmp_path / "s.csv"
    csv_format.write(path, rec.t, rec.gyr, rec.acc, rec.mag, rec.reference.q)
    outs = {k: tmp_path / f"out.{k}" for k in ("csv", "json", "html")}
    code = main(["replay", str(path), "-e", "mahony", "--declination-deg", "1.5",
                 "--csv", str(outs["csv"]), "--json", str(outs["json"]),
                 "--report", str(outs["html"]), "--png", str(tmp_path / "png")])
    assert code == 0
    out = capsys.readouterr().out
    assert "declination: +1.50° (--declination-deg)" in out
    doc = json.loads(outs["json"].read_text())
    assert doc["declination_deg"] == 1.5 and doc["declination_source"] == "--declination-deg"
    scores = doc["estimators"]["mahony"]
    missing = {k for k, v in scores.items() if v is None}
    assert missing == set(scores["reasons"])  # every null says why
    assert outs["csv"].read_text().splitlines()[0].startswith("t,acc_norm,mag_norm")
    assert "Bokeh" in outs["html"].read_text(encoding="utf-8")
    assert len(list((tmp_path / "png").glob("*.png"))) == 3


def _signal_state(pid: int) -> str:
    """Each thread's blocked, ignored and caught signal masks (Linux /proc), so that a
    lost SIGINT can be told apart: inherited as ignored, blocked, or taken by a thread."""
    lines = []
    for task in sorted(Path(f"/proc/{pid}/task").glob("*/status")):
        try:
            fields = dict(line.split(":", 1) for line in task.read_text().splitlines())
        except OSError:
            continue
        lines.append(" ".join(f"{k}={fields.get(k, '?').strip()}" for k in
                              ("Name", "SigBlk", "SigIgn", "SigCgt", "SigPnd", "ShdPnd")))
    return "\n".join(lines)


def test_ctrl_c_in_tune_keeps_the_partial_sweep(tmp_path):
    """SIGINT while tune sweeps: exit 130, one line instead of a traceback, and the points
    done so far in --out. The grid is long (4000 points, about 10 s) so that the signal
    lands in the middle of it: 400 points once finished in 1.1 s, before the signal."""
    import signal
    import subprocess
    import sys
    import time

    rec = generate(SyntheticConfig(duration_s=30.0, seed=5))
    data = tmp_path / "s.csv"
    csv_format.write(data, rec.t, rec.gyr, rec.acc, rec.mag, rec.reference.q)
    out = tmp_path / "sweep.csv"
    points = 4000
    args = ["tune", str(data), "-e", "mahony", "-p", f"kp=0.05:5:{points}", "--set", "ki=0",
            "-j", "2", "--out", str(out)]
    # As typed in a terminal: a suite started in the background of a non-interactive
    # shell hands its children SIGINT ignored (SigIgn bit 1), and a program keeps an
    # ignored SIGINT ignored, so the child is given Python's own handler first.
    start = ("import runpy, signal, sys; signal.signal(signal.SIGINT, "
             "signal.default_int_handler); sys.argv = ['attitude-bridge', *sys.argv[1:]]; "
             "runpy.run_module('bridge.app.cli', run_name='__main__', alter_sys=True)")
    cmd = [sys.executable, "-c", start, *args]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=os.path.dirname(os.path.dirname(__file__)))
    deadline = time.monotonic() + 120
    progress = ""
    while time.monotonic() < deadline:  # wait until some grid points are done
        progress += os.read(proc.stderr.fileno(), 4096).decode()
        if any(f" {n}/{points} " in progress for n in range(5, points)):
            break
    assert proc.poll() is None, "the sweep ended before it could be interrupted"
    signal_state = _signal_state(proc.pid)
    proc.send_signal(signal.SIGINT)
    time.sleep(0.3)
    signal_state += "\nafter:\n" + _signal_state(proc.pid)
    stdout, stderr = proc.communicate(timeout=60)
    stderr = progress + stderr
    assert proc.returncode == 130, f"{stderr}\nsignal state before SIGINT:\n{signal_state}"
    assert "Traceback" not in stderr and "interrupted:" in stderr
    rows = out.read_text().splitlines()
    assert rows[0].startswith("kp,mean_total_deg") and 5 <= len(rows) - 1 < points
    assert "best mahony" in stdout


def _small_csv(tmp_path: Path, name: str = "s.csv", seed: int = 5) -> Path:
    rec = generate(SyntheticConfig(duration_s=2.0, seed=seed))
    path = tmp_path / name
    csv_format.write(path, rec.t, rec.gyr, rec.acc, rec.mag, rec.reference.q)
    return path


@pytest.mark.parametrize("option", ["--json", "--csv", "--report"])
def test_an_output_that_is_the_log_read_is_refused(tmp_path, capsys, option):
    """`replay log.csv --json log.csv` replaced the log with its results, exit 0."""
    log = _small_csv(tmp_path)
    before = log.read_bytes()
    assert main(["replay", str(log), "-e", "mahony", option, str(log)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is one of the logs read" in err[0] and option in err[0]
    assert log.read_bytes() == before


def test_two_outputs_to_one_file_are_refused(tmp_path, capsys):
    log = _small_csv(tmp_path)
    same = tmp_path / "same.out"
    assert main(["replay", str(log), "-e", "mahony", "--json", str(same),
                 "--csv", str(same)]) == 2
    err = capsys.readouterr().err
    assert "--csv" in err and "also given to --json" in err and not same.exists()


def test_tune_output_that_is_one_of_the_logs_is_refused(tmp_path, capsys):
    a, b = _small_csv(tmp_path, "a.csv", 5), _small_csv(tmp_path, "b.csv", 6)
    before = a.read_bytes()
    assert main(["tune", str(a), str(b), "-e", "mahony", "-p", "kp=1,2", "--out", str(a),
                 "-q"]) == 2
    assert "is one of the logs read" in capsys.readouterr().err
    assert a.read_bytes() == before


def test_a_corpus_output_inside_the_corpus_and_a_missing_log_are_refused(tmp_path, capsys):
    """In a corpus, an output that is one of its logs is refused like a single log's; a
    named log that does not exist is refused like a pattern that matches nothing (it
    used to be scored as a failed log, exit 0, while the pattern was an error)."""
    a, b = _small_csv(tmp_path, "a.csv", 5), _small_csv(tmp_path, "b.csv", 6)
    before = b.read_bytes()
    assert main(["replay", str(tmp_path), "-e", "mahony", "-q", "--json", str(b)]) == 2
    assert "is one of the logs read" in capsys.readouterr().err
    assert b.read_bytes() == before
    missing = tmp_path / "nonexistent.csv"
    assert main(["replay", str(a), str(missing), "-e", "mahony", "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"attitude-bridge replay: error: {missing}: no such file or folder"]


@pytest.mark.parametrize("args", [["-e", "mahony", "--declination-deg", "30"],
                                  ["-e", "mahony:declination_deg=30"]])
def test_a_declination_against_a_magnetic_reference_is_refused(data_dir, capsys, args):
    """BROAD's reference is relative to magnetic north: a declination turned only the
    estimates, and the replay reported a 30° heading error of the user's making."""
    path = data_dir / "broad" / "01_undisturbed_slow_rotation_A.npz"
    assert main(["replay", str(path), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "relative to magnetic north" in err[0]


def test_absurd_accelerometer_samples_leak_no_numpy_warning():
    """An accelerometer logged ×1e200 (a wrong unit) overflowed |acc| in the board check
    with a RuntimeWarning on the output; such samples count as not finite."""
    from replay.board import rest_magnitude

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isnan(rest_magnitude(np.full((100, 3), 1e200)))
        big = np.full((100, 3), 1e150)
        big[::2] *= 2.0
        assert np.isfinite(rest_magnitude(big))
