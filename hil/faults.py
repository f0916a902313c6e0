"""Fault injection: what can go wrong on a real board and a real link, each one counted.

Three families, each with its own random stream (so turning one on never changes the
samples of another):

* link faults act on finished UDP datagrams, one fault at most per datagram: loss,
  duplication (sent twice), reordering (held back until after the next datagram that
  goes out unharmed), corrupted bytes
  (1-3 bytes changed after the 10-byte MAVLink 2 header, so the CRC catches them) and
  truncation (cut short at a random length);
* clock faults shift the board clock from one IMU sample on: a jump forward or a step
  backwards in time (every later timestamp carries the shift);
* sensor faults: saturation (one IMU axis pinned at the int16 limit for a while, e.g. a
  knock), stuck IMU (the board keeps re-sending the last gyro/accel/temperature
  reading), vibration (a sinusoid on accelerometer and gyro, all the time), magnetic
  disturbance (a magnet nearby: an extra field for a while) and gyro bias steps.

Rates are events per second of stream time; link faults are probabilities per datagram.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np

from .sensors.hmc5883l import LSB_PER_GAUSS, OUTPUT_MAX
from .sensors.mpu6050 import ACCEL_RANGE_G, GYRO_RANGE_DPS

#: Largest clock jump / step [s]. A glitch of more than a day is no glitch but another
#: clock; and the board's time also goes out as a uint32 millisecond time_boot_ms
#: (49.7 days), which a handful of day-long jumps already spans.
MAX_CLOCK_STEP_S = 86_400.0
#: Longest saturation / stuck / magnetic event [s]: an hour is already "broken sensor";
#: beyond a day the event outlasts any run.
MAX_EVENT_DURATION_S = 86_400.0
#: Largest sizes: the widest full scale of the emulated chips (MPU6050 ±16 g at
#: AFS_SEL 3, ±2000 °/s at FS_SEL 3; HMC5883L 2047 counts at 230 LSB/G, ~8.9 G). Beyond
#: it every reading is pinned at the limit whatever the size, so a larger value is a typo.
MAX_SIZE = {
    "vibration_g": ACCEL_RANGE_G[-1],
    "vibration_dps": GYRO_RANGE_DPS[-1],
    "gyro_bias_step_dps": GYRO_RANGE_DPS[-1],
    "mag_disturbance_gauss": round(OUTPUT_MAX / LSB_PER_GAUSS[-1], 1),
    "time_jump_s": MAX_CLOCK_STEP_S,
    "time_backwards_s": MAX_CLOCK_STEP_S,
    "saturation_duration_s": MAX_EVENT_DURATION_S,
    "stuck_duration_s": MAX_EVENT_DURATION_S,
    "mag_disturbance_duration_s": MAX_EVENT_DURATION_S,
}
#: Events per second; the emulator refuses any above the IMU rate (one per sample).
EVENT_RATES = ("time_jump_rate_hz", "time_backwards_rate_hz", "saturation_rate_hz",
               "stuck_rate_hz", "mag_disturbance_rate_hz", "gyro_bias_step_rate_hz")


class FaultSettingError(ValueError):
    """A fault setting out of range; ``setting`` is the field's name."""

    def __init__(self, setting: str, message: str):
        super().__init__(message)
        self.setting = setting


@dataclass(frozen=True)
class FaultConfig:
    # link: probability per datagram (at most one fault per datagram)
    loss: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    corrupt: float = 0.0
    truncate: float = 0.0
    # board clock: events per second, and their size
    time_jump_rate_hz: float = 0.0
    time_jump_s: float = 0.5
    time_backwards_rate_hz: float = 0.0
    time_backwards_s: float = 0.05
    # sensors
    saturation_rate_hz: float = 0.0
    saturation_duration_s: float = 0.02
    stuck_rate_hz: float = 0.0
    stuck_duration_s: float = 0.2
    vibration_g: float = 0.0  # accelerometer vibration amplitude [g]
    vibration_dps: float = 0.0  # gyro vibration amplitude [°/s]
    vibration_hz: float = 70.0
    mag_disturbance_rate_hz: float = 0.0
    mag_disturbance_gauss: float = 0.6
    mag_disturbance_duration_s: float = 1.0
    gyro_bias_step_rate_hz: float = 0.0
    gyro_bias_step_dps: float = 5.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not (math.isfinite(v) and v >= 0.0):
                raise FaultSettingError(
                    f.name, f"fault setting {f.name} must be finite and >= 0, got {v}")
            top = MAX_SIZE.get(f.name)
            if top is not None and v > top:
                raise FaultSettingError(
                    f.name, f"fault setting {f.name} must be at most {top:g}, got {v:g}")
        if self.link_total > 1.0:
            raise ValueError("link fault probabilities must add up to at most 1")

    @property
    def link_total(self) -> float:
        return self.loss + self.duplicate + self.reorder + self.corrupt + self.truncate


