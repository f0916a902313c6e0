"""The board's sampling loop: motion truth -> chips -> firmware readings, chunk by chunk.

Both ``simulate`` (arrays) and the live emulator (UDP) pull the same fixed-size chunks
from a ``SampleSource``, each random process drawing from its own seeded stream, so the
same seed gives the same samples on both paths.
"""

from __future__ import annotations

import math

import numpy as np

from .board import BoardClock
from .config import EmulatorConfig
from .faults import ClockFaults, FaultCounts, SensorFaults
from .gps import GpsFixes, GpsReceiver
from .motion import Profile, make_profile
from .recording import Recording
from .sensors import ms5611
from .sensors.hmc5883l import OVERFLOW, Hmc5883l
from .sensors.mpu6050 import G, Mpu6050, temperature_c
from .truth import Truth

CHUNK_S = 0.05  # stream time per chunk
#: Stream time of motion truth evaluated at once, ahead of the chunks (``TruthAhead``).
TRUTH_AHEAD_S = 1.0
#: Profiles are laid out for this long when streaming without a duration (then hover).
UNBOUNDED_HORIZON_S = 6 * 3600.0
#: RNG streams, in SeedSequence.spawn order. Never reorder (it changes every run).
STREAMS = ("mpu_build", "mpu_noise", "hmc_build", "hmc_noise", "baro", "clock",
           "sensor_faults", "clock_faults", "link_faults", "gps")


def frd_from_chip(v: np.ndarray) -> np.ndarray:
    """Chip axes (RFU: X right, Y forward, Z up) -> FRD; also the inverse."""
    v = np.asarray(v, dtype=float)
    return np.stack([v[..., 1], v[..., 0], -v[..., 2]], axis=-1)


chip_from_frd = frd_from_chip


def random_streams(seed: int) -> dict[str, np.random.Generator]:
    children = np.random.SeedSequence(seed).spawn(len(STREAMS))
    return {name: np.random.default_rng(s) for name, s in zip(STREAMS, children, strict=True)}


class TruthAhead:
    """A profile's truth on the grid t = i / rate, evaluated a block of indices at a time.

    A profile's truth costs about as much for one time as for a thousand (a few dozen
    numpy calls on short arrays), and each 50-ms chunk asks for it at four rates (the
    chip's internal rate, the IMU's, the magnetometer's, the barometer's): evaluated a
    second ahead, the sampling loop runs several times faster. The samples stay the same:
    every time is the same float i / rate, and a profile's truth at a time does not
    depend on the other times it is asked with."""

    def __init__(self, profile: Profile, rate_hz: float, block: int, end: int | None):
        self.profile = profile
        self.rate_hz = rate_hz
        self.block = max(1, block)
        self.end = end  # no lookahead past this index: a finite run's end (None: unbounded)
        self._start = 0
        self._held: Truth | None = None

    def at(self, start: int, stop: int) -> Truth:
        """The truth at i / rate for i in [start, stop)."""
        held = self._held
        if held is None or start < self._start or stop > self._start + len(held.t):
            ahead = start + self.block
            if self.end is not None:
                ahead = min(ahead, self.end)
            times = np.arange(start, max(stop, ahead)) / self.rate_hz
            held = self._held = self.profile.truth(times)
            self._start = start
        return held.rows(slice(start - self._start, stop - self._start))


