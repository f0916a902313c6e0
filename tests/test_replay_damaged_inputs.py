"""Damaged input files: one clear line and exit 2, or the data kept with a counted note.

Never an internal error, a hang, a leaked numpy warning or data lost without a word. Each
damaged file is made here from the shared sample data.
"""

from __future__ import annotations

import os
import shutil
import struct
import warnings
import zipfile

import numpy as np
import pytest

from bridge.app.cli import main
from replay import load
from replay.align import measure_lag
from replay.readers import csv as csv_format
from replay.synthetic import SyntheticConfig, generate, truth_attitude

os.environ["MAVLINK20"] = "1"

BROAD = "broad/01_undisturbed_slow_rotation_A.npz"
ROWS = 20_000  # of the BROAD trial, for the CSVs


def broad_csv(data_dir, path, t_of=None) -> None:
    """The first ``ROWS`` samples of a BROAD trial as a CSV; ``t_of`` changes the times.

    Written with 15 digits: a stamp near 1e6 s keeps its sub-millisecond steps.
    """
    trial = np.load(data_dir / BROAD)
    t = np.arange(ROWS) / float(trial["rate"])
    if t_of is not None:
        t = t_of(t)
    table = np.hstack([t[:, None], trial["gyr"][:ROWS], trial["acc"][:ROWS],
                       trial["mag"][:ROWS], trial["quat_ref"][:ROWS]])
    with path.open("w") as f:
        f.write("# world: ENU\nt,gx,gy,gz,ax,ay,az,mx,my,mz,qw,qx,qy,qz\n")
        np.savetxt(f, table, delimiter=",", fmt="%.15g")


def one_line_error(capsys, command: str, path) -> str:
    """The error line (checked to be the only output on stderr)."""
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err.startswith(f"attitude-bridge {command}: error: {path}: "), err
    return err


# --- .npz --------------------------------------------------------------------------------

def test_npz_with_a_damaged_member_is_one_line_in_replay_and_left_out_by_tune(
        data_dir, tmp_path, capsys):
    """1000 zeroed bytes in the middle of the archive used to end in "internal error
    (BadZipFile: Bad CRC-32 ...)", exit 1, in replay and in tune (which aborted)."""
    data = bytearray((data_dir / BROAD).read_bytes())
    middle = len(data) // 2
    data[middle:middle + 1000] = bytes(1000)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(bytes(data))
    assert main(["replay", str(bad), "-e", "mahony"]) == 2
    err = one_line_error(capsys, "replay", bad)
    assert "not a readable .npz (quat_ref: zipfile.BadZipFile: Bad CRC-32" in err

    rec = generate(SyntheticConfig(duration_s=4.0, seed=5))
    good = tmp_path / "good.csv"
    csv_format.write(good, rec.t, rec.gyr, rec.acc, rec.mag, rec.reference.q)
    assert main(["tune", str(bad), str(good), "-e", "mahony", "--param", "kp=0.5,1",
                 "--jobs", "1", "-q"]) == 0
    out, err = capsys.readouterr()
    assert f"left out {bad}: not a readable .npz" in err and "good.csv: total" in out


def test_npz_with_a_broken_deflate_stream_is_one_line(data_dir, tmp_path, capsys):
    """Zeros where a compressed member's data starts: zlib's "Error -3 while
    decompressing data" used to be an internal error."""
    src = data_dir / BROAD
    with zipfile.ZipFile(src) as archive:
        member = archive.getinfo("acc.npy")
    data = bytearray(src.read_bytes())
    name_len, extra_len = struct.unpack("<HH", data[member.header_offset + 26:
                                                    member.header_offset + 30])
    start = member.header_offset + 30 + name_len + extra_len
    data[start:start + 64] = bytes(64)  # a stored block whose length check fails
    path = tmp_path / "garbled.npz"
    path.write_bytes(bytes(data))
    assert main(["replay", str(path), "-e", "mahony"]) == 2
    err = one_line_error(capsys, "replay", path)
    assert "not a readable .npz (acc: zlib.error: Error -3 while decompressing" in err


