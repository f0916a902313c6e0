"""``attitude-bridge calibrate`` on hostile input: options checked before any work,
damaged logs fitted with a counted note, absurd ones refused in one line and without
numpy warnings (a RuntimeWarning here fails the test: ``filterwarnings("error")``)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from test_calibration import RATE, fibonacci_directions, synthetic_session

import bridge.app.calibrate_cli as calibrate_cli
from bridge.app.cli import main as cli_main

HEADER = "t,gx,gy,gz,ax,ay,az,mx,my,mz"


@pytest.fixture(scope="module")
def session() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return synthetic_session(fibonacci_directions(16), np.random.default_rng(7))


def write_log(path: Path, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray) -> Path:
    t = np.arange(len(gyr)) / RATE
    np.savetxt(path, np.column_stack([t, gyr, acc, mag]), delimiter=",", header=HEADER,
               comments="")
    return path


@pytest.fixture
def log(tmp_path, session) -> Path:
    return write_log(tmp_path / "session.csv", *session)


def calibrate(capsys, *args: object) -> tuple[int, str, str]:
    try:
        code = cli_main(["calibrate", *map(str, args)])
    except SystemExit as exc:  # argparse's own usage errors
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def one_error(err: str) -> str:
    """The single stderr line, which must be an ``error:`` line."""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "calibrate: error: " in lines[0], err
    return lines[0]


# --- B: absurd samples are refused without numpy warnings ----------------------------

@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("damage, message", [
    (lambda g, a, m: (g, np.zeros_like(a), m),
     r"accelerometer: 16 of 16 static poses read \|a\| .*median 0\.000 m/s\^2"),
    (lambda g, a, m: (g, a * 1e200, m), r"accelerometer.*beyond ±2000 m/s\^2"),
    (lambda g, a, m: (g, a, m * 1e300), r"magnetometer.*beyond ±100 gauss"),
])
def test_absurd_samples_are_refused_in_one_line(tmp_path, capsys, session, damage, message):
    path = write_log(tmp_path / "absurd.csv", *damage(*session))
    code, _, err = calibrate(capsys, path, "-o", tmp_path / "c.toml")
    assert code == 2
    assert re.search(message, one_error(err)), err


@pytest.mark.filterwarnings("error")
def test_isolated_infinite_samples_are_interpolated_without_warnings(tmp_path, capsys,
                                                                     session):
    gyr, acc, mag = session
    acc = acc.copy()
    acc[::100] = np.inf
    path = write_log(tmp_path / "inf.csv", gyr, acc, mag)
    code, out, err = calibrate(capsys, path, "-o", tmp_path / "c.toml")
    assert (code, err) == (0, "")
    assert f"accelerometer: {len(acc[::100])} samples unusable ({len(acc[::100])} " \
           "non-finite)" in out


# --- C: damage is reported, and NaN samples do not cost still stretches or turns -----

def test_reader_notes_are_printed(tmp_path, capsys, log):
    lines = log.read_text().splitlines()
    lines[3000:3000] = ["abc,1,2,3,4,5,6,7,8,9", "1.2.3,1,2,3,4,5,6,7,8,9"]
    damaged = tmp_path / "damaged.csv"
    damaged.write_text("\n".join(lines) + "\n")
    out_file = tmp_path / "c.toml"
    code, out, _ = calibrate(capsys, damaged, "-o", out_file)
    assert code == 0
    note = f"note: {damaged}: CSV: 2 rows with non-numeric cells dropped (first at line"
    assert note in out
    assert "2 rows with non-numeric cells dropped" in out_file.read_text()  # and in the file


def test_isolated_nan_samples_are_interpolated_and_counted(tmp_path, capsys, session):
    gyr, acc, mag = (x.copy() for x in session)
    rng = np.random.default_rng(5)
    bad_g, bad_a = rng.random(len(gyr)) < 0.01, rng.random(len(gyr)) < 0.01
    gyr[bad_g], acc[bad_a], mag[rng.random(len(gyr)) < 0.01] = np.nan, np.nan, np.nan
    path = write_log(tmp_path / "nan.csv", gyr, acc, mag)
    code, out, err = calibrate(capsys, path, "-o", tmp_path / "c.toml")
    assert code == 0, err
    assert f"gyro: {bad_g.sum()} samples unusable ({bad_g.sum()} non-finite); " \
           f"{bad_g.sum()} interpolated from their neighbours" in out
    assert f"accelerometer: {bad_a.sum()} samples unusable" in out
    assert "magnetometer:" in out and "left out" in out
    assert "16 static poses" in out and "from 15 turns" in out  # as without the NaNs


def test_a_refusal_names_the_unusable_samples(tmp_path, capsys, session):
    """Runs of NaN too long to interpolate break every still stretch: the refusal must
    say so, not only blame the motion."""
    gyr, acc, mag = (x.copy() for x in session)
    gyr[np.arange(len(gyr)) % 60 < 10] = np.nan
    path = write_log(tmp_path / "holes.csv", gyr, acc, mag)
    code, _, err = calibrate(capsys, path, "-o", tmp_path / "c.toml")
    assert code == 2
    line = one_error(err)
    assert "still stretch" in line and "gyro/accelerometer samples were unusable" in line


# --- D: the same file twice is used once ----------------------------------------------

def test_the_same_log_given_twice_is_used_once(tmp_path, capsys, log, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, _ = calibrate(capsys, log, "session.csv", "-o", "c.toml")
    assert code == 0
    assert f"note: {log} given 2 times; used once" in out
    assert "from 15 turns" in out


# --- F: options and the output file are checked before any work ------------------------

@pytest.fixture
def no_fit(monkeypatch):
    """Fail the test if a log is read or a fit started."""

    def refuse(*_: object, **__: object) -> None:
        raise AssertionError("work started before the options were checked")

    monkeypatch.setattr(calibrate_cli, "load_log", refuse)
    monkeypatch.setattr(calibrate_cli, "fit_calibration", refuse)


@pytest.mark.parametrize("output, message", [
    ("{tmp}/missing/c.toml", "-o/--output {tmp}/missing/c.toml: folder {tmp}/missing does "
                             "not exist"),
    ("", "-o/--output .: is a folder"),
    ("/proc/version", "-o/--output /proc/version: cannot be written"),
    ("{log}", "-o/--output {log}: is one of the LOG files"),
])
def test_bad_output_is_refused_before_any_work(tmp_path, capsys, log, no_fit, output,
                                              message):
    before = log.read_bytes()
    code, _, err = calibrate(capsys, log, "-o", output.format(tmp=tmp_path, log=log))
    assert code == 2
    assert message.format(tmp=tmp_path, log=log) in one_error(err)
    assert log.read_bytes() == before


def test_output_that_is_an_input_under_another_name_is_refused(tmp_path, capsys, log,
                                                               no_fit, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = calibrate(capsys, log, "-o", "./session.csv")
    assert code == 2 and "is one of the LOG files" in one_error(err)


@pytest.mark.parametrize("args, message", [
    (["--no-gyro", "--no-accel", "--no-mag"], "nothing to fit"),
    (["--board", "bogus"], "argument --board: invalid choice: 'bogus'"),
    (["--imu", "BOGUS"], "--imu 'BOGUS': unknown IMU message"),
])
def test_bad_options_are_refused_whatever_the_input(tmp_path, capsys, log, no_fit, args,
                                                    message):
    code, _, err = calibrate(capsys, log, "-o", tmp_path / "c.toml", *args)
    assert code == 2 and message in one_error(err)
    assert not (tmp_path / "c.toml").exists()


def test_a_negative_seed_names_the_option(tmp_path, capsys, no_fit):
    code, _, err = calibrate(capsys, "--emulator", "--seed", "-1", "-o", tmp_path / "c.toml")
    assert code == 2 and "argument --seed: " in one_error(err)
