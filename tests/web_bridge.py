"""The bridge as a user starts it with the web view, ``attitude-bridge run --web
127.0.0.1:0`` (the built-in emulator as the source), in a subprocess, watched through
its status file."""

from __future__ import annotations

import functools
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path


class WebBridge:
    """One bridge process; ``args`` are its estimators and any other options."""

    def __init__(self, folder: Path, *args: str, env: dict[str, str] | None = None) -> None:
        self.status_path = folder / "status.json"
        self.log_path = folder / "log"
        cmd = [sys.executable, "-m", "bridge.app.cli", "run", "--web", "127.0.0.1:0",
               "--status-file", str(self.status_path), *args]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL,
                                     stderr=self.log_path.open("w"),
                                     env={**os.environ, "PYTHONUNBUFFERED": "1",
                                          **(env or {})})

    def status(self) -> dict:
        try:
            return json.loads(self.status_path.read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return {}

    def wait_for(self, pred: Callable[[dict], object], timeout: float, what: str) -> dict:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            st = self.status()
            if st and pred(st):
                return st
            if self.proc.poll() is not None:
                break
            time.sleep(0.1)
        raise AssertionError(f"no {what} within {timeout} s; log:\n{self.log()}")

    @property
    def web(self) -> dict:
        return self.status()["connection"]["web"]

    @functools.cached_property
    def address(self) -> tuple[str, int]:
        """(host, port) of the web view, waited for once it serves."""
        st = self.wait_for(lambda s: s.get("connection", {}).get("web", {}).get("url"),
                           60, "web view")
        host, port = st["connection"]["web"]["url"].removeprefix("http://").rstrip(
            "/").split(":")
        return host, int(port)

    @property
    def host(self) -> str:
        return self.address[0]

    @property
    def port(self) -> int:
        return self.address[1]

    def connect(self) -> socket.socket:
        return socket.create_connection(self.address, timeout=5)

    def log(self) -> str:
        return self.log_path.read_text()[-3000:]

    def stop(self) -> int:
        self.proc.send_signal(signal.SIGINT)
        return self.proc.wait(timeout=20)
