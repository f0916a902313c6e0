"""Other people's filters beside ours, on the same log: ``replay --compare``.

A number means little alone: 0.8° on one log can be easy or hard. VQF (Laidig & Seel,
online and its offline mode that sees the whole recording) and imufusion (x-io's
Fusion AHRS) are well-kept, published implementations, so running them on the same
samples, with the same declination, scored by the same code, says where an estimate
stands. They are optional packages (``vqf``, ``imufusion``: the ``compare`` extra), only
imported when asked for.

Frames. Both libraries are run on the recording's own body frame and time step (the
mean rate: neither takes per-sample steps). VQF's world is ENU with magnetic north;
imufusion's is NED or ENU as configured, magnetic north too. Each result is expressed
in the recording's world and turned to true north by the recording's declination, as
our estimators are (``declination`` parameter), so the scores compare like with like.

Samples our estimators would skip are handed over in the form each library itself
treats as missing: an all-zero accelerometer or magnetometer vector (VQF and imufusion
ignore those); a non-finite gyro sample repeats the last finite one (neither library
has a "missing gyro"), and is counted in :attr:`ReferenceRun.note`.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
import time
from dataclasses import dataclass

import numpy as np

from estimators import quat as Q

#: ``--compare`` names -> (score label, Python package).
REFERENCES = {
    "vqf": ("vqf online", "vqf"),
    "vqf-offline": ("vqf offline", "vqf"),
    "imufusion": ("imufusion", "imufusion"),
}
STANDARD_GRAVITY = 9.80665  # imufusion takes the accelerometer in g


@dataclass(frozen=True)
class ReferenceRun:
    """One reference filter's attitude over the recording (body -> the log's world)."""

    label: str
    q: np.ndarray  # (N, 4)
    six_d: bool  # no magnetometer in the log: judged on inclination only
    seconds: float  # wall time of the run
    note: str = ""  # what was done to samples the library cannot take ("" when none)


def parse_compare(values: list[str] | None) -> tuple[str, ...]:
    """``--compare`` values (repeatable, each a comma list) as names, in order, once
    each; ValueError naming the bad one and the valid names."""
    names: list[str] = []
    for value in values or []:
        for name in (part.strip() for part in value.split(",")):
            if name not in REFERENCES:
                raise ValueError(f"--compare: unknown reference {name!r}; valid: "
                                 f"{', '.join(REFERENCES)}")
            if name not in names:
                names.append(name)
    return tuple(names)


def reference_labels(names: tuple[str, ...]) -> list[str]:
    """The score rows' labels of the named references."""
    return [REFERENCES[name][0] for name in names]


def check_available(names: tuple[str, ...]) -> None:
    """ValueError naming the package a requested reference needs, before any work."""
    for name in names:
        package = REFERENCES[name][1]
        if importlib.util.find_spec(package) is None:
            raise ValueError(f"--compare {name} needs the {package} package: "
                             f"pip install 'attitude-bridge[compare]'")


def reference_runs(rec, declination_rad: float, names: tuple[str, ...]
                   ) -> list[ReferenceRun]:
    """Each named reference filter run over ``rec`` (a replay Recording)."""
    return reference_attitudes(rec.gyr, rec.acc, rec.mag, rec.rate_hz, rec.world,
                               declination_rad, names)


def reference_attitudes(gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None,
                        rate_hz: float, world: str, declination_rad: float,
                        names: tuple[str, ...]) -> list[ReferenceRun]:
    """Each named reference filter on these samples (body frame, rad/s, m/s², any
    magnetometer unit), its attitude body -> ``world`` ("NED" or "ENU") turned to true
    north by ``declination_rad``."""
    if not names:
        return []
    gyr, acc, mag, note = _library_inputs(gyr, acc, mag)
    out = []
    for name in names:
        began = time.perf_counter()
        if name in ("vqf", "vqf-offline"):
            q = _vqf(gyr, acc, mag, rate_hz, offline=name == "vqf-offline")
            q = Q.enu_to_ned(q) if world == "NED" else q
        else:
            q = _imufusion(gyr, acc, mag, rate_hz, world)
        out.append(ReferenceRun(reference_labels((name,))[0],
                                _in_world(q, world, declination_rad), mag is None,
                                time.perf_counter() - began, note))
    return out


def _library_inputs(gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, str]:
    """Contiguous float64 copies with missing samples in each library's own form."""
    gyr = np.array(gyr, dtype=float, order="C")
    bad_gyro = ~np.all(np.isfinite(gyr), axis=1)
    if bad_gyro.any():  # each bad row takes the last good row before it (0 before any)
        last = np.maximum.accumulate(np.where(~bad_gyro, np.arange(len(gyr)), -1))
        gyr = np.where(last[:, None] >= 0, gyr[np.maximum(last, 0)], 0.0)
    acc = np.array(acc, dtype=float, order="C")
    bad_acc = ~np.all(np.isfinite(acc), axis=1)
    acc[bad_acc] = 0.0
    if mag is not None:
        mag = np.array(mag, dtype=float, order="C")
        mag[~np.all(np.isfinite(mag), axis=1)] = 0.0
    parts = []
    if bad_gyro.any():
        parts.append(f"{int(bad_gyro.sum())} non-finite gyro samples held at the last "
                     f"finite rate")
    if bad_acc.any():
        parts.append(f"{int(bad_acc.sum())} non-finite accelerometer samples left out")
    return gyr, acc, mag, "; ".join(parts)


def _vqf(gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None, rate_hz: float,
         offline: bool) -> np.ndarray:
    """VQF's body -> ENU (magnetic north) quaternions, 9D with a magnetometer, else 6D."""
    vqf = importlib.import_module("vqf")
    ts = 1.0 / rate_hz
    if offline:
        result = vqf.offlineVQF(gyr, acc, mag, ts)
    else:
        result = vqf.VQF(ts).updateBatch(gyr, acc, mag)
    return np.asarray(result["quat9D" if mag is not None else "quat6D"], dtype=float)


def _imufusion(gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None, rate_hz: float,
               world: str) -> np.ndarray:
    """imufusion's body -> world (magnetic north) quaternions, with its defaults."""
    imufusion = importlib.import_module("imufusion")
    ahrs = imufusion.Ahrs()
    settings = imufusion.AhrsSettings()
    # imufusion 1.3 ignores a convention given to AhrsSettings' constructor: set it after.
    settings.convention = imufusion.CONVENTION_NED if world == "NED" else \
        imufusion.CONVENTION_ENU
    settings.sample_rate = rate_hz
    ahrs.set_settings(settings)
    gyr_dps, acc_g = np.degrees(gyr), acc / STANDARD_GRAVITY
    out = np.empty((len(gyr), 4))
    for i in range(len(gyr)):
        if mag is not None:
            ahrs.update(gyr_dps[i], acc_g[i], mag[i])
        else:
            ahrs.update_no_magnetometer(gyr_dps[i], acc_g[i])
        out[i] = ahrs.get_quaternion()
    return out


def _in_world(q: np.ndarray, world: str, declination_rad: float) -> np.ndarray:
    """Magnetic-north attitudes turned to true north: a heading east of magnetic north
    by ``declination`` is a turn about the vertical (down in NED, up in ENU)."""
    if declination_rad == 0.0 or not math.isfinite(declination_rad):
        return q
    turn = declination_rad if world == "NED" else -declination_rad
    return Q.multiply(Q.from_axis_angle(np.array([0.0, 0.0, 1.0]), np.array(turn)), q)
