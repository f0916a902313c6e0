"""MQTT settings a user can get wrong are refused at start, with one line naming the
option and the value (exit 2), never accepted and then retried forever, ignored, or
silently replaced: an empty URL, port 0 or out of range, a host that does not resolve,
TLS files without TLS (credentials would go in plaintext), TLS files that do not load,
a topic prefix no broker would accept."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest

from bridge.app.cli import main
from bridge.app.config import BridgeConfig
from bridge.publish import mqtt as mqtt_module
from bridge.publish.mqtt import (
    MAX_PREFIX_BYTES,
    MqttPublisher,
    MqttSettings,
    check_topic_prefix,
    orphan_options,
)

OPENSSL = shutil.which("openssl")


def refused(capsys, argv: list[str], *expected: str) -> str:
    """Run ``attitude-bridge run ARGV`` (1 s at most, should it start after all) and
    check it answers with exit 2 and one ``error:`` line containing ``expected``."""
    code = main(["run", "--estimator", "quaternion", "--duration", "1", *argv])
    err = capsys.readouterr().err
    assert code == 2, (argv, code, err)
    assert "Traceback" not in err and err.count("\n") == 1, (argv, err)
    assert err.startswith("attitude-bridge run: error: "), (argv, err)
    for text in expected:
        assert text in err, (argv, text, err)
    return err


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> dict[str, Path]:
    """A self-signed CA-ish certificate with its key, a second key that does not match
    it, and an encrypted key (openssl, as a user would make them)."""
    if OPENSSL is None:
        pytest.skip("openssl not installed")
    d = tmp_path_factory.mktemp("pki")
    files = {"cert": d / "cert.pem", "key": d / "key.pem", "other_key": d / "other.pem",
             "encrypted_key": d / "encrypted.pem"}
    subprocess.run([OPENSSL, "req", "-x509", "-newkey", "ec", "-pkeyopt",
                    "ec_paramgen_curve:prime256v1", "-nodes", "-subj", "/CN=127.0.0.1",
                    "-days", "2", "-keyout", str(files["key"]), "-out", str(files["cert"])],
                   check=True, capture_output=True)
    subprocess.run([OPENSSL, "genpkey", "-algorithm", "ec", "-pkeyopt",
                    "ec_paramgen_curve:prime256v1", "-out", str(files["other_key"])],
                   check=True, capture_output=True)
    subprocess.run([OPENSSL, "pkey", "-in", str(files["key"]), "-aes256", "-passout",
                    "pass:secret", "-out", str(files["encrypted_key"])],
                   check=True, capture_output=True)
    return files


# --- 23: an empty URL -------------------------------------------------------------

def test_empty_mqtt_url_is_refused_not_silently_no_mqtt(capsys):
    refused(capsys, ["--mqtt", ""], "--mqtt ''", "empty")
    with pytest.raises(ValueError, match="--mqtt '   '"):
        BridgeConfig(mqtt="   ").validate()
    BridgeConfig(mqtt=None).validate()  # not given: no MQTT, fine


# --- 10: ports -----------------------------------------------------------------------

def test_port_zero_and_out_of_range_ports_are_refused_naming_mqtt_and_the_url(capsys):
    refused(capsys, ["--mqtt", "mqtt://127.0.0.1:0"], "--mqtt", "mqtt://127.0.0.1:0",
            "1..65535")
    refused(capsys, ["--mqtt", "mqtt://127.0.0.1:99999"], "--mqtt",
            "mqtt://127.0.0.1:99999", "1..65535")
    refused(capsys, ["--mqtt", "mqtt://127.0.0.1:http"], "--mqtt", "mqtt://127.0.0.1:http",
            "1..65535")
    BridgeConfig(mqtt="mqtt://127.0.0.1:65535").validate()
    BridgeConfig(mqtt="mqtt://127.0.0.1").validate()  # the default port


def test_a_password_in_a_bad_url_is_not_echoed(capsys):
    err = refused(capsys, ["--mqtt", "mqtt://user:hunter2@127.0.0.1:0"], "--mqtt", "user")
    assert "hunter2" not in err


def test_a_path_in_the_url_is_refused_it_would_be_ignored(capsys):
    refused(capsys, ["--mqtt", "mqtt://127.0.0.1:1883/drones"], "--mqtt",
            "mqtt://127.0.0.1:1883/drones", "mqtt-prefix")
    BridgeConfig(mqtt="mqtt://127.0.0.1:1883/").validate()


# --- 21: a host that does not resolve ----------------------------------------------

def test_unresolvable_broker_host_is_refused_at_start(capsys):
    refused(capsys, ["--mqtt", "mqtt://nonexistent.invalid:1883"], "--mqtt",
            "cannot resolve host 'nonexistent.invalid'")
    BridgeConfig(mqtt="mqtt://localhost:1883").validate()
    BridgeConfig(mqtt="mqtt://[::1]:1883").validate()


def test_a_resolver_that_cannot_answer_now_does_not_stop_the_start(monkeypatch):
    """A temporary failure (no network yet at boot) or a resolver that hangs is not a
    typo: the bridge starts, and keeps trying (and warning) at run time."""
    def temporary(*args, **kwargs):
        raise socket.gaierror(socket.EAI_AGAIN, "Temporary failure in name resolution")

    monkeypatch.setattr(mqtt_module.socket, "getaddrinfo", temporary)
    BridgeConfig(mqtt="mqtt://broker.example:1883").validate()

    release = threading.Event()

    def hanging(*args, **kwargs):
        release.wait(30.0)
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")

    monkeypatch.setattr(mqtt_module.socket, "getaddrinfo", hanging)
    monkeypatch.setattr(mqtt_module, "RESOLVE_TIMEOUT_S", 0.3)
    start = time.monotonic()
    try:
        BridgeConfig(mqtt="mqtt://broker.example:1883").validate()
    finally:
        release.set()
    assert time.monotonic() - start < 2.0


# --- 8: TLS files without TLS --------------------------------------------------------

def test_tls_files_without_tls_are_refused_not_ignored(capsys, pki):
    refused(capsys, ["--mqtt", "mqtt://127.0.0.1:1883", "--mqtt-ca", "/nonexistent.pem",
                     "--mqtt-cert", "/nonexistent"],
            "--mqtt-ca /nonexistent.pem", "mqtts://", "--mqtt-tls")
    refused(capsys, ["--mqtt", "mqtt://127.0.0.1:1883", "--mqtt-cert", str(pki["cert"]),
                     "--mqtt-key", str(pki["key"])], f"--mqtt-cert {pki['cert']}", "plaintext")
    # With TLS, the same files are fine (mqtts:// or --mqtt-tls).
    BridgeConfig(mqtt="mqtts://127.0.0.1", mqtt_ca=str(pki["cert"])).validate()
    BridgeConfig(mqtt="mqtt://127.0.0.1:8883", mqtt_tls=True, mqtt_ca=str(pki["cert"]),
                 mqtt_cert=str(pki["cert"]), mqtt_key=str(pki["key"])).validate()


def test_mqtt_credentials_or_tls_without_mqtt_are_told_at_the_default_level(caplog, pki):
    """Without --mqtt these options did nothing, and nothing said so: the bridge ran
    without publishing. A warning, not a refusal (an environment file with the broker's
    credentials is kept while MQTT is off)."""
    caplog.set_level(logging.WARNING)
    code = main(["run", "--connect", "udpin:127.0.0.1:0", "--estimator", "quaternion",
                 "--duration", "0.3", "--mqtt-tls", "--mqtt-ca", str(pki["cert"]),
                 "--mqtt-password", "s3cret"])
    assert code == 0
    told = [r.getMessage() for r in caplog.records if "without --mqtt" in r.getMessage()]
    assert told == ["--mqtt-password, --mqtt-tls, --mqtt-ca given without --mqtt: ignored, "
                    "nothing is published over MQTT"], told
    assert all("s3cret" not in r.getMessage() for r in caplog.records)
    assert orphan_options(BridgeConfig(mqtt="mqtt://127.0.0.1", mqtt_username="b")) == []
    assert orphan_options(BridgeConfig(mqtt_rate=2.0, mqtt_prefix="drones")) == []


# --- 9: TLS files that do not load ----------------------------------------------------

def test_missing_or_invalid_ca_is_refused_naming_the_file(capsys, tmp_path):
    garbage = tmp_path / "garbage.pem"
    garbage.write_text("-----BEGIN CERTIFICATE-----\nnot base64 at all\n"
                       "-----END CERTIFICATE-----\n")
    for ca in ("/nonexistent.pem", str(tmp_path), str(garbage)):
        refused(capsys, ["--mqtt", "mqtt://127.0.0.1:8883", "--mqtt-tls", "--mqtt-ca", ca],
                f"--mqtt-ca {ca}")
    refused(capsys, ["--mqtt", "mqtts://127.0.0.1", "--mqtt-ca", ""], "--mqtt-ca ''", "empty")


def test_missing_invalid_or_mismatched_client_cert_and_key_are_refused(capsys, pki, tmp_path):
    url = ["--mqtt", "mqtts://127.0.0.1"]
    refused(capsys, [*url, "--mqtt-cert", "/nonexistent"], "--mqtt-cert /nonexistent")
    refused(capsys, [*url, "--mqtt-cert", str(pki["cert"]), "--mqtt-key", "/nonexistent"],
            "--mqtt-key /nonexistent")
    refused(capsys, [*url, "--mqtt-cert", str(tmp_path / "nothing.pem")],
            f"--mqtt-cert {tmp_path / 'nothing.pem'}")
    # a certificate without its key, and a key that is not the certificate's
    refused(capsys, [*url, "--mqtt-cert", str(pki["cert"])], f"--mqtt-cert {pki['cert']}")
    refused(capsys, [*url, "--mqtt-cert", str(pki["cert"]), "--mqtt-key",
                     str(pki["other_key"])], f"--mqtt-key {pki['other_key']}")


def test_key_without_cert_is_refused(capsys, pki):
    refused(capsys, ["--mqtt", "mqtts://127.0.0.1", "--mqtt-key", str(pki["key"])],
            f"--mqtt-key {pki['key']}", "--mqtt-cert")


def test_an_encrypted_key_is_refused_without_asking_for_a_passphrase(capsys, pki):
    """OpenSSL would prompt on the terminal (a service has none; a prompt at every
    reconnect would block the event loop): refused, saying why."""
    refused(capsys, ["--mqtt", "mqtts://127.0.0.1", "--mqtt-cert", str(pki["cert"]),
                     "--mqtt-key", str(pki["encrypted_key"])],
            f"--mqtt-key {pki['encrypted_key']}", "encrypted")


# --- 11: topic prefix -------------------------------------------------------------------

def test_wildcard_prefix_in_a_settings_file_is_refused(capsys, tmp_path):
    for prefix in ("#", "a/+/b"):
        path = tmp_path / "bridge.toml"
        path.write_text(f'mqtt-prefix = "{prefix}"\nmqtt = "mqtt://127.0.0.1:1883"\n')
        refused(capsys, ["--config", str(path)], f"mqtt-prefix {prefix!r}", "wildcard")


@pytest.mark.parametrize("prefix, why", [
    ("", "empty"), ("$SYS/attitude", "'$'"), ("a\0b", "NUL"), ("a\x07b", "control"),
    ("/attitude", "empty level"), ("attitude/", "empty level"), ("a//b", "empty level"),
    ("x" * (MAX_PREFIX_BYTES + 1), f"{MAX_PREFIX_BYTES} bytes"),
    ("é" * (MAX_PREFIX_BYTES // 2 + 1), f"{MAX_PREFIX_BYTES} bytes"),  # bytes, not chars
])
def test_bad_topic_prefixes_are_refused(prefix, why):
    with pytest.raises(ValueError, match="mqtt-prefix") as exc:
        BridgeConfig(mqtt="mqtt://127.0.0.1:1883", mqtt_prefix=prefix).validate()
    assert why in str(exc.value) and "\n" not in str(exc.value)


def test_ordinary_topic_prefixes_are_accepted():
    for prefix in ("attitude", "fleet/north field/attitude", "x" * MAX_PREFIX_BYTES,
                   "Flughöhe"):
        check_topic_prefix(prefix)


def test_a_key_that_became_encrypted_after_the_start_is_retried_not_fatal(pki, caplog):
    """The publisher builds its TLS context at every connection attempt (a renewed
    certificate is picked up): a key that needs a passphrase by then is reported and
    retried like a missing file, never a terminal prompt, never the end of the task."""
    async def scenario() -> tuple[bool, MqttPublisher]:
        publisher = MqttPublisher(MqttSettings(
            "127.0.0.1", 1, tls=True, cert_file=str(pki["cert"]),
            key_file=str(pki["encrypted_key"])))
        task = asyncio.create_task(publisher.run())
        await asyncio.sleep(0.6)  # the first attempt and a retry (backoff from 0.25 s)
        alive = not task.done()
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        return alive, publisher

    caplog.set_level(logging.WARNING, logger="bridge.publish.mqtt")
    alive, publisher = asyncio.run(scenario())
    assert alive and publisher.stats.errors >= 2
    assert "encrypted" in publisher.stats.last_error
    assert any("encrypted" in r.getMessage() for r in caplog.records)
