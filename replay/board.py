"""Which board profile a RAW_IMU stream needs, judged by gravity, and a plausibility check.

RAW_IMU integers mean different things to different senders (``imu.boards``): the same
message from the GY-86 emulator read as ArduPilot's mG says 4 g at rest, and every
estimate is then ~180° off without any error. Gravity is the one quantity every log
contains: at rest (and on average in hover) the accelerometer reads 1 g, so the profile
whose scale turns the resting counts into ≈ 9.81 m/s² is the right one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

G = 9.80665
PLAUSIBLE = 0.15  # |acc| at rest within ±15 % of g: the scale is right
WINDOW = 16  # samples per window when looking for the quietest stretches


def rest_magnitude(acc: np.ndarray) -> float:
    """|acc| while the vehicle is quietest: the median over the calmest quarter of
    16-sample windows (relative spread of |acc|), so manoeuvres do not bias it. A sample
    whose norm overflows (1e200: a wrong unit or corrupt) counts as not finite."""
    with np.errstate(over="ignore", invalid="ignore"):
        norm = np.linalg.norm(np.asarray(acc, dtype=float), axis=1)
    norm = norm[np.isfinite(norm)]
    if norm.size == 0:
        return float("nan")
    if norm.size < 2 * WINDOW:
        return float(np.median(norm))
    n = norm.size // WINDOW * WINDOW
    win = norm[:n].reshape(-1, WINDOW)
    mean = win.mean(axis=1)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        spread = win.std(axis=1) / mean
    if not np.isfinite(spread).any():  # every window reads zero: a dead accelerometer
        return float(np.median(norm))
    calm = spread <= np.nanpercentile(spread, 25)
    return float(np.median(mean[calm]))


def plausible(magnitude: float) -> bool:
    return bool(np.isfinite(magnitude) and abs(magnitude / G - 1.0) <= PLAUSIBLE)


@dataclass(frozen=True)
class BoardChoice:
    """The profile used and what |acc| at rest each candidate gives."""

    name: str
    magnitudes: dict[str, float]  # profile -> |acc| at rest [m/s²]
    detected: bool  # False: given with --board

    @property
    def magnitude(self) -> float:
        return self.magnitudes[self.name]

    def note(self) -> str:
        others = ", ".join(f"{k} {v:.1f}" for k, v in self.magnitudes.items() if k != self.name)
        how = "detected" if self.detected else "as given"
        return (f"RAW_IMU board profile {self.name} ({how}): |acc| at rest "
                f"{self.magnitude:.2f} m/s² (other profiles: {others})")

    def warning(self) -> str | None:
        """One line when the chosen scale cannot be right (None when it is plausible)."""
        if plausible(self.magnitude):
            return None
        fits = [k for k, v in self.magnitudes.items() if plausible(v)]
        hint = (f"--board {fits[0]} gives {self.magnitudes[fits[0]]:.2f}" if fits
                else "no known profile gives ≈ 9.81: RAW_IMU units unknown")
        return (f"|acc| at rest is {self.magnitude:.1f} m/s² ({self.magnitude / G:.2f} g) "
                f"under board profile {self.name}: attitudes will be wrong; {hint}")


def choose_board(acc_counts: np.ndarray, board: str | None) -> BoardChoice:
    """``board`` None: the profile whose accelerometer scale gives ≈ g at rest."""
    from imu.boards import PROFILES, board_profile

    if board is not None:
        board_profile(board)  # ValueError listing the valid names
    counts = rest_magnitude(acc_counts)
    magnitudes = {name: counts * make().accel_scale for name, make in PROFILES.items()}
    if board is not None:
        return BoardChoice(board, magnitudes, detected=False)
    best = min(magnitudes, key=lambda k: abs(np.log(magnitudes[k] / G))
               if np.isfinite(magnitudes[k]) and magnitudes[k] > 0 else np.inf)
    return BoardChoice(best, magnitudes, detected=True)


def magnitude_warning(acc: np.ndarray, what: str) -> str | None:
    """For SI streams (HIGHRES_IMU, SCALED_IMU, ULog, npz, CSV): a line if |acc| at rest
    is not about g (wrong unit or a broken accelerometer), else None."""
    m = rest_magnitude(acc)
    if plausible(m):
        return None
    return (f"|acc| at rest is {m:.2f} m/s² ({m / G:.2f} g) in {what}, not ≈ 9.81: "
            f"inclination and every score built on it are doubtful")
