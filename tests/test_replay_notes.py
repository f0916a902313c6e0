"""Damaged but usable input is counted in a note, impossible input is a one-line error.

Every file here is a copy of real data (the first 20000 samples of a BROAD trial, or
the SIH tlog) with one kind of damage put in: the replay must say what it found
instead of scoring damaged input as if it were sound.
"""

from __future__ import annotations

import json
import os
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest

import replay
from bridge.app.cli import main
from replay.readers import csv as csv_format

os.environ["MAVLINK20"] = "1"
N = 20000  # BROAD samples kept: 70 s, enough to have a scored stretch, fast to run
BROAD = "broad/01_undisturbed_slow_rotation_A.npz"


@pytest.fixture(scope="module")
def broad(data_dir) -> dict[str, np.ndarray]:
    """The BROAD trial cut to its first N samples, as arrays to damage."""
    with np.load(data_dir / BROAD) as data:
        out = {k: np.array(data[k]) for k in data.files}
    for key in ("gyr", "acc", "mag", "quat_ref", "movement"):
        out[key] = out[key][:N].copy()
    return out


def npz(tmp_path: Path, data: dict[str, np.ndarray], **damaged: np.ndarray) -> Path:
    """The trial with some arrays replaced, written to ``tmp_path``."""
    path = tmp_path / "damaged.npz"
    np.savez(path, **(data | damaged))
    return path


def as_csv(tmp_path: Path, data: dict[str, np.ndarray], t: np.ndarray | None = None,
           score: np.ndarray | None = None, **columns: np.ndarray) -> Path:
    """The trial as this project's CSV (ENU, magnetic north), with columns replaced."""
    arrays = {"t": np.arange(N) / float(data["rate"]), "gyr": data["gyr"],
              "acc": data["acc"], "mag": data["mag"], "quat_ref": data["quat_ref"]}
    arrays |= {"t": arrays["t"] if t is None else t, **columns}
    names = ["t", "gx", "gy", "gz", "ax", "ay", "az", "mx", "my", "mz", "qw", "qx", "qy", "qz"]
    parts = [arrays["t"][:, None], arrays["gyr"], arrays["acc"], arrays["mag"],
             arrays["quat_ref"]]
    if score is not None:
        names.append("score")
        parts.append(score[:, None].astype(float))
    path = tmp_path / "damaged.csv"
    with path.open("w", encoding="utf-8") as f:
        f.write(f"# world: ENU\n# north: magnetic\n{','.join(names)}\n")
        np.savetxt(f, np.hstack(parts), delimiter=",", fmt="%.9g")
    return path


