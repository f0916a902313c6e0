"""``replay`` / ``tune`` given bad options or damaged logs: one line naming the option and
exit 2, or a note in the output; never a NaN row, a silently ignored value or the
current folder replayed for an empty path."""

from __future__ import annotations

import json
import math
import socket
from pathlib import Path

import numpy as np
import pytest
from cli_support import one_line_error
from cli_support import run_cli as cli

from bridge.wire.codec import signing_key_from_text
from replay.dataset import ReplayInputError
from replay.logpaths import expand
from replay.readers import csv as csv_format
from replay.readers import load
from replay.synthetic import SyntheticConfig, generate
from replay.tune import damage_notes
from replay.tune_tasks import TuneInputs, sweep_share

SMALL_ULOG = "pyulog_sample_log_small.ulg"
TUNE = ["-e", "mahony", "--jobs", "1", "-q"]


@pytest.fixture
def small_ulog(data_dir) -> str:
    return str(data_dir / "logs" / SMALL_ULOG)


@pytest.fixture
def damaged_csv(tmp_path) -> Path:
    """A short synthetic log with truth whose time goes backwards at two rows and with a
    row that holds no number: the reader drops and counts them."""
    rec = generate(SyntheticConfig(duration_s=3.0, rate_hz=100.0, seed=4))
    path = tmp_path / "damaged.csv"
    t = rec.t.copy()
    t[[100, 200]] = t[[100, 200]] - 0.5  # going backwards
    csv_format.write(path, t, rec.gyr, rec.acc, rec.mag, rec.reference.q)
    lines = path.read_text().splitlines()
    cells = lines[50].split(",")
    cells[2] = "1.2.x"
    lines[50] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    return path


# --- 1. every value of a -p list is checked -------------------------------------------


@pytest.mark.parametrize("bad", ["nan", "inf", "-5", "1e308"])
def test_every_value_of_a_param_list_is_checked(small_ulog, tmp_path, bad):
    out = tmp_path / "n.csv"
    code, _, err = cli(["tune", small_ulog, *TUNE, "-p", f"kp=1,{bad}", "--out", str(out)])
    one_line_error(code, err, "--param", "'kp'")
    assert not out.exists()
    alone = cli(["tune", small_ulog, *TUNE, "-p", f"kp={bad}"])
    assert alone[0] == 2  # as a single value is


# --- 2. --jobs below 1 ----------------------------------------------------------------


@pytest.mark.parametrize("jobs", ["0", "-3"])
def test_jobs_below_one_is_refused_on_one_log(small_ulog, jobs):
    code, _, err = cli(["tune", small_ulog, "-e", "mahony", "-q", "-p", "kp=1,2",
                        "--jobs", jobs])
    one_line_error(code, err, f"--jobs {jobs}: expected a number of processes >= 1")
    code, out, err = cli(["replay", small_ulog, "-e", "mahony", "--jobs", jobs])
    one_line_error(code, err, f"--jobs {jobs}: expected a number of processes >= 1")
    assert out == ""


# --- 3. -p NAME_dps / NAME_deg ------------------------------------------------------------


def test_param_takes_degree_aliases_as_set_does(small_ulog, tmp_path):
    doc = {}
    for name, values in (("alias", "bias_limit_dps=1,20"),
                         ("si", f"bias_limit={math.radians(1)!r},{math.radians(20)!r}")):
        out = tmp_path / f"{name}.json"
        code, stdout, err = cli(["tune", small_ulog, *TUNE, "-p", values, "--out", str(out)])
        assert code == 0, err
        doc[name] = json.loads(out.read_text())
        doc[name]["stdout"] = stdout.splitlines()[1]
    # shown as --set shows a fixed one: the library's name, in rad/s
    assert doc["alias"]["params"] == {"bias_limit": pytest.approx(
        [math.radians(1), math.radians(20)], rel=1e-12)}
    assert doc["alias"]["stdout"] == doc["si"]["stdout"]
    assert doc["alias"]["stdout"].startswith("best mahony: bias_limit=0.0")
    code, _, err = cli(["tune", small_ulog, *TUNE, "-p", "bias_limit_dps=1,5000"])
    one_line_error(code, err, "--param", "bias_limit")
    code, _, err = cli(["tune", small_ulog, *TUNE, "-p", "bias_limit_dps=1",
                        "--set", "bias_limit=0.1"])
    one_line_error(code, err, "bias_limit: both swept (-p) and fixed")


# --- 4. an empty path -------------------------------------------------------------------


@pytest.mark.parametrize("command", [["replay"], ["tune", "-e", "mahony", "-p", "kp=1"]])
def test_an_empty_path_is_refused_not_the_current_folder(command, small_ulog, tmp_path,
                                                         monkeypatch):
    monkeypatch.chdir(tmp_path)  # a folder with a log in it: "" used to replay it
    (tmp_path / "a.ulg").write_bytes(Path(small_ulog).read_bytes())
    for paths in ([""], [small_ulog, ""]):
        code, out, err = cli([command[0], *paths, *command[1:]])
        one_line_error(code, err, "empty path")
        assert out == ""
    with pytest.raises(ReplayInputError, match="empty path"):
        expand([""])


