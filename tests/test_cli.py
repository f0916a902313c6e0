"""The command line as a user meets it: every sub-command given bad input answers with
one line and exit code 2, never a traceback; settings by option name from TOML files
and the environment; degrees at the user surface."""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bridge.app.cli import main
from bridge.app.config import BridgeConfig, check_rotation
from bridge.app.run_cli import config_from_args
from estimators.spec import EstimatorSpec

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def busy_port():
    """A UDP port on 127.0.0.1 that another socket holds."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        yield s.getsockname()[1]


def bad_inputs(tmp: Path, busy: int) -> list[tuple[list[str], str]]:
    """(argv, what the one-line error must mention), for every sub-command."""
    bad_toml = tmp / "bad.toml"
    bad_toml.write_text("estimator = [\n")
    typo = tmp / "typo.toml"
    typo.write_text('conect = "udpin:0.0.0.0:14550"\n')
    key_file = tmp / "key"
    key_file.write_text("a" * 64 + "\n")
    huge_window = tmp / "window.toml"  # was a MemoryError per sample (18 TiB), exit 0
    huge_window.write_text("window-s = 1e9\n")
    log = tmp / "log.csv"
    log.write_text("not,a,log\n")
    return [
        (["run", "--out", "udpout:nohost.invalid:14550"], "cannot resolve host"),
        (["run", "--connect", f"udpin:127.0.0.1:{busy}"], "already in use"),
        (["run", "--connect", "udpin:192.0.2.1:14550"], "not on this machine"),
        (["run", "--signing-key", "env:ATTITUDE_BRIDGE_TEST_NO_SUCH_VARIABLE"], "not set"),
        # read whole, /dev/zero filled 10 GB of memory; '' silently turned signing off
        (["run", "--connect", "udpin:127.0.0.1:0", "--signing-key", "file:/dev/zero"],
         "longer than 4096 bytes"),
        (["run", "--connect", "udpin:127.0.0.1:0", "--signing-key", ""],
         "an empty --signing-key"),
        (["run", "--signing-key", str(key_file)], "with the built-in emulator"),
        # accepted silently: the user meant to sign and nothing was signed or checked
        (["run", "--connect", "udpin:127.0.0.1:0", "--allow-unsigned"],
         "--allow-unsigned without --signing-key"),
        (["run", "--config", str(tmp / "missing.toml")], "does not exist"),
        (["run", "--config", str(bad_toml)], f"{bad_toml} is not valid TOML"),
        (["run", "--config", str(typo)], "unknown setting 'conect'"),
        (["run", "--config", str(huge_window)], "'window_s' must be within 0.1..600"),
        (["run", "--rotation", "YAW_91"], "unknown rotation 'YAW_91'"),
        (["run", "--estimator", "mahony:kp=fast"], "kp"),
        (["run", "--estimator", "eskf:declination_deg=400"], "declination"),
        (["run", "--imu-rate", "-1"], "imu_rate"),
        (["run", "--component-id", "1"], "is the autopilot's"),  # served nothing, silently
        (["run", "--mqtt", "http://broker"], "MQTT URL"),
        (["run", "--record", str(tmp / "no" / "session.tlog")], "does not exist"),
        # the status, rewritten every second, would have replaced the recording
        (["run", "--record", str(tmp / "same"), "--status-file", str(tmp / "same")],
         "also given to --record"),
        (["demo", "--duration", "0"], "duration must be more than 0"),
        (["demo", "--duration", "1e8"], "at most 3.1536e+07 s"),  # was 64 MB/s, no start
        (["run", "--imu-rate", "1e-300"], "'imu_rate' must be within 1..10000"),  # traceback
        (["run", "--accel-range", "0.5"], "'accel_range_g' must be within 2.."),  # all refused
        (["run", "--gyro-range", "1e-300"], "'gyro_range_dps' must be within 100.."),
        (["demo", "--profile", "wobble"], "unknown profile 'wobble'"),
        (["demo", "--imu-rate", "1e9"], "'imu_rate' must be within 1..10000"),
        (["run", "--connect", ""], "bad connection URL ''"),
        # a folder that exists but takes no file (access() says writable): before any work
        (["hil", "--target", "udp:127.0.0.1:9", "--duration", "5", "--stats-json",
          "/proc/stats.json"], "cannot be written"),
        (["replay", str(log), "--json", "/proc/r.json"], "cannot be written"),
        (["demo", "--seed", "-5"], "seed must not be negative"),
        (["hil", "--target", "udp:127.0.0.1:9", "--clock-drift-ppm", "nan"], "clock drift"),
        (["hil", "--target", "udp:127.0.0.1:9", "--clock-drift-ppm", "1e9"], "clock drift"),
        (["estimators", "foo"], "unknown estimator 'foo'"),
        (["hil", "--target", "udp:127.0.0.1:9", "--profile", "wobble"], "unknown profile"),
        (["hil", "--target", "nowhere"], "udp:HOST:PORT"),
        (["replay", str(tmp / "missing.tlog")], "missing.tlog"),
        (["replay", str(log), "--report", str(tmp / "no" / "r.html")], "does not exist"),
        (["tune", str(tmp / "missing.tlog"), "-e", "mahony", "-p", "kp=0.1:1:3"],
         "missing.tlog"),
        (["calibrate", "-o", str(tmp / "c.toml")], "no LOG files"),
        (["calibrate", "--emulator", "-o", str(tmp / "c.toml"), "--rotation", "YAW_91"],
         "unknown rotation"),
        (["warmup", "foo"], "unknown estimator 'foo'"),
    ]


def test_every_subcommand_answers_bad_input_with_one_line(tmp_path, busy_port, capsys):
    for argv, expected in bad_inputs(tmp_path, busy_port):
        code = main(argv)
        err = capsys.readouterr().err
        assert code == 2, (argv, code, err)
        assert "Traceback" not in err and err.count("\n") == 1, (argv, err)
        assert err.startswith(f"attitude-bridge {argv[0]}: error: "), (argv, err)
        assert expected in err, (argv, err)


def test_option_errors_are_argparse_usage_never_a_traceback(capsys):
    for argv in (["run", "--imu-rate", "fast"], ["bogus"], ["replay"],
                 ["run", "--board", "pixhawk"]):
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and "Traceback" not in err and "error:" in err
        assert err.count("\n") == 1 and "--help" in err  # one line, not the whole usage


def test_durations_must_be_finite_and_not_negative(tmp_path, capsys):
    """`float` takes nan, inf and -5: `hil --duration nan` streamed for ever and `health
    --max-age nan` called a stale file fresh. Every duration option refuses them in one
    line, exit 2 (hil also as a real process: there the old code never ended)."""
    stale = tmp_path / "status.json"
    stale.write_text('{"time_unix": 0}')
    for argv in (["run", "--duration", "nan"], ["demo", "--duration", "-1"],
                 ["hil", "--target", "udp:127.0.0.1:9", "--duration", "inf"],
                 ["health", "--status-file", str(stale), "--max-age", "nan"]):
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and err.count("\n") == 1, (argv, err)
        assert err.startswith(f"attitude-bridge {argv[0]}: error: argument {argv[-2]}: must "
                              f"be a finite number of seconds >= 0, got '{argv[-1]}'"), err
    procs = [subprocess.Popen([sys.executable, "-m", "bridge.app.cli", "hil", "--target",
                               "udp:127.0.0.1:9", "--fast", "--duration", value],
                              cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              text=True) for value in ("nan", "-5")]
    try:
        errs = [p.communicate(timeout=30)[1] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    assert [p.returncode for p in procs] == [2, 2], errs
    assert all(e.count("\n") == 1 and "argument --duration" in e for e in errs), errs


def test_health_without_a_running_bridge_is_unhealthy_in_one_line(tmp_path, capsys):
    assert main(["health", "--status-file", str(tmp_path / "status.json")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("unhealthy: no status file")


def test_version_and_the_entry_point():
    """The real entry point, in a process: --version on one line."""
    out = subprocess.run([sys.executable, "-m", "bridge.app.cli", "--version"], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stderr == ""
    assert out.stdout.startswith("attitude-bridge ") and out.stdout.count("\n") == 1
    assert "numba" in out.stdout and "pymavlink" in out.stdout


def test_rotations_are_the_autopilots_names():
    for name in ("NONE", "YAW_90", "ROTATION_ROLL_180_YAW_90", "MAV_SENSOR_ROTATION_PITCH_270",
                 "ROLL_90_PITCH_68_YAW_293", "roll_45"):
        check_rotation(name)
    for bad in ("YAW_91", "ROLL_10", "YAW", "SPIN_90"):
        with pytest.raises(ValueError, match="unknown rotation"):
            check_rotation(bad)


def test_angle_parameters_in_degrees_at_the_user_surface():
    spec = EstimatorSpec.parse("eskf:declination_deg=3.5,bias_max_dps=20,tilt_init=0.2")
    assert spec.params["declination"] == pytest.approx(math.radians(3.5))
    assert spec.params["bias_max"] == pytest.approx(math.radians(20.0))
    assert spec.params["tilt_init"] == 0.2  # the library's own name stays radians
    assert spec.label == "eskf:declination_deg=3.5,bias_max_dps=20,tilt_init_deg=11.4592"
    assert spec.user_params()["declination_deg"] == pytest.approx(3.5)
    for bad, message in (("eskf:declination_deg=1,declination=0.1", "twice"),
                         ("mahony:kp_deg=3", "unknown parameter 'kp_deg'"),
                         ("madgwick:beta_dps=fast", "number of degrees")):
        with pytest.raises(ValueError, match=message):
            EstimatorSpec.parse(bad)
    est = spec.create(100.0)
    assert est.params.declination == pytest.approx(math.radians(3.5))


def test_estimators_listing_shows_degrees(capsys):
    assert main(["estimators", "eskf"]) == 0
    out = capsys.readouterr().out
    assert "declination_deg = 0; magnetic declination [deg]" in out
    assert "bias_max_dps = 20 (0.0572958..inf); " in out and "[deg/s]" in out
    assert "\n    declination = " not in out


def parse(argv: list[str]):
    from bridge.app.cli import build_parser

    return build_parser().parse_args(argv)


def test_e_is_short_for_estimator_on_every_command_that_takes_it():
    """The README writes `-e NAME:k=v`; every command with --estimator takes it."""
    from bridge.app.cli import build_parser

    commands = build_parser()._subparsers._group_actions[0].choices
    options = {name: next((a.option_strings for a in p._actions
                           if "--estimator" in a.option_strings), None)
               for name, p in commands.items()}
    takers = {name for name, strings in options.items() if strings}
    assert {"run", "demo", "replay", "tune"} <= takers
    assert all("-e" in options[name] for name in takers), options
    for command in ("run", "demo"):
        args = parse([command, "-e", "eskf:declination_deg=3.5", "-e", "mahony"])
        cfg = config_from_args(args, demo=command == "demo", environ={})
        cfg.validate()
        assert cfg.estimators == ["eskf:declination_deg=3.5", "mahony"]


def test_every_relative_path_in_a_settings_file_is_relative_to_that_file(tmp_path,
                                                                       monkeypatch):
    """Only the calibration was: a service started from / with ``record = "s.tlog"``
    tried to write /s.tlog, and its TLS files were looked for in the wrong folder."""
    folder = tmp_path / "etc"
    folder.mkdir()
    path = folder / "bridge.toml"
    path.write_text('record = "logs/s.tlog"\nstatus-file = "status.json"\n'
                    'mqtt-ca = "ca.pem"\nmqtt-cert = "/abs/cert.pem"\n'
                    'mqtt-key = "~/key.pem"\nsigning-key = "file:key.txt"\n'
                    'calibration = "cal.toml"\n')
    monkeypatch.chdir(tmp_path)
    cfg = config_from_args(parse(["run", "--config", str(path)]), demo=False, environ={})
    assert (cfg.record, cfg.status_file, cfg.mqtt_ca, cfg.calibration) == (
        str(folder / "logs" / "s.tlog"), str(folder / "status.json"), str(folder / "ca.pem"),
        str(folder / "cal.toml"))
    assert cfg.mqtt_cert == "/abs/cert.pem"
    assert cfg.mqtt_key == str(Path("~/key.pem").expanduser())
    assert cfg.signing_key == "file:" + str(folder / "key.txt")
    path.write_text('signing-key = "env:BRIDGE_KEY"\n')
    cfg = config_from_args(parse(["run", "--config", str(path)]), demo=False, environ={})
    assert cfg.signing_key == "env:BRIDGE_KEY"
    # on the command line a relative path stays relative to the working folder
    cfg = config_from_args(parse(["run", "--config", str(path), "--record", "here.tlog"]),
                           demo=False, environ={})
    assert cfg.record == "here.tlog"


def test_settings_file_takes_option_names_and_the_environment_overrides_it(tmp_path):
    path = tmp_path / "bridge.toml"
    path.write_text('connect = "udpin:0.0.0.0:14550"\nestimator = ["mahony", "eskf"]\n'
                    'out = "udpout:127.0.0.1:14551"\npeer-timeout = 20\nno-aiding = true\n'
                    'declination-deg = 2.5\nout_rate = 20\nwindow_s = 5.0\n')
    env = {"ATTITUDE_BRIDGE_OUT_RATE": "25", "ATTITUDE_BRIDGE_MQTT_PASSWORD": "s3cret",
           "ATTITUDE_BRIDGE_VEHICLE": "1 2", "ATTITUDE_BRIDGE_DATA": "/elsewhere"}
    cfg = config_from_args(parse(["run", "--config", str(path), "--imu-rate", "500"]),
                           demo=False, environ=env)
    cfg.validate()
    assert cfg.estimators == ["mahony", "eskf"] and cfg.outs == ["udpout:127.0.0.1:14551"]
    assert (cfg.peer_timeout_s, cfg.aiding, cfg.declination_deg, cfg.window_s) == (
        20.0, False, 2.5, 5.0)
    assert (cfg.out_rate, cfg.mqtt_password, cfg.vehicles, cfg.imu_rate) == (
        25.0, "s3cret", [1, 2], 500.0)
    # The file by environment; options over the environment.
    env2 = {"ATTITUDE_BRIDGE_CONFIG": str(path), "ATTITUDE_BRIDGE_NO_AIDING": "false"}
    cfg2 = config_from_args(parse(["run", "--out-rate", "5"]), demo=False, environ=env2)
    assert cfg2.aiding is True and cfg2.out_rate == 5.0 and cfg2.peer_timeout_s == 20.0
    with pytest.raises(ValueError, match="ATTITUDE_BRIDGE_OUT_RTAE: unknown setting"):
        config_from_args(parse(["run"]), demo=False, environ={"ATTITUDE_BRIDGE_OUT_RTAE": "1"})
    with pytest.raises(ValueError, match="ATTITUDE_BRIDGE_TABLE: expected true or false"):
        config_from_args(parse(["run"]), demo=False, environ={"ATTITUDE_BRIDGE_TABLE": "maybe"})


def test_every_run_option_is_a_setting_name():
    """Option names and settings cannot drift apart: each option of `run` is accepted
    as a TOML key and lands on a field."""
    from bridge.app.cli import build_parser

    run = build_parser()._subparsers._group_actions[0].choices["run"]
    for action in run._actions:
        long = [o for o in action.option_strings if o.startswith("--")]
        if not long or action.dest in ("help", "config", "verbose", "quiet"):
            continue
        for option in long:
            field, _ = BridgeConfig.field_of(option)
            assert field == action.dest, (option, field, action.dest)


def test_example_settings_file_loads(tmp_path):
    cfg = BridgeConfig.from_toml(REPO / "examples" / "bridge.toml")
    cfg.validate()
    assert cfg.connect and cfg.estimators[0] == "eskf" and cfg.mqtt


def readme_commands() -> list[str]:
    """Every concrete `attitude-bridge ...` command in the README's code blocks (the
    synopsis lines, with [optional] parts or placeholders, are not commands)."""
    import re

    text = (REPO / "README.md").read_text(encoding="utf-8")
    found = []
    for block in re.findall(r"```[a-z]*\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split("  #")[0].split("&&")[-1].strip()
            if line.startswith("attitude-bridge ") and not any(
                    c in line for c in ("[", "|", "...")):
                found.append(line)
    return found


def test_readme_commands_are_valid(tmp_path, monkeypatch):
    """The README's commands parse with the real parser, and those of the bridge make
    settings that pass validation (in a folder with the files they name)."""
    import shlex

    from bridge.app.cli import build_parser
    from imu.calibration import SensorCalibration

    (tmp_path / "examples").mkdir()
    (tmp_path / "examples" / "bridge.toml").write_text(
        (REPO / "examples" / "bridge.toml").read_text())
    SensorCalibration().save(tmp_path / "calib.toml", "identity")
    monkeypatch.chdir(tmp_path)
    commands = readme_commands()
    assert len(commands) >= 8, commands
    for command in commands:
        args = build_parser().parse_args(shlex.split(command)[1:])
        if args.command in ("run", "demo"):
            config_from_args(args, demo=args.command == "demo", environ={}).validate()


@pytest.mark.parametrize("time_unix, why", [
    ("1e308", "in the future"), ("NaN", "is not a time"), ('"now"', "unreadable")])
def test_health_refuses_a_status_file_from_the_future_or_without_a_time(tmp_path, capsys,
                                                                        time_unix, why):
    """An hour-ahead file said 'healthy: updated -3517.0 s ago', a NaN one 'nan s ago'."""
    status = tmp_path / "status.json"
    status.write_text(f'{{"time_unix": {time_unix}, "vehicles": {{}}}}')
    assert main(["health", "--status-file", str(status)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("unhealthy: ") and why in err


def test_a_status_file_that_is_not_a_regular_file_is_refused(tmp_path, capsys):
    """The status file is replaced by a rename: `--status-file /dev/null` made /dev/null a
    regular file (as root). A FIFO stands in for the device here."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    assert main(["run", "--duration", "1", "--status-file", str(fifo)]) == 2
    err = capsys.readouterr().err
    assert "not a regular file" in err and err.count("\n") == 1
    assert fifo.is_fifo()