class SampleSource:
    """Produces consecutive ``Recording`` chunks of ``chunk_samples`` IMU samples."""

    def __init__(self, config: EmulatorConfig, counts: FaultCounts | None = None,
                 truth_ahead_s: float = TRUTH_AHEAD_S):
        self.config = config
        self.counts = counts if counts is not None else FaultCounts()
        self.rng = random_streams(config.seed)
        mpu_cfg = config.mpu
        self.imu_rate = mpu_cfg.rate_hz
        self.internal_rate = mpu_cfg.internal_rate_hz
        self.decimation = mpu_cfg.decimation
        self.mag_rate = config.hmc5883l.rate_hz
        horizon = config.duration_s if config.duration_s is not None else UNBOUNDED_HORIZON_S
        self.profile: Profile = make_profile(config.profile, horizon, config.rotor_drag_per_s)
        self.mpu = Mpu6050(mpu_cfg, self.rng["mpu_build"])
        self.hmc = Hmc5883l(config.hmc5883l, self.rng["hmc_build"])
        self.clock = BoardClock(config.boot_time_s, config.clock_drift_ppm,
                                config.clock_jitter_us, self.rng["clock"])
        self.clock_faults = ClockFaults(config.faults, self.rng["clock_faults"], self.counts,
                                        self.imu_rate)
        self.sensor_faults = SensorFaults(config.faults, self.rng["sensor_faults"], self.counts,
                                          self.imu_rate, self.mag_rate)
        self.field_ned = config.environment.field_ned_gauss()
        self.gps = (GpsReceiver(config.gps, self.profile, self.rng["gps"])
                    if config.gps is not None else None)
        # The accelerometer's 1 kHz hold needs whole 8-sample blocks at 8 kHz internal.
        self.chunk_samples = 8 * max(1, math.ceil(self.imu_rate * CHUNK_S / 8))
        self.total_samples = (None if config.duration_s is None
                              else round(config.duration_s * self.imu_rate))
        self.next_index = 0
        self._truth_int = self._truth_grid(self.internal_rate, truth_ahead_s)
        self._truth_mag = self._truth_grid(self.mag_rate, truth_ahead_s)
        self._truth_baro = self._truth_grid(config.baro_rate_hz, truth_ahead_s)
        self._next_mag = 0  # index of the next magnetometer sample to take
        self._next_baro = 0
        self._mag_held = np.zeros(3, dtype=np.int16)
        self._last_imu = (np.zeros(3, np.int16), np.zeros(3, np.int16), 0)

    def _truth_grid(self, rate_hz: float, ahead_s: float) -> TruthAhead:
        duration = self.config.duration_s
        end = None if duration is None else math.ceil(duration * rate_hz) + 1
        return TruthAhead(self.profile, rate_hz, math.ceil(ahead_s * rate_hz), end)

    @property
    def finished(self) -> bool:
        return self.total_samples is not None and self.next_index >= self.total_samples

    @property
    def time_s(self) -> float:
        """True time of the next sample (= end of what was produced so far)."""
        return self.next_index / self.imu_rate

    def chunk(self) -> Recording:
        """The next chunk (shorter at the end of a finite run)."""
        cfg = self.config
        k0, n = self.next_index, self.chunk_samples
        if self.total_samples is not None:
            n = min(n, self.total_samples - k0)
        if n <= 0:
            raise ValueError("the run is finished")
        self.next_index += n
        dec = self.decimation
        t_int = (k0 * dec + np.arange(n * dec)) / self.internal_rate
        t = t_int[::dec]

        # MPU6050 at its internal rate, with the physical faults added in.
        truth_int = self._truth_int.at(k0 * dec, (k0 + n) * dec)
        rate_dps = np.degrees(chip_from_frd(truth_int.rates))
        accel_g = chip_from_frd(truth_int.specific_force()) / G
        bias_dps, vib_g = self.sensor_faults.physical(t_int, self.internal_rate)
        temp = cfg.environment.board_temperature(t_int)
        gyr_c, acc_c, temp_raw = self.mpu.measure(rate_dps + bias_dps, accel_g + vib_g, temp,
                                                  self.rng["mpu_noise"])
        self.sensor_faults.count_vibration(n)
        self.sensor_faults.imu_counts(gyr_c, acc_c, temp_raw, self._last_imu)
        self._last_imu = (gyr_c[-1].copy(), acc_c[-1].copy(), int(temp_raw[-1]))

        truth = truth_int.rows(slice(None, None, dec))
        armed, landed_state = self.profile.flight_state(t)
        mag_c, updated = self._magnetometer(t)
        time_us = self.clock.stamp(t, self.clock_faults.offsets(t))
        baro = self._barometer(self.time_s)
        gps = self._gps(self.time_s)
        lsb_g, lsb_a = self.mpu.config.gyro_lsb_per_dps, self.mpu.config.accel_lsb_per_g
        mag = frd_from_chip(mag_c) / self.hmc.config.lsb_per_gauss
        mag[np.any(mag_c == OVERFLOW, axis=1)] = np.nan
        return Recording(
            time_us=time_us, t_s=t,
            gyr_counts=gyr_c, acc_counts=acc_c, mag_counts=mag_c, temp_raw=temp_raw,
            mag_updated=updated,
            gyr=np.radians(frd_from_chip(gyr_c) / lsb_g),
            acc=frd_from_chip(acc_c) * (G / lsb_a),
            mag=mag,
            temperature_c=temperature_c(temp_raw),
            truth_q=truth.q, truth_rates=truth.rates,
            truth_specific_force=truth.specific_force(),
            truth_mag=truth.to_body(self.field_ned),
            truth_position_ned=truth.position_ned, truth_velocity_ned=truth.velocity_ned,
            truth_on_wire=(k0 + np.arange(n)) % cfg.truth_divider == 0,
            armed=armed, landed_state=landed_state,
            **baro, **gps,
        )

    def _magnetometer(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Held HMC5883L counts at IMU times t, taking new readings at the chip's rate."""
        latest = np.floor(t * self.mag_rate + 1e-9).astype(np.int64)  # newest reading index
        new = np.arange(self._next_mag, latest[-1] + 1)
        out = np.empty((len(t), 3), dtype=np.int16)
        updated = np.zeros(len(t), dtype=bool)
        if len(new):
            body = self._truth_mag.at(int(new[0]), int(new[-1]) + 1).to_body(self.field_ned)
            field = chip_from_frd(body) + self.sensor_faults.mag_field(len(new))
            counts = self.hmc.measure(field, self.rng["hmc_noise"])
            prior = np.concatenate([[self._mag_held], counts]).astype(np.int16)
            pos = latest - self._next_mag + 1  # 0 -> the previous chunk's held value
            out[:] = prior[pos]
            updated = np.diff(np.concatenate([[self._next_mag - 1], latest])) > 0
            self._mag_held = counts[-1]
            self._next_mag = int(latest[-1]) + 1
        else:
            out[:] = self._mag_held
        return out, updated

    def _barometer(self, t_end: float) -> dict[str, np.ndarray]:
        """MS5611 readings taken before t_end, compensated by the firmware."""
        env = self.config.environment
        stop = math.ceil(t_end * self.config.baro_rate_hz - 1e-9)
        first, stop = self._next_baro, max(self._next_baro, stop)
        self._next_baro = stop
        t = np.arange(first, stop) / self.config.baro_rate_hz
        truth = self._truth_baro.at(first, stop)
        true_p = env.pressure_pa(env.ground_altitude_m - truth.position_ned[:, 2])
        d1, d2 = self.config.ms5611.convert(true_p, env.board_temperature(t), self.rng["baro"])
        comp = [ms5611.compensate(self.config.ms5611.c, a, b) for a, b in zip(d1, d2, strict=True)]
        return {
            "baro_time_us": self.clock.stamp(t, self.clock_faults.offset_at(t)),
            "baro_t_s": t,
            "baro_d1": d1, "baro_d2": d2,
            "pressure_pa": np.array([c.pressure_pa for c in comp], dtype=np.int64),
            "baro_temp_cdeg": np.array([c.temp_cdeg for c in comp], dtype=np.int64),
            "truth_pressure_pa": true_p,
        }


    def _gps(self, t_end: float) -> dict[str, np.ndarray]:
        """GPS fixes sent before t_end (each measured ``latency`` earlier)."""
        if self.gps is None:
            fixes = GpsFixes.empty()
        else:
            fixes = self.gps.fixes_until(
                t_end, lambda t: self.clock.stamp(t, self.clock_faults.offset_at(t), jitter=False))
        return {"gps_t_s": fixes.t_s, "gps_time_us": fixes.time_us,
                "gps_sent_t_s": fixes.sent_t_s, "gps_vel_ned": fixes.vel_ned,
                "gps_pos_ned": fixes.pos_ned, "gps_truth_vel_ned": fixes.truth_vel_ned}


def simulate(config: EmulatorConfig, truth_ahead_s: float = TRUTH_AHEAD_S) -> Recording:
    """All samples and truth of a finite run, without sockets (faults in ``.faults``);
    ``truth_ahead_s`` as ``SampleSource``'s (the samples do not depend on it)."""
    if config.duration_s is None:
        raise ValueError("simulate needs a finite duration_s")
    source = SampleSource(config, truth_ahead_s=truth_ahead_s)
    parts = []
    while not source.finished:
        parts.append(source.chunk())
    rec = Recording.concatenate(parts)
    rec.faults = source.counts
    return rec
