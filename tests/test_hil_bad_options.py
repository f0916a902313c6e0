"""``hil`` given bad options: one line naming the option and exit 2; never an internal
error, a leaked numpy warning or garbage sent as "faults injected: none"."""

from __future__ import annotations

import contextlib
import io

import pytest
from cli_support import one_line_error, run_cli

from hil.board import MAX_BOARD_US, BoardClock
from hil.cli import parse_home

H = ["hil", "--target", "udp:127.0.0.1:14599", "--fast", "--duration", "0.5"]


def cli(argv: list[str]) -> tuple[int, str, str]:
    """A leaked numpy RuntimeWarning fails the test."""
    return run_cli(argv, warnings_as_errors=True)


@pytest.mark.parametrize("args, option", [
    (["--time-jump-s", "1e308"], "--time-jump-s"),
    (["--time-backwards-s", "1e308"], "--time-backwards-s"),
    (["--time-jump-rate-hz", "10", "--time-jump-s", "1e9"], "--time-jump-s"),
    (["--time-backwards-rate-hz", "1e6"], "--time-backwards-rate-hz"),
    (["--time-backwards-rate-hz", "1e308"], "--time-backwards-rate-hz"),
    (["--saturation-rate-hz", "10", "--saturation-duration-s", "1e308"],
     "--saturation-duration-s"),
    (["--stuck-rate-hz", "10", "--stuck-duration-s", "1e308"], "--stuck-duration-s"),
    (["--mag-disturbance-rate-hz", "10", "--mag-disturbance-duration-s", "1e308"],
     "--mag-disturbance-duration-s"),
    (["--vibration-g", "1e308"], "--vibration-g"),
    (["--vibration-dps", "1e308"], "--vibration-dps"),
    (["--gyro-bias-step-rate-hz", "10", "--gyro-bias-step-dps", "1e308"],
     "--gyro-bias-step-dps"),
    (["--mag-disturbance-rate-hz", "10", "--mag-disturbance-gauss", "1e308"],
     "--mag-disturbance-gauss"),
    (["--vibration-hz", "1e308"], "--vibration-hz"),
])
def test_fault_sizes_rates_and_durations_are_bounded(args, option):
    """Items 1 and 3: before, OverflowError/struct.error (exit 1), numpy overflow
    warnings (exit 0) or NaN packed into int16."""
    one_line_error(*cli(H + args)[::2], f"argument {option}:", "at most")


@pytest.mark.parametrize("home", ["0,0,1e308", "0,0,1e7", "0,0,-1000"])
def test_home_altitude_is_bounded(home):
    """Item 2: before, numpy warnings then an internal error (exit 1)."""
    one_line_error(*cli([*H, "--home", home])[::2], "--home", "altitude -500..11000 m")


def test_seed_must_be_non_negative():
    """Item 4: before, "error: expected non-negative integer" without the option."""
    one_line_error(*cli([*H, "--seed", "-1"])[::2],
                   "argument --seed: expected an integer >= 0, got '-1'")


def test_negative_home_is_a_value_not_an_option():
    """Item 5: before, argparse refused ``--home -33.9,151.2`` (expected one argument)."""
    import argparse

    from hil.cli import register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    for text in ("-33.9,151.2", "-33.9,-151.2,20", "-.5,1"):
        args = parser.parse_args(["hil", "--target", "udp:h:1", "--home", text])
        assert args.home == text
    env = parse_home("-33.9,151.2")
    assert (env.latitude_deg, env.longitude_deg) == (-33.9, 151.2)
    with contextlib.redirect_stderr(io.StringIO()), pytest.raises(SystemExit):
        parser.parse_args(["hil", "--target", "udp:h:1", "--home", "-x"])  # still an option


def test_extreme_clock_faults_stay_within_the_message_fields():
    """The largest allowed clock faults, one per sample, are held at the board clock's
    limits (0 .. uint32 ms) instead of packing garbage or failing."""
    clock = BoardClock(2.0, 0.0, 0.0, None)
    import numpy as np

    stamped = clock.stamp(np.array([0.0, 1.0]), np.array([-10**12, 10**15]))
    assert stamped.tolist() == [0, MAX_BOARD_US]
    for args in (["--time-jump-rate-hz", "1000", "--time-jump-s", "86400"],
                 ["--time-backwards-rate-hz", "1000", "--time-backwards-s", "86400"]):
        code, _, err = cli([*H[:-1], "0.05", *args])
        assert code == 0, err


def test_target_refusing_every_send_is_an_error():
    """Item 6: before, a broadcast target refused all 1051 sends and the run exited 0."""
    code, _, err = cli(["hil", "--fast", "--duration", "0.5",
                        "--target", "udp:255.255.255.255:14550"])
    lines = [line for line in err.splitlines() if "error" in line]
    assert code == 2 and len(lines) == 1, err
    assert "udp:255.255.255.255:14550" in lines[0] and "Errno" in lines[0], err


def test_non_finite_profile_row_is_named(tmp_path):
    """Item 7: before, "need at least 2 rows of finite numbers" for a file with 2."""
    path = tmp_path / "q.csv"
    path.write_text("time_s,qw,qx,qy,qz\n0,1,0,0,0\n1,nan,0,0,0\n2,1,0,0,0\n")
    one_line_error(*cli([*H, "--profile", f"file:{path}"])[::2], "line 3", "not a finite")
