"""tune finds the optimum that a brute-force computation in the test finds.

Data: replay.synthetic (known truth; gyro bias and noise, accelerometer noise), two
seeds as two "files". The trade-off of the seed paper makes the optimum interior: a
small kp follows the biased gyro, a large kp passes accelerometer noise through.
"""

from __future__ import annotations

import io

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import estimators
from replay.evaluate import prepare
from replay.synthetic import SyntheticConfig, generate
from replay.tune import ParamAxis, Progress, parse_param, sweep

KP = np.geomspace(0.02, 20.0, 9)
KI = np.array([0.0, 0.05])


def brute_force_total(rec, kp: float, ki: float) -> float:
    res = estimators.run("mahony", rec.gyr, rec.acc, rec.mag, rate_hz=rec.rate_hz, kp=kp, ki=ki,
                         dt=np.full(rec.n, 1.0 / rec.rate_hz))
    est = Rotation.from_quat(res.q[:, [1, 2, 3, 0]])
    ref = Rotation.from_quat(rec.reference.q[:, [1, 2, 3, 0]])
    angle = (est * ref.inv()).magnitude()
    return float(np.degrees(np.sqrt(np.mean(angle[(res.flags & 1) != 0] ** 2))))


def test_tune_finds_the_brute_force_optimum():
    recs = [generate(SyntheticConfig(duration_s=30.0, seed=s)) for s in (11, 12)]
    result = sweep([prepare(r) for r in recs], "mahony",
                   [ParamAxis("kp", KP), ParamAxis("ki", KI)], jobs=2, progress=False)
    expected = np.array([[np.mean([brute_force_total(r, kp, ki) for r in recs]) for ki in KI]
                         for kp in KP])
    np.testing.assert_allclose(result.grid(), expected, rtol=1e-9)
    i, j = np.unravel_index(np.argmin(expected), expected.shape)
    assert result.best == {"kp": KP[i], "ki": KI[j]}
    assert 0 < i < len(KP) - 1  # interior: both too small and too large gains are worse
    assert expected[0].min() > 1.5 * expected[i, j] and expected[-1].min() > 1.2 * expected[i, j]


def test_parse_param_forms():
    a = parse_param("kp=0.1:3:30")
    assert a.name == "kp" and len(a.values) == 30 and a.values[0] == 0.1 and a.values[-1] == 3
    assert list(parse_param("ki=0,0.5").values) == [0.0, 0.5]
    for bad in ("kp", "kp=1:2", "kp=a:b:3", "kp=0:1:0", "=1"):
        with pytest.raises(ValueError, match="NAME="):
            parse_param(bad)


def test_unknown_parameter_is_refused_before_work():
    prep = prepare(generate(SyntheticConfig(duration_s=2.0)))
    with pytest.raises(ValueError, match="valid"):
        sweep([prep], "mahony", [ParamAxis("gain", np.array([1.0]))], progress=False)


def test_progress_bar_reaches_total():
    out = io.StringIO()
    bar = Progress(4, stream=out)
    for _ in range(4):
        bar.advance()
    text = out.getvalue()
    assert text.count("\r") == 4 and " 4/4 " in text
    assert "[" + "#" * 30 + "]" in text and text.endswith("\n")


def test_tune_on_emulator_data_finds_the_interior_optimum():
    """Emulator ``flight``: a small kp follows the MPU6050's biased gyro, a large kp
    follows the linear acceleration of the manoeuvres; the test checks tune's grid and
    choice against its own brute force on the emulator's arrays and truth."""
    from hil import EmulatorConfig, simulate
    from replay.emulator import from_simulation

    sims = [simulate(EmulatorConfig(profile="flight", rate_hz=250.0, duration_s=20.0, seed=s))
            for s in (1, 2)]
    kp = np.geomspace(0.02, 20.0, 7)
    result = sweep([prepare(from_simulation(s)) for s in sims], "mahony",
                   [ParamAxis("kp", kp)], fixed={"ki": 0.0}, jobs=2, progress=False)

    def total(sim, gain: float) -> float:
        t = (sim.time_us - sim.time_us[0]) / 1e6
        dt = np.diff(t, prepend=t[0] - np.median(np.diff(t)))
        res = estimators.run("mahony", sim.gyr, sim.acc, sim.mag, rate_hz=250.0, dt=dt,
                             kp=gain, ki=0.0)
        est = Rotation.from_quat(res.q[:, [1, 2, 3, 0]])
        ref = Rotation.from_quat(sim.truth_q[:, [1, 2, 3, 0]])
        angle = (est * ref.inv()).magnitude()[(res.flags & 1) != 0]
        return float(np.degrees(np.sqrt(np.mean(angle**2))))

    expected = np.array([np.mean([total(s, g) for s in sims]) for g in kp])
    np.testing.assert_allclose(result.mean_total, expected, rtol=1e-9)
    best = int(np.argmin(expected))
    assert result.best == {"ki": 0.0, "kp": kp[best]}
    assert 0 < best < len(kp) - 1


def test_without_magnetometer_tune_minimises_inclination():
    from dataclasses import replace

    rec = replace(generate(SyntheticConfig(duration_s=10.0, seed=13)), mag=None)
    result = sweep([prepare(rec)], "mahony", [ParamAxis("kp", np.geomspace(0.05, 10, 5))],
                   jobs=1, progress=False)
    assert result.objective == "inclination"
    assert result.best_index == int(np.argmin(result.inclination[:, 0]))