def test_a_tlog_named_npz_is_said_to_be_no_zip_archive(data_dir, tmp_path, capsys):
    """numpy's message for it invited the user to load the file with allow_pickle."""
    path = tmp_path / "flight.npz"
    shutil.copyfile(data_dir / "px4_sih" / "sih_box.tlog", path)
    assert main(["replay", str(path), "-e", "mahony"]) == 2
    err = one_line_error(capsys, "replay", path)
    assert "not a .npz (zip) archive" in err and "pickle" not in err


def test_complex_npz_arrays_are_refused_without_a_numpy_warning(data_dir, tmp_path, capsys):
    """A complex gyro used to be cast to real with numpy's ComplexWarning on the terminal
    and replayed as if nothing was wrong."""
    trial = np.load(data_dir / BROAD)
    n = 2000
    path = tmp_path / "complex.npz"
    np.savez(path, rate=trial["rate"], gyr=trial["gyr"][:n].astype(complex),
             acc=trial["acc"][:n], mag=trial["mag"][:n], quat_ref=trial["quat_ref"][:n])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert main(["replay", str(path), "-e", "mahony"]) == 2
    err = one_line_error(capsys, "replay", path)
    assert "gyr holds complex numbers (complex128); expected real numbers" in err


# --- time stamps: lag grid, CSV spikes ---------------------------------------------------

def test_lag_is_measured_on_the_longest_stretch_when_the_clock_jumps():
    """The lag grid spanned the whole time: a jump of 1e9 s asked numpy for terabytes
    (MemoryError, an internal error); a jump of 1e6 s took minutes and gigabytes."""
    cfg = SyntheticConfig(duration_s=30.0, rate_hz=200.0)
    t, q = truth_attitude(cfg)
    delay = 40  # samples = 0.2 s
    est = np.vstack([np.repeat(q[:1], delay, axis=0), q[:-delay]])
    jumped = t.copy()
    jumped[4000:] += 1e9  # the first 20 s, then 10 s a clock jump later
    lag, why = measure_lag(jumped, est, q)
    assert why == "" and lag == pytest.approx(0.2, abs=0.5 / cfg.rate_hz)
    short = t.copy()
    short[10:] += 1e9  # the longest stretch is too short to measure a lag on
    lag, why = measure_lag(short, est, q, np.arange(len(t)) < 20)
    assert np.isnan(lag)
    assert why == "longest scored stretch without a time gap shorter than 16 IMU steps"