def cli(path: Path, capsys, *extra: str) -> tuple[int, str, str]:
    """``attitude-bridge replay PATH -e mahony`` with any numpy warning as an error."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code = main(["replay", str(path), "-e", "mahony", *extra])
    out, err = capsys.readouterr()
    return code, out, err


def evaluate(path: Path) -> replay.Evaluation:
    return replay.evaluate(replay.load(path), ["mahony"], aid="none")


# 1. sample rates no IMU has --------------------------------------------------------------

def test_an_npz_rate_beyond_any_imu_is_a_one_line_error(tmp_path, broad, capsys):
    path = npz(tmp_path, broad, rate=np.array(1e300))
    code, out, err = cli(path, capsys)
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and str(path) in err
    assert "rate 1e+300 Hz implausible" in err and "time not in seconds?" in err


def test_a_csv_time_in_nanoseconds_is_a_one_line_error(tmp_path, broad, capsys):
    path = as_csv(tmp_path, broad, t=np.arange(N) / float(broad["rate"]) * 1e-9)
    code, out, err = cli(path, capsys)
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and "implausible: time not in seconds?" in err


def test_a_tiny_rate_is_too_slow_without_a_numpy_warning(tmp_path, broad, capsys):
    path = npz(tmp_path, broad, rate=np.array(1e-300))
    code, out, err = cli(path, capsys)
    assert code == 0 and err == ""
    head = out.splitlines()[0].removeprefix(str(path))
    assert "at 1e-300 Hz" in head and len(head) < 100  # not 300 digits
    assert "not scored: IMU at 1e-300 Hz is too slow" in out


# 2. a magnetometer without usable readings -----------------------------------------------

def assert_heading_not_scored(ev: replay.Evaluation, n: int) -> None:
    s = ev.scores["mahony"]
    assert s.six_d and np.isnan(s.heading_deg) and np.isfinite(s.inclination_deg)
    assert f"no usable magnetometer reading ({n} of {n} " in s.reasons["heading_deg"]
    assert "heading not observable" in s.reasons["heading_deg"]
    assert ev.recording.mag is None


def test_an_all_nan_npz_magnetometer_is_no_magnetometer(tmp_path, broad):
    ev = evaluate(npz(tmp_path, broad, mag=np.full((N, 3), np.nan)))
    assert_heading_not_scored(ev, N)


def test_an_all_nan_csv_magnetometer_is_no_magnetometer(tmp_path, broad):
    ev = evaluate(as_csv(tmp_path, broad, mag=np.full((N, 3), np.nan)))
    assert_heading_not_scored(ev, N)


def test_a_partly_damaged_magnetometer_is_counted(tmp_path, broad):
    mag = broad["mag"].copy()
    mag[3000:3500] = np.nan
    mag[4000:4200] = 0.0
    rec = replay.load(npz(tmp_path, broad, mag=mag))
    assert f"magnetometer: 700 of {N} readings unusable (NaN, infinite or zero)" in rec.notes


# 3. damaged accelerometer and reference rows ---------------------------------------------

def test_non_finite_npz_accelerometer_rows_are_counted(tmp_path, broad):
    acc = broad["acc"].copy()
    acc[5000:6000] = np.inf
    rec = replay.load(npz(tmp_path, broad, acc=acc))
    assert any(n.startswith(f"accelerometer: 1000 of {N} readings not finite")
               for n in rec.notes)


def test_non_finite_csv_accelerometer_cells_are_counted(tmp_path, broad, capsys):
    acc = broad["acc"].copy()
    acc[100:130, 0] = np.nan
    acc[200:210, 2] = -np.inf
    code, out, _ = cli(as_csv(tmp_path, broad, acc=acc), capsys)
    assert code == 0
    assert f"  note: accelerometer: 40 of {N} readings not finite" in out


def test_infinite_csv_reference_cells_are_counted_and_never_scored(tmp_path, broad):
    q = broad["quat_ref"].copy()
    q[100:150, 0] = np.inf
    q[150] = [1e308, 1e308, 0.0, 0.0]  # finite, but its norm is not
    ev = evaluate(as_csv(tmp_path, broad, quat_ref=q))
    assert (f"reference: 51 of {N} quaternions unusable (zero or not finite)"
            in ev.recording.notes)
    assert not ev.prepared.scored[100:151].any()
    assert np.isnan(ev.prepared.q_ref[100:151]).all()


def test_zero_npz_reference_rows_are_counted(tmp_path, broad):
    q = broad["quat_ref"].copy()
    q[::2] = 0.0
    rec = replay.load(npz(tmp_path, broad, quat_ref=q))
    assert f"reference: {N // 2} of {N} quaternions unusable (zero or not finite)" in rec.notes
    assert np.isnan(rec.reference.q[::2]).all()


def test_a_reference_made_directly_drops_zero_and_non_finite_rows():
    q = np.array([[1.0, 0, 0, 0], [0, 0, 0, 0], [np.inf, 0, 0, 0], [np.nan] * 4])
    ref = replay.Reference(t=np.arange(4.0), q=q, kind="truth", source="test")
    assert ref.damaged == 2  # the all-NaN row means "no reference there": no damage
    assert np.isfinite(ref.q[0]).all() and np.isnan(ref.q[1:]).all()
    assert q[1].tolist() == [0, 0, 0, 0]  # the caller's array is left alone


# 4. footnotes that give the real reason --------------------------------------------------

def test_an_all_zero_reference_says_it_has_no_valid_quaternion(tmp_path, broad, capsys):
    code, out, _ = cli(npz(tmp_path, broad, quat_ref=np.zeros((N, 4))), capsys)
    assert code == 0
    why = (f"reference (quat_ref (optical)) has no valid quaternion ({N} of {N} zero or "
           f"not a number)")
    assert f"(1) total°: {why}" in out
    assert "does not overlap" not in out and "score mask" not in out


def test_a_score_column_of_zeros_says_it_selects_no_row(tmp_path, broad, capsys):
    code, out, _ = cli(as_csv(tmp_path, broad, score=np.zeros(N)), capsys)
    assert code == 0
    assert "(1) total°: the file's score column selects no row" in out
    assert "does not overlap" not in out


def swapped_halves(source: Path, target: Path) -> Path:
    """The tlog with the records of its second half moved before the first."""
    raw = source.read_bytes()
    records, i = [], 0
    while i + 8 < len(raw):  # 8-byte time stamp, then one MAVLink 1 or 2 frame
        length = raw[i + 9]
        signed = raw[i + 10] & 1
        frame = 12 + length + (13 if signed else 0) if raw[i + 8] == 0xFD else 8 + length
        records.append(raw[i:i + 8 + frame])
        i += 8 + frame
    half = len(records) // 2
    target.write_bytes(b"".join(records[half:] + records[:half]))
    assert struct.unpack(">Q", target.read_bytes()[:8]) != struct.unpack(">Q", raw[:8])
    return target


def test_the_autopilot_row_gets_its_own_reason(tmp_path, data_dir, capsys):
    path = swapped_halves(data_dir / "px4_sih" / "sih_box.tlog", tmp_path / "swapped.tlog")
    code, out, _ = cli(path, capsys, "--json", str(tmp_path / "r.json"))
    assert code == 0
    reasons = json.loads((tmp_path / "r.json").read_text())["estimators"]["autopilot"]
    why = reasons["reasons"]["total_deg"]
    assert why.startswith("the autopilot's attitude (ATTITUDE_QUATERNION, ")
    assert "does not overlap the scored IMU samples" in why
    assert "accelerometer" not in out


def test_csv_helper_writes_what_the_reader_reads(tmp_path, broad):
    """The CSV written here is the documented format (guards the tests above)."""
    rec = csv_format.read(as_csv(tmp_path, broad))
    assert rec.n == N and rec.world == "ENU" and rec.notes == ()
    assert rec.reference is not None and rec.reference.north == "magnetic"
