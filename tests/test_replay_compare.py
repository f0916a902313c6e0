"""`replay --compare`: VQF (online, offline) and imufusion beside our estimators, on the
same samples, with the same declination, scored by the same code."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest
import vqf

from bridge.app.cli import main
from estimators import metrics
from replay import references

BROAD_01 = "broad/01_undisturbed_slow_rotation_A.npz"


def replay_json(capsys, tmp_path, *argv: str) -> dict:
    out = tmp_path / "r.json"
    code = main(["replay", *argv, "--json", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    doc = json.loads(out.read_text())
    doc["_stdout"] = captured.out
    return doc


def test_vqf_in_replay_is_vqf_run_by_hand_on_a_broad_trial(data_dir, tmp_path, capsys):
    """BROAD's world is ENU with magnetic north: VQF's own output, scored by the
    dataset's rule over the movement samples, must be what the replay reports."""
    path = data_dir / BROAD_01
    doc = replay_json(capsys, tmp_path, str(path), "-e", "eskf", "--compare", "vqf")
    with np.load(path) as d:
        q = vqf.VQF(1.0 / float(d["rate"])).updateBatch(
            np.ascontiguousarray(d["gyr"]), np.ascontiguousarray(d["acc"]),
            np.ascontiguousarray(d["mag"]))["quat9D"]
        by_hand = metrics.rms_errors(q, d["quat_ref"], np.asarray(d["movement"], bool))
    got = doc["estimators"]["vqf online"]
    assert got["total_deg"] == pytest.approx(by_hand.total_deg, abs=1e-6)
    assert got["inclination_deg"] == pytest.approx(by_hand.inclination_deg, abs=1e-6)
    assert "vqf online" in doc["_stdout"]


def test_every_reference_on_a_px4_flight_in_true_north_ned(data_dir, tmp_path, capsys):
    """A PX4 SIH flight: FRD body, NED world, the truth in true north (declination
    3.66°). Wrong frames would score tens of degrees; without the declination the
    heading would carry 3.7° more. The numbers are docs/accuracy.md's for these
    libraries (VQF 2.1, imufusion 1.3), measured by benchmarks/accuracy.py."""
    doc = replay_json(capsys, tmp_path, str(data_dir / "px4_sih" / "sih_box.tlog"),
                      "-e", "eskf", "--compare", "vqf,vqf-offline", "--compare", "imufusion")
    scores = doc["estimators"]
    assert list(scores) == ["eskf", "autopilot", "vqf online", "vqf offline", "imufusion"]
    for label, (total, incl) in {"vqf online": (3.389, 3.198),
                                 "vqf offline": (2.650, 2.375),
                                 "imufusion": (5.413, 3.708)}.items():
        assert scores[label]["total_deg"] == pytest.approx(total, abs=0.01), label
        assert scores[label]["inclination_deg"] == pytest.approx(incl, abs=0.01), label
        assert scores[label]["phases"]["flight"]["samples"] > 0  # every phase scored too
    assert scores["eskf"]["total_deg"] < scores["vqf online"]["total_deg"]


def test_the_csv_carries_each_reference_beside_the_estimators(data_dir, tmp_path, capsys):
    out = tmp_path / "series.csv"
    doc = replay_json(capsys, tmp_path, str(data_dir / BROAD_01), "-e", "eskf",
                      "--compare", "vqf", "--csv", str(out))
    header = out.read_text().splitlines()[0].split(",")
    assert "vqf online.qw" in header and "vqf online.err_total_deg" in header
    table = np.genfromtxt(out, delimiter=",", skip_header=1)
    err = table[:, header.index("vqf online.err_total_deg")]
    with np.load(data_dir / BROAD_01) as d:
        movement = np.asarray(d["movement"], bool)
    scored = movement & np.isfinite(err)
    rms = float(np.sqrt(np.mean(err[scored] ** 2)))
    assert rms == pytest.approx(doc["estimators"]["vqf online"]["total_deg"], rel=1e-6)


def test_bad_names_and_a_missing_package_are_one_line_before_any_work(
        data_dir, capsys, monkeypatch):
    path = str(data_dir / BROAD_01)
    assert main(["replay", path, "--compare", "vqf,vqff"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown reference 'vqff'" in err
    assert "vqf, vqf-offline, imufusion" in err
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "imufusion" else real(name, *a))
    assert main(["replay", path, "--compare", "imufusion"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "--compare imufusion needs the imufusion package" in err
    assert "attitude-bridge[compare]" in err


def test_damaged_samples_are_handed_over_as_missing_and_noted(data_dir, tmp_path, capsys):
    """A non-finite gyro row would turn VQF's whole attitude into NaN from there on,
    and a non-finite accelerometer row imufusion's: held / left out, and said so."""
    with np.load(data_dir / BROAD_01) as d:
        arrays = {k: d[k] for k in d.files}
    arrays["gyr"][20000:20010] = np.nan  # inside the movement that is scored
    arrays["acc"][30000:30004] = np.inf
    path = tmp_path / "damaged.npz"
    np.savez(path, **arrays)
    doc = replay_json(capsys, tmp_path, str(path), "-e", "eskf", "--compare",
                      "vqf,imufusion")
    for label in ("vqf online", "imufusion"):
        total = doc["estimators"][label]["total_deg"]
        assert total is not None and 0.0 < total < 10.0, (label, total)
    out = doc["_stdout"]
    assert ("note: vqf online: 10 non-finite gyro samples held at the last finite rate; "
            "4 non-finite accelerometer samples left out") in out


def test_library_inputs_hold_the_last_finite_gyro_row():
    gyr = np.array([[np.nan] * 3, [1.0, 2, 3], [np.nan, 0, 0], [4.0, 5, 6]])
    held, _, _, note = references._library_inputs(gyr, np.ones((4, 3)), None)
    np.testing.assert_array_equal(held, [[0, 0, 0], [1, 2, 3], [1, 2, 3], [4, 5, 6]])
    assert note.startswith("2 non-finite gyro samples")


def test_a_corpus_gets_a_column_per_reference(data_dir, tmp_path, capsys):
    logs = [data_dir / BROAD_01, data_dir / "broad" / "10_undisturbed_slow_translation_A.npz"]
    out = tmp_path / "corpus.json"
    code = main(["replay", *map(str, logs), "-e", "eskf", "--compare", "vqf", "-q",
                 "--jobs", "1", "--json", str(out)])
    assert code == 0, capsys.readouterr().err
    doc = json.loads(out.read_text())
    assert doc["estimators"] == ["eskf", "vqf online"]
    printed = capsys.readouterr().out
    assert "vqf online" in printed
    by_log = {entry["file"]: entry["estimators"]["vqf online"]["total_deg"]
              for entry in doc["per_log"]}
    assert by_log[str(logs[0])] == pytest.approx(1.986, abs=0.01)  # as the single-log run


def test_against_the_smoothed_attitude_too_when_the_log_has_no_truth(data_dir, tmp_path,
                                                                     capsys):
    path = data_dir / "logs" / "pyulog_sample_px4_events.ulg"
    doc = replay_json(capsys, tmp_path, str(path), "-e", "eskf", "--smooth", "--compare",
                      "vqf")
    assert doc["reference"] == "autopilot"
    assert "vqf online" in doc["estimators"]
    assert "vqf online" in doc["vs_smoothed"]["estimators"]