def test_csv_whose_clock_jumps_by_days_replays(data_dir, tmp_path, capsys):
    """The CLI end of the above: the replay used to hang with gigabytes of memory."""
    path = tmp_path / "jump.csv"
    broad_csv(data_dir, path, lambda t: np.where(np.arange(len(t)) >= ROWS // 2, t + 1e6, t))
    assert main(["replay", str(path), "-e", "mahony"]) == 0
    out = capsys.readouterr().out
    assert f"{ROWS} samples" in out and "dropped" not in out


def test_one_csv_time_spike_drops_that_row_alone(data_dir, tmp_path, capsys):
    """One stamp of 1e9 s among seconds used to drop every row after it as "going
    backwards" (three quarters of the file, with only a count to say so)."""
    path = tmp_path / "spike.csv"

    def spike(t):
        t = t.copy()
        t[5000] = 1e9
        return t

    broad_csv(data_dir, path, spike)
    rec = load(path)
    assert rec.n == ROWS - 1 and rec.cleanup.dropped == 0 and rec.t[-1] < 100.0
    assert rec.notes == (f"CSV: 1 row with a time stamp out of line with the rows either side "
                         f"dropped (first: t = 1e+09 s, the next row's {rec.t[5000]:g} s)",)
    assert main(["replay", str(path), "-e", "mahony"]) == 0
    assert "note: CSV: 1 row with a time stamp out of line" in capsys.readouterr().out


def test_a_csv_clock_reset_still_drops_the_rows_going_backwards(data_dir, tmp_path):
    """A clock that really goes back is no spike: the rows behind the last kept time are
    dropped and counted as before."""
    path = tmp_path / "reset.csv"
    broad_csv(data_dir, path, lambda t: np.where(np.arange(len(t)) >= 15_000, t - 30.0, t))
    rec = load(path)
    assert rec.cleanup.backwards > 0 and rec.n == ROWS - rec.cleanup.backwards
    assert not [n for n in rec.notes if "out of line" in n]


def test_csv_with_a_duplicated_column_is_refused(data_dir, tmp_path, capsys):
    """A second `gx` column (another gyro, or the same one in other units) was ignored
    without a word: the first one was used."""
    path = tmp_path / "dup.csv"
    broad_csv(data_dir, path)
    lines = path.read_text().splitlines()
    header = lines.index("t,gx,gy,gz,ax,ay,az,mx,my,mz,qw,qx,qy,qz")
    lines[header] += ",gx"
    lines[header + 1:] = [line + ",0" for line in lines[header + 1:]]
    path.write_text("\n".join(lines) + "\n")
    assert main(["replay", str(path), "-e", "mahony"]) == 2
    err = one_line_error(capsys, "replay", path)
    assert "duplicate column gx in the header (columns 2 and 15)" in err


# --- tlog -------------------------------------------------------------------------------

def tlog_records(data: bytes) -> list[bytes]:
    """A tlog's records (8-byte stamp + one MAVLink 1 or 2 frame), in file order."""
    records, i = [], 0
    while i + 8 < len(data):
        length, signed = data[i + 9], data[i + 10] & 0x01
        frame = 12 + length + 13 * signed if data[i + 8] == 0xFD else 8 + length
        records.append(data[i:i + 8 + frame])
        i += 8 + frame
    return records


def test_tlog_whose_recorder_clock_jumps_keeps_the_records_after_it(data_dir, tmp_path):
    """The arrival stamps of the second half 10^12 µs (11.6 days) later, as when a
    companion computer takes the network's time mid-flight: everything after the jump
    used to be lost, the only note "skipped 1 unreadable stretch(es)"."""
    src = data_dir / "px4_sih" / "sih_box.tlog"
    records = tlog_records(src.read_bytes())
    half = len(records) // 2
    path = tmp_path / "jump.tlog"
    with path.open("wb") as f:
        for k, record in enumerate(records):
            stamp = struct.unpack(">Q", record[:8])[0] + (10**12 if k >= half else 0)
            f.write(struct.pack(">Q", stamp) + record[8:])
    rec, whole = load(path), load(src)
    np.testing.assert_array_equal(rec.t, whole.t)
    np.testing.assert_array_equal(rec.reference.t, whole.reference.t)
    assert not [n for n in rec.notes if "unreadable" in n]
    assert (f"the recorder's clock (tlog arrival stamps) jumped 1 time(s), by up to "
            f"+11.6 days (first at record {half + 1} of {len(records)}): the "
            f"{len(records) - half} records from there are kept, their arrival times moved "
            f"to follow on from before the jump") in rec.notes


def test_a_spike_in_the_last_csv_row_is_dropped_too(data_dir, tmp_path, capsys):
    """The last row has no next row to be out of line with: a stamp of 1e9 s there was
    kept, and the replay reported a recording of 1e9 s."""
    path = tmp_path / "last.csv"

    def spike(t):
        t = t.copy()
        t[-1] = 1e9
        return t

    broad_csv(data_dir, path, spike)
    rec = load(path)
    assert rec.n == ROWS - 1 and rec.t[-1] < 100.0
    assert rec.notes == (f"CSV: 1 row with a time stamp out of line with the rows either side "
                         f"dropped (first: t = 1e+09 s, the row before's {rec.t[-1]:g} s)",)
    assert main(["replay", str(path), "-e", "mahony"]) == 0
    assert "1e+09 s at" not in capsys.readouterr().out


def test_a_csv_whose_clock_moves_on_after_a_pause_keeps_its_last_row(data_dir, tmp_path):
    """A last step as long as the recording before it is not yet out of line: only a
    step longer than everything before it is."""
    path = tmp_path / "pause.csv"

    def pause(t):
        t = t.copy()
        t[-1] = t[-2] + 0.9 * (t[-2] - t[0])
        return t

    broad_csv(data_dir, path, pause)
    rec = load(path)
    assert rec.n == ROWS and not [n for n in rec.notes if "out of line" in n]