def test_each_command_is_registered_by_the_module_the_table_names():
    """``SUBCOMMANDS`` says which module to import for a command: it must be the one
    that registers it, and every command must be in it (else it is missing from
    ``--help``), in the order ``--help`` lists them."""
    import argparse
    import importlib

    from bridge.app.cli import SUBCOMMANDS, build_parser, command_in

    registered = {}
    for module in dict.fromkeys(SUBCOMMANDS.values()):
        sub = argparse.ArgumentParser().add_subparsers()
        importlib.import_module(module).register(sub)
        registered.update(dict.fromkeys(sub.choices, module))
    assert registered == SUBCOMMANDS
    assert list(build_parser()._subparsers._group_actions[0].choices) == list(SUBCOMMANDS)
    for command, module in SUBCOMMANDS.items():
        only = build_parser(command)._subparsers._group_actions[0].choices
        assert command in only and set(only) <= {c for c, m in SUBCOMMANDS.items()
                                                  if m == module}
    # top-level help lists every command, whatever follows it
    assert command_in(["replay", "x.tlog"]) == "replay"
    assert command_in(["-h", "replay"]) is None and command_in([]) is None


def test_health_check_loads_no_estimator_or_mavlink_code(tmp_path):
    """The container runs ``health`` every 30 s beside the bridge: it reads one JSON
    file, and must not import numpy, numba, pymavlink or the estimators to do it (most
    of a second of CPU each time when every command's module was imported)."""
    status = tmp_path / "status.json"
    status.write_text(json.dumps({"time_unix": time.time(), "vehicles": {}}))
    probe = ("import sys\n"
             "from bridge.app.cli import main\n"
             f"code = main(['health', '--status-file', {str(status)!r}])\n"
             "heavy = [m for m in ('numpy', 'numba', 'pymavlink', 'estimators')"
             " if m in sys.modules]\n"
             "print(code, heavy)\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=60)
    assert out.stdout.splitlines()[-1] == "0 []", out.stdout + out.stderr


def test_ctrl_c_while_the_commands_import_is_one_line(monkeypatch, capsys):
    """Ctrl-C in the first fraction of a second (the commands' modules importing) gave
    a traceback: it is 'interrupted' and exit 130 like any other moment."""
    import bridge.app.cli as cli

    def interrupted(command=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert cli.main(["run"]) == 130
    err = capsys.readouterr().err
    assert err == "attitude-bridge: interrupted\n"


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_a_cold_start_while_the_estimators_compile(tmp_path, sig):
    """The compilation runs inside the blocked event loop, whose handlers only wake the
    loop: Ctrl-C or a service manager's SIGTERM on a cold start (an empty numba cache)
    waited for the compiler, about a minute on this machine."""
    from bridge_support import free_udp_port

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cold-cache")}
    proc = subprocess.Popen(
        [sys.executable, "-m", "bridge.app.cli", "run", "--connect",
         f"udpin:127.0.0.1:{free_udp_port()}", "-e", "eskf"],
        stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = ""
        while "preparing estimators" not in line:
            char = proc.stderr.read(1)
            assert char, f"the bridge ended before compiling: {line}"
            line += char
        time.sleep(1.0)  # well inside the compilation
        sent = time.monotonic()
        proc.send_signal(sig)
        code = proc.wait(timeout=30)
        waited = time.monotonic() - sent
        err = proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert code == 130 and "attitude-bridge run: interrupted" in err, err
    assert "Traceback" not in err
    assert waited < 10.0, f"{waited:.1f} s after the signal"
