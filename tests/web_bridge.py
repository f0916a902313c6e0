"""The bridge as a user starts it with the web view, ``attitude-bridge run --web
127.0.0.1:0`` (the built-in emulator as the source), in a subprocess, watched through
its status file (``sitl_support.BridgeProcess``)."""

from __future__ import annotations

import functools
import socket
from dataclasses import dataclass
from pathlib import Path

from sitl_support import BridgeProcess


@dataclass
class WebBridge(BridgeProcess):
    """One bridge process serving its web view on a free port."""

    @classmethod
    def serving(cls, folder: Path, *args: str, env: dict[str, str] | None = None
                ) -> WebBridge:
        """``args``: its estimators and any other options."""
        return cls.run(folder, "--web", "127.0.0.1:0", *args, env=env)

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