@dataclass
class FaultCounts:
    """Every injected fault, counted where it was injected."""

    lost: int = 0
    duplicated: int = 0
    reordered: int = 0
    corrupted: int = 0
    truncated: int = 0
    time_jumps: int = 0
    time_backwards: int = 0
    saturation_events: int = 0
    saturated_samples: int = 0  # IMU samples
    stuck_events: int = 0
    stuck_samples: int = 0
    vibration_samples: int = 0
    mag_disturbances: int = 0
    mag_disturbed_samples: int = 0  # magnetometer readings (15 Hz), not IMU samples
    gyro_bias_steps: int = 0

    def to_dict(self) -> dict[str, int]:
        return asdict(self)


# ---- link ------------------------------------------------------------------------

MAVLINK2_HEADER_LEN = 10


class LinkFaults:
    """Applies link faults to a stream of datagrams (state carries across calls)."""

    def __init__(self, config: FaultConfig, rng: np.random.Generator, counts: FaultCounts):
        self.config = config
        self.rng = rng
        self.counts = counts
        self._held: bytes | None = None  # a datagram waiting to be sent after the next
        c = config
        self._edges = np.cumsum([c.loss, c.duplicate, c.reorder, c.corrupt, c.truncate])

    def apply(self, datagram: bytes) -> list[bytes]:
        """The datagrams to put on the wire now, in order, for one input datagram."""
        if self.config.link_total == 0.0:
            return [datagram]
        kind = int(np.searchsorted(self._edges, self.rng.random(), side="right"))
        out: list[bytes]
        clean = False
        if kind == 0:
            self.counts.lost += 1
            out = []
        elif kind == 1:
            self.counts.duplicated += 1
            out = [datagram, datagram]
        elif kind == 2 and self._held is None:
            self.counts.reordered += 1
            self._held = datagram  # goes out right after the next datagram
            return []
        elif kind == 3 and len(datagram) > MAVLINK2_HEADER_LEN:
            self.counts.corrupted += 1
            out = [self._corrupt(datagram)]
        elif kind == 4 and len(datagram) > 1:
            self.counts.truncated += 1
            out = [datagram[: int(self.rng.integers(1, len(datagram)))]]
        else:
            out = [datagram]
            clean = True
        if clean and self._held is not None:
            # The held datagram follows the next clean one, so the swap is always
            # visible to a receiver (same sequence numbers, opposite order).
            out.append(self._held)
            self._held = None
        return out

    def flush(self) -> list[bytes]:
        """A still-held reordered datagram at the end of the stream."""
        held, self._held = self._held, None
        return [held] if held is not None else []

    def _corrupt(self, datagram: bytes) -> bytes:
        data = bytearray(datagram)
        n = int(self.rng.integers(1, 4))
        where = self.rng.choice(np.arange(MAVLINK2_HEADER_LEN, len(data)),
                                size=min(n, len(data) - MAVLINK2_HEADER_LEN), replace=False)
        for i in where:
            data[i] ^= int(self.rng.integers(1, 256))  # never a no-op
        return bytes(data)


# ---- clock -----------------------------------------------------------------------

class ClockFaults:
    """Random jumps of the board clock; ``offsets`` gives the shift at each IMU sample."""

    def __init__(self, config: FaultConfig, rng: np.random.Generator, counts: FaultCounts,
                 rate_hz: float):
        self.config = config
        self.rng = rng
        self.counts = counts
        self.rate_hz = rate_hz
        self.offset_us = 0
        self.events: list[tuple[float, int]] = []  # (true time, offset from then on)

    def offsets(self, t: np.ndarray) -> np.ndarray:
        """Clock shift [µs] for IMU samples at true times t (draws new events)."""
        c = self.config
        n = len(t)
        jumps = self.rng.random(n) < c.time_jump_rate_hz / self.rate_hz
        backs = self.rng.random(n) < c.time_backwards_rate_hz / self.rate_hz
        step = (jumps * round(c.time_jump_s * 1e6) - backs * round(c.time_backwards_s * 1e6))
        self.counts.time_jumps += int(jumps.sum())
        self.counts.time_backwards += int(backs.sum())
        out = self.offset_us + np.cumsum(step)
        for k in np.flatnonzero(step):
            self.events.append((float(t[k]), int(out[k])))
        self.offset_us = int(out[-1]) if n else self.offset_us
        return out.astype(np.int64)

    def offset_at(self, t: np.ndarray) -> np.ndarray:
        """Shift at other times (barometer, heartbeat), from the events drawn so far."""
        if not self.events:
            return np.zeros(len(t), dtype=np.int64)
        times = np.array([e[0] for e in self.events])
        values = np.array([0] + [e[1] for e in self.events], dtype=np.int64)
        return values[np.searchsorted(times, t, side="right")]


# ---- sensors ---------------------------------------------------------------------

