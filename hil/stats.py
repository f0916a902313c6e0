"""Counts of what the emulator sent and every fault it injected (printed at exit)."""

from __future__ import annotations

from dataclasses import dataclass, field

from .commands import Requests
from .faults import FaultCounts


@dataclass
class EmulatorStats:
    messages: dict[str, int] = field(default_factory=dict)  # packed, per MAVLink type
    datagrams_sent: int = 0  # after link faults, per target
    bytes_sent: int = 0
    send_errors: int = 0  # e.g. ICMP port unreachable from a vanished peer
    imu_samples: int = 0
    stream_time_s: float = 0.0  # true time covered by what was sent
    wall_time_s: float = 0.0
    faults: FaultCounts = field(default_factory=FaultCounts)
    requests: Requests = field(default_factory=Requests)  # commands read from the link

    def count_message(self, kind: str) -> None:
        self.messages[kind] = self.messages.get(kind, 0) + 1

    def to_dict(self) -> dict:
        return {
            "messages": dict(self.messages),
            "datagrams_sent": self.datagrams_sent,
            "bytes_sent": self.bytes_sent,
            "send_errors": self.send_errors,
            "imu_samples": self.imu_samples,
            "stream_time_s": self.stream_time_s,
            "wall_time_s": self.wall_time_s,
            "faults": self.faults.to_dict(),
            "requests": self.requests.to_dict(),
        }

    def summary(self) -> str:
        """Human-readable lines for the end of a CLI run."""
        msgs = ", ".join(f"{k} {v}" for k, v in sorted(self.messages.items()))
        faults = ", ".join(f"{k} {v}" for k, v in self.faults.to_dict().items() if v)
        asked = ", ".join(f"{k} {v}" for k, v in self.requests.to_dict().items() if v)
        return (f"sent {self.datagrams_sent} datagrams ({self.bytes_sent} bytes) in "
                f"{self.wall_time_s:.2f} s for {self.stream_time_s:.2f} s of stream; "
                f"send errors {self.send_errors}\n"
                f"messages: {msgs or 'none'}\nfaults injected: {faults or 'none'}\n"
                f"requests: {asked or 'none'}")