# --- 5. --scheduler addresses -------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as s:  # a port where nothing listens
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_scheduler_errors_name_the_option(small_ulog, tmp_path):
    two = [small_ulog, str(tmp_path / "copy.ulg")]
    Path(two[1]).write_bytes(Path(small_ulog).read_bytes())
    code, _, err = cli(["replay", *two, "--scheduler", "tcp://[::1"])
    one_line_error(code, err, "--scheduler 'tcp://[::1'", "tcp://HOST:PORT")
    code, _, err = cli(["replay", *two, "--scheduler", f"tls://127.0.0.1:{free_port()}"])
    one_line_error(code, err, "--scheduler", "only tcp://")
    code, _, err = cli(["tune", *two, "-e", "mahony", "-p", "kp=1", "--scheduler",
                        f"tls://127.0.0.1:{free_port()}"])
    one_line_error(code, err, "--scheduler", "only tcp://")
    code, out, err = cli(["replay", small_ulog, "--scheduler", "tcp://[::1"])
    assert out == ""
    one_line_error(code, err, "--scheduler 'tcp://[::1'")  # not ignored for one log


# --- 6. tune shows the reader's damage notes --------------------------------------------


def test_tune_shows_and_writes_the_damage_notes(damaged_csv, small_ulog, tmp_path):
    out = tmp_path / "sweep.json"
    code, stdout, err = cli(["tune", str(damaged_csv), small_ulog, "-e", "mahony",
                             "--jobs", "1", "-p", "kp=0.5,1", "--out", str(out)])
    assert code == 0, err
    rec = load(damaged_csv)  # the reader's own words, as the single-file replay says them
    assert rec.cleanup.backwards == 2
    cells = next(n for n in rec.notes if "non-numeric cells dropped (first at line 51)" in n)
    notes = [cells, f"dropped IMU samples: {rec.cleanup}"]
    lines = stdout.splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("  damaged.csv: total"))
    assert lines[at + 1:at + 3] == [f"    note: {n}" for n in notes], stdout
    assert "magnetometer from" not in stdout  # not damage: not repeated here
    doc = json.loads(out.read_text())
    assert doc["notes"] == {str(damaged_csv): notes, small_ulog: []}
    quiet = cli(["tune", str(damaged_csv), "-e", "mahony", "--jobs", "1", "-q",
                 "-p", "kp=0.5,1"])
    assert quiet[0] == 0 and "note:" not in quiet[1]


def test_a_cluster_share_brings_back_the_damage_notes(damaged_csv):
    """What a Dask worker returns for one log (run here, no cluster needed)."""
    share = sweep_share("damaged.csv", str(damaged_csv), TuneInputs(), "mahony", {},
                        ({"kp": 1.0},), "sensors")
    assert share["notes"][-1] == f"dropped IMU samples: {load(damaged_csv).cleanup}"
    assert np.isfinite(share["scores"]).all()


def test_every_damage_a_reader_counts_is_a_damage_note_in_tune(tmp_path):
    """tune picked the damage notes by their wording and missed the unusable
    magnetometer and accelerometer readings ("unusable", "not finite")."""
    t = np.arange(400) / 200.0
    rows = np.column_stack([t, np.zeros((400, 3)), np.tile([0.0, 0.0, -9.81], (400, 1)),
                            np.tile([0.2, 0.0, 0.4], (400, 1))])
    rows[10:20, 7:10] = np.nan  # magnetometer
    rows[30, 4] = np.inf  # accelerometer
    path = tmp_path / "sensors.csv"
    np.savetxt(path, rows, delimiter=",", header="t,gx,gy,gz,ax,ay,az,mx,my,mz",
               comments="")
    notes = damage_notes(load(path))
    assert notes == ("magnetometer: 10 of 400 readings unusable (NaN, infinite or zero)",
                     "accelerometer: 1 of 400 readings not finite (the estimators use the "
                     "gyro alone there)")


def test_a_signing_key_a_digit_short_is_refused_not_hashed_as_a_passphrase(tmp_path,
                                                                            monkeypatch):
    """63 hex digits were hashed as a passphrase: the bridge signed with a key the
    autopilot does not have, and every signed frame was refused there in silence."""
    key = "0123456789abcdef" * 4
    monkeypatch.setenv("BRIDGE_TEST_KEY", key[:-1])
    code, _, err = cli(["run", "--signing-key", "env:BRIDGE_TEST_KEY", "--duration", "1"])
    one_line_error(code, err, "--signing-key env:BRIDGE_TEST_KEY", "63 hex digits",
                   "a key has 64")
    (tmp_path / "key.txt").write_text(key + "0\n")
    code, _, err = cli(["run", "--signing-key", f"file:{tmp_path / 'key.txt'}",
                        "--duration", "1"])
    one_line_error(code, err, "65 hex digits")
    # the whole key, and a passphrase, are taken as before
    assert signing_key_from_text(key) == bytes.fromhex(key)
    assert len(signing_key_from_text("correct horse battery staple")) == 32
    assert len(signing_key_from_text("cafe")) == 32  # short: a passphrase