class SensorFaults:
    """Sensor faults, drawn sample by sample; state carries across chunks."""

    def __init__(self, config: FaultConfig, rng: np.random.Generator, counts: FaultCounts,
                 imu_rate_hz: float, mag_rate_hz: float):
        self.config = config
        self.rng = rng
        self.counts = counts
        self.imu_rate_hz = imu_rate_hz
        self.mag_rate_hz = mag_rate_hz
        self._bias_dps = np.zeros(3)
        self._vibration_phase = rng.uniform(0.0, 2.0 * math.pi)
        axis = rng.normal(size=3)
        self._vibration_axis = axis / np.linalg.norm(axis)
        self._imu_event_left = 0  # samples left of a running saturation/stuck event
        self._imu_event: tuple[str, int, int, np.ndarray | None] | None = None
        self._mag_left = 0
        self._mag_vector = np.zeros(3)

    def physical(self, t: np.ndarray, fs: float) -> tuple[np.ndarray, np.ndarray]:
        """Additive (gyro °/s, accel g) in chip axes at internal-rate times t."""
        c = self.config
        n = len(t)
        steps = self.rng.random(n) < c.gyro_bias_step_rate_hz / fs
        axes = self.rng.integers(0, 3, n)
        signs = self.rng.choice([-1.0, 1.0], n)
        delta = np.zeros((n, 3))
        delta[np.flatnonzero(steps), axes[steps]] = signs[steps] * c.gyro_bias_step_dps
        self.counts.gyro_bias_steps += int(steps.sum())
        gyro = self._bias_dps + np.cumsum(delta, axis=0)
        if n:
            self._bias_dps = gyro[-1].copy()
        wave = np.sin(2.0 * math.pi * c.vibration_hz * t + self._vibration_phase)[:, None]
        accel = wave * c.vibration_g * self._vibration_axis
        gyro = gyro + wave * c.vibration_dps * self._vibration_axis[::-1]
        return gyro, accel

    def count_vibration(self, n_output: int) -> None:
        if self.config.vibration_g > 0.0 or self.config.vibration_dps > 0.0:
            self.counts.vibration_samples += n_output

    def imu_counts(self, gyro: np.ndarray, accel: np.ndarray, temp: np.ndarray,
                   last: tuple[np.ndarray, np.ndarray, int]) -> None:
        """Saturation and stuck events on the output counts, in place.

        ``last`` is the previous chunk's final (gyro, accel, temp) reading, which a stuck
        event starting on the first sample repeats.
        """
        c = self.config
        n = len(gyro)
        p_sat = c.saturation_rate_hz / self.imu_rate_hz
        p_stuck = c.stuck_rate_hz / self.imu_rate_hz
        draws = self.rng.random((n, 2))
        which = self.rng.integers(0, 2, n)  # 0 gyro, 1 accel
        axes = self.rng.integers(0, 3, n)
        signs = self.rng.integers(0, 2, n)
        if p_sat == 0.0 and p_stuck == 0.0 and self._imu_event_left == 0:
            return
        prev_g, prev_a, prev_t = last
        for k in range(n):
            if self._imu_event_left == 0:
                if draws[k, 0] < p_sat:
                    value = 32767 if signs[k] else -32768
                    self._imu_event = ("saturation", int(which[k]), int(axes[k]), np.int16(value))
                    self._imu_event_left = max(1, round(c.saturation_duration_s * self.imu_rate_hz))
                    self.counts.saturation_events += 1
                elif draws[k, 1] < p_stuck:
                    frozen = (prev_g.copy(), prev_a.copy(), prev_t) if k == 0 else (
                        gyro[k - 1].copy(), accel[k - 1].copy(), int(temp[k - 1]))
                    self._imu_event = ("stuck", 0, 0, frozen)
                    self._imu_event_left = max(1, round(c.stuck_duration_s * self.imu_rate_hz))
                    self.counts.stuck_events += 1
            if self._imu_event_left > 0:
                kind, sensor, axis, value = self._imu_event
                if kind == "saturation":
                    (gyro if sensor == 0 else accel)[k, axis] = value
                    self.counts.saturated_samples += 1
                else:
                    gyro[k], accel[k], temp[k] = value
                    self.counts.stuck_samples += 1
                self._imu_event_left -= 1

    def mag_field(self, n: int) -> np.ndarray:
        """Additive disturbance [gauss, chip axes] for the next n magnetometer samples."""
        c = self.config
        p = c.mag_disturbance_rate_hz / self.mag_rate_hz
        draws = self.rng.random(n)
        directions = self.rng.normal(size=(n, 3))
        out = np.zeros((n, 3))
        for k in range(n):
            if self._mag_left == 0 and draws[k] < p:
                self._mag_vector = (c.mag_disturbance_gauss * directions[k]
                                    / np.linalg.norm(directions[k]))
                self._mag_left = max(1, round(c.mag_disturbance_duration_s * self.mag_rate_hz))
                self.counts.mag_disturbances += 1
            if self._mag_left > 0:
                out[k] = self._mag_vector
                self._mag_left -= 1
                self.counts.mag_disturbed_samples += 1
        return out
