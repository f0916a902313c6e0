"""benchmarks/accuracy.py's leave-one-out scores its grid on several processes
(``--jobs``): the choice must not depend on how many."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np

from estimators import quat as Q
from estimators.base import G

_SPEC = importlib.util.spec_from_file_location(
    "accuracy_benchmark", Path(__file__).resolve().parents[1] / "benchmarks" / "accuracy.py")
accuracy = importlib.util.module_from_spec(_SPEC)
sys.modules[_SPEC.name] = accuracy  # its dataclasses and the forked workers look it up
_SPEC.loader.exec_module(accuracy)


def _swinging_board(name: str, seed: int) -> accuracy.Trial:
    """A board rocking about roll and pitch for 8 s at 200 Hz, noisy sensors, truth known."""
    rate, n = 200.0, 1600
    t = np.arange(n) / rate
    roll, pitch = 0.3 * np.sin(1.1 * t + seed), 0.2 * np.sin(0.7 * t)
    truth = Q.from_euler(roll, pitch, np.zeros(n))
    body = Q.conjugate(truth)
    rng = np.random.default_rng(seed)
    gyr = np.zeros((n, 3))
    gyr[:-1] = Q.to_rotvec(Q.multiply(body[:-1], truth[1:])) * rate
    gyr[-1] = gyr[-2]
    acc = Q.rotate(body, np.tile([0.0, 0.0, -G], (n, 1))) + rng.normal(0, 0.05, (n, 3))
    mag = Q.rotate(body, np.tile([0.2, 0.0, 0.45], (n, 1))) + rng.normal(0, 0.002, (n, 3))
    runs = [accuracy.Run("drag", params={"drag": 0.5}), accuracy.Run("generic")]
    return accuracy.Trial(name, "emulator", gyr + rng.normal(0, 0.002, (n, 3)), acc, mag,
                          np.full(n, 1.0 / rate), rate, "NED", truth, np.ones(n, bool),
                          0.0, runs, airborne=np.ones(n))


def test_grid_scores_and_choices_equal_on_one_and_on_two_processes():
    trials = [_swinging_board("a", 1), _swinging_board("b", 2), _swinging_board("c", 3)]
    # 12 points: two tasks of up to 10, so two processes do share the work
    grid = {"gyro_noise": (0.005, 0.008, 0.012), "drag_noise": (0.1, 0.3),
            "mag_noise": (0.25, 0.4)}
    points = accuracy.grid_points(grid)
    one = accuracy._score_grid(trials, points, 1, lambda _: None)
    two = accuracy._score_grid(trials, points, 2, lambda _: None)
    assert len(one) == len(points) == 12
    assert one == two  # ErrorRms values, bit for bit, in grid order
    # the noise values do change the scores: the grid is not scoring one point four times
    totals = {round(row[0]["drag"].total_deg, 9) for row in one}
    assert len(totals) > 1
    _, _, held_one = accuracy.leave_one_out(trials, grid, lambda _: None, jobs=1)
    _, _, held_two = accuracy.leave_one_out(trials, grid, lambda _: None, jobs=2)
    assert held_one == held_two
