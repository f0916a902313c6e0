"""Contracts every registered estimator must keep (SPEC "Python API"), checked generically.

Each test is parametrised over ``estimators.names()`` at collection time, so estimators
added later are covered without touching this file.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import estimators
from estimators import quat as Q
from estimators.metrics import attitude_errors

G = 9.80665
FIELD_NED = np.array([0.2, 0.0, 0.45])
NAMES = estimators.names()
GYRO_ONLY = {"euler", "dcm", "quaternion"}


def _consistent(truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free accelerometer (specific force at rest) and magnetometer for ``truth``."""
    body = Q.conjugate(truth)
    return Q.rotate(body, np.array([0.0, 0.0, -G])), Q.rotate(body, FIELD_NED)


def _rotation(w: np.ndarray, seconds: float, rate: float,
              q0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = round(seconds * rate)
    t = np.arange(1, n + 1) / rate
    return np.tile(w, (n, 1)), Q.multiply(q0, Q.from_rotvec(np.outer(t, w)))


def _messy_sequence(seed: int = 3, n: int = 1500) -> dict[str, np.ndarray]:
    """Smooth random motion with sensor noise, jittered dt and every kind of bad sample."""
    rng = np.random.default_rng(seed)
    rate = 400.0
    dt = np.full(n, 1.0 / rate) * (1.0 + 0.05 * rng.uniform(-1.0, 1.0, n))
    w = np.cumsum(rng.normal(0.0, 0.15, (n, 3)), axis=0)
    w -= w.mean(axis=0)
    q = Q.identity(n)
    q[0] = Q.from_euler(0.2, -0.1, 0.5)
    for i in range(1, n):
        q[i] = Q.multiply(q[i - 1], Q.from_rotvec(w[i] * dt[i]))
    acc, mag = _consistent(q)
    acc = acc + rng.normal(0.0, 0.05, acc.shape) + 0.3 * np.sin(np.arange(n) / 20.0)[:, None]
    mag = mag + rng.normal(0.0, 0.01, mag.shape)
    gyr = w + rng.normal(0.0, 0.01, w.shape) + np.array([0.01, -0.02, 0.015])
    acc[0:3] = np.nan  # not initialisable yet
    acc[100] = np.nan
    acc[101] = 0.0
    acc[102] = [0.0, 0.0, 200.0]  # beyond the default ±16 g: saturated
    acc[103] = [np.inf, 0.0, -G]
    acc[104] = [0.0, 0.0, -G]  # product of components is 0: a perfectly usable sample
    gyr[200] = np.nan
    gyr[201] = [np.inf, 0.0, 0.0]
    dt[300], dt[301], dt[302], dt[303] = 0.0, -1e-3, np.nan, 2.0  # 2 s > default max_dt
    mag[400] = np.nan
    mag[401] = 0.0
    acc[500:520] = np.nan  # a longer accelerometer outage
    return {"gyr": gyr, "acc": acc, "mag": mag, "dt": dt}


EXPECTED_COUNTS = {  # of _messy_sequence, by construction
    "samples": 1500, "skipped": 6, "bad_dt": 4,
    "acc_unusable": 3 + 4 + 20, "mag_unusable": 2,
}


@pytest.mark.parametrize("with_mag", [True, False])
@pytest.mark.parametrize("name", NAMES)
def test_batch_equals_update(name, with_mag):
    data = _messy_sequence()
    mag = data["mag"] if with_mag else None
    one = estimators.create(name, rate_hz=400.0)
    q_update = np.array([one.update(data["gyr"][i], data["acc"][i],
                                    None if mag is None else mag[i], dt=data["dt"][i])
                         for i in range(len(data["dt"]))])
    many = estimators.create(name, rate_hz=400.0)
    result = many.run(data["gyr"], data["acc"], mag, dt=data["dt"])
    assert np.all(np.isfinite(result.q))
    assert np.allclose(np.linalg.norm(result.q, axis=1), 1.0, atol=1e-9)
    assert np.abs(result.q - q_update).max() <= 1e-9
    assert np.abs(result.bias[-1] - one.bias).max() <= 1e-9
    assert one.counters == many.counters
    counts = dataclasses.asdict(many.counters)
    expected = dict(EXPECTED_COUNTS, mag_unusable=EXPECTED_COUNTS["mag_unusable"] * with_mag)
    assert {k: counts[k] for k in expected} == expected
    # And the module-level batch() gives the same numbers too.
    q_batch = estimators.batch(name, data["gyr"], data["acc"], mag, rate_hz=400.0,
                               dt=data["dt"])
    assert np.abs(q_batch - q_update).max() <= 1e-9


@pytest.mark.parametrize("name", NAMES)
def test_batch_continues_from_current_state(name):
    """run() on two halves equals run() on the whole (the state carries over)."""
    data = _messy_sequence(seed=5, n=600)
    whole = estimators.create(name, rate_hz=400.0).run(data["gyr"], data["acc"], data["mag"],
                                                       dt=data["dt"]).q
    est = estimators.create(name, rate_hz=400.0)
    first = est.run(data["gyr"][:250], data["acc"][:250], data["mag"][:250], dt=data["dt"][:250])
    second = est.run(data["gyr"][250:], data["acc"][250:], data["mag"][250:],
                     dt=data["dt"][250:])
    assert np.abs(np.vstack([first.q, second.q]) - whole).max() <= 1e-9


@pytest.mark.parametrize("bad_acc", [[np.nan, 0.0, -G], [0.0, 0.0, 0.0], [0.0, 0.0, 170.0],
                                     [np.inf, np.inf, np.inf]])
@pytest.mark.parametrize("name", NAMES)
def test_gyro_integrates_when_only_accelerometer_is_bad(name, bad_acc):
    """An unusable accelerometer must not stop the gyro (the seed's early return did):
    the attitude follows the rate to within the first-order step error N·(ω·dt)³/12."""
    rate, w = 500.0, np.array([0.3, -0.6, 1.2])
    q0 = Q.from_euler(0.2, 0.3, -1.0)
    gyr, truth = _rotation(w, 1.0, rate, q0)
    est = estimators.create(name, rate_hz=rate, q0=q0)
    q = est.run(gyr, np.tile(bad_acc, (len(gyr), 1))).q
    first_order_bound = len(gyr) * (np.linalg.norm(w) / rate) ** 3 / 12.0
    tol = 2e-3 if name == "euler" else first_order_bound + 1e-12  # euler: Euler-ODE error
    assert Q.angle_between(q[-1], truth[-1]) <= tol
    assert est.counters.acc_unusable == len(gyr)
    assert est.counters.skipped == 0


@pytest.mark.parametrize("name", NAMES)
def test_level_accelerometer_with_zero_components_is_used(name):
    """acc = [0, 0, -g] has ax·ay·az == 0 yet is the most ordinary sample there is: it is
    counted as usable and the yaw rotation still integrates (level stays level). The seed's
    early return would leave the whole 1.5 rad; 1e-4 rad leaves room for rounding-level
    corrections (a normalised gradient of a ~1e-17 residual, as in Madgwick's algorithm)."""
    rate, w = 500.0, np.array([0.0, 0.0, 1.5])
    gyr, truth = _rotation(w, 1.0, rate, Q.identity())
    est = estimators.create(name, rate_hz=rate, q0=Q.identity())
    q = est.run(gyr, np.tile([0.0, 0.0, -G], (len(gyr), 1))).q
    assert est.counters.acc_unusable == 0
    assert Q.angle_between(q, truth).max() < 1e-4


@pytest.mark.parametrize("name", sorted(set(NAMES) - GYRO_ONLY))
def test_filters_use_a_level_accelerometer(name):
    """...and the filters really use it: from a 10° roll error, 3 s of a level reading
    reduce the error (gyro-only integrators are excluded: they ignore the accelerometer)."""
    start = Q.from_euler(math.radians(10.0), 0.0, 0.0)
    n = 1500
    q = estimators.batch(name, np.zeros((n, 3)), np.tile([0.0, 0.0, -G], (n, 1)),
                         rate_hz=500.0, q0=start)
    roll, pitch, _ = Q.to_euler(q[-1])
    assert math.hypot(roll, pitch) < math.radians(5.0)


@pytest.mark.parametrize("name", NAMES)
def test_unusable_samples_leave_the_state_untouched(name):
    est = estimators.create(name, rate_hz=100.0, q0=Q.from_euler(0.1, 0.2, 0.3))
    est.update([0.1, 0.2, 0.3], [0.0, 0.0, -G])
    before = est.q
    for gyr, dt in [([np.nan, 0.0, 0.0], 0.01), ([0.0, np.inf, 0.0], 0.01),
                    ([1.0, 1.0, 1.0], 0.0), ([1.0, 1.0, 1.0], -0.01),
                    ([1.0, 1.0, 1.0], np.nan), ([1.0, 1.0, 1.0], np.inf),
                    ([1.0, 1.0, 1.0], 0.6)]:
        assert np.array_equal(est.update(gyr, [0.0, 0.0, -G], dt=dt), before)
    counters = est.counters
    assert counters.samples == 8 and counters.skipped == 7 and counters.bad_dt == 5
    assert not est.status.initialising


@pytest.mark.parametrize("with_mag", [True, False])
@pytest.mark.parametrize("name", NAMES)
def test_initialises_from_first_usable_sample(name, with_mag):
    truth = Q.from_euler(math.radians(-20.0), math.radians(35.0), math.radians(140.0))
    acc, mag = _consistent(truth)
    est = estimators.create(name, rate_hz=200.0)
    assert est.status.initialising
    for bad in ([np.nan, 0.0, 0.0], [0.0, 0.0, 0.0]):
        q = est.update([0.5, 0.5, 0.5], bad, mag if with_mag else None)
        assert np.array_equal(q, Q.identity())  # nothing to anchor to yet
        assert est.status.initialising
    q = est.update([0.5, 0.5, 0.5], acc, mag if with_mag else None)
    assert not est.status.initialising
    expected = Q.from_acc_mag(acc, mag if with_mag else None)
    assert Q.angle_between(q, expected) < 1e-12
    if with_mag:
        assert Q.angle_between(q, truth) < 1e-12
    assert est.counters.acc_unusable == 2 and est.counters.samples == 3


@pytest.mark.parametrize("name", NAMES)
def test_enu_output_is_the_ned_estimate_re_expressed(name):
    data = _messy_sequence(seed=11, n=600)
    ned = estimators.batch(name, data["gyr"], data["acc"], data["mag"], dt=data["dt"])
    enu = estimators.batch(name, data["gyr"], data["acc"], data["mag"], dt=data["dt"],
                           world="ENU")
    assert np.abs(enu - Q.ned_to_enu(ned)).max() < 1e-12
    # World-frame meaning: the body z axis of a level FRD body points down = -Up in ENU.
    acc, mag = _consistent(Q.identity())
    q = estimators.create(name, world="enu").update([0.0, 0.0, 0.0], acc, mag)
    assert np.allclose(Q.rotate(q, [0.0, 0.0, 1.0]), [0.0, 0.0, -1.0], atol=1e-12)
    assert np.allclose(Q.rotate(q, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-12)  # North


@pytest.mark.parametrize("world", ["NED", "ENU"])
@pytest.mark.parametrize("name", NAMES)
def test_q0_is_taken_in_the_requested_world_frame(name, world):
    q0 = Q.normalize(np.array([0.3, -0.5, 0.6, 0.2]))
    est = estimators.create(name, world=world, q0=q0)
    assert not est.status.initialising
    assert Q.angle_between(est.q, q0) < 1e-12
    q = est.update([0.0, 0.0, 0.0], [np.nan] * 3)  # nothing but a zero-rate step
    assert Q.angle_between(q, q0) < 1e-12
    est.reset(Q.identity())
    assert Q.angle_between(est.q, Q.identity()) < 1e-12 and est.counters.samples == 0


@pytest.mark.parametrize("name", NAMES)
def test_passage_through_vertical_with_consistent_sensors(name):
    """Pitch 0 -> 180° at 2 rad/s (through +90°) with noise-free acc and mag: every
    estimator stays finite and within 1° of the truth (a gimbal-lock blow-up or a heading
    flip would be tens of degrees)."""
    rate = 1000.0
    gyr, truth = _rotation(np.array([0.0, 2.0, 0.0]), math.pi / 2.0, rate, Q.identity())
    acc, mag = _consistent(truth)
    for m in (mag, None):
        q = estimators.batch(name, gyr, acc, m, rate_hz=rate, q0=Q.identity())
        assert np.all(np.isfinite(q))
        assert math.degrees(Q.angle_between(q, truth).max()) < 1.0


@pytest.mark.parametrize("name", NAMES)
def test_unknown_parameter_is_a_value_error_listing_the_valid_ones(name):
    valid = estimators.estimator_class(name).param_names()
    with pytest.raises(ValueError, match="no_such_gain") as info:
        estimators.create(name, no_such_gain=1.0)
    for key in valid:
        assert key in str(info.value)


@pytest.mark.parametrize("name", NAMES)
def test_parameters_are_documented(name):
    for field in dataclasses.fields(estimators.estimator_class(name).Params):
        assert field.metadata.get("doc"), f"{name}.{field.name} has no doc"


def test_unknown_name_is_a_value_error_listing_the_valid_ones():
    with pytest.raises(ValueError, match="nonesuch") as info:
        estimators.create("nonesuch")
    for name in NAMES:
        assert name in str(info.value)


def test_required_names_are_registered():
    assert {"euler", "dcm", "quaternion", "kalman"} <= set(NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_bad_construction_arguments(name):
    with pytest.raises(ValueError):
        estimators.create(name, world="NWU")
    with pytest.raises(ValueError):
        estimators.create(name, rate_hz=0.0)
    with pytest.raises(ValueError), np.errstate(invalid="ignore"):
        estimators.create(name, q0=[0.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError):
        estimators.create(name).update([0.0, 0.0], [0.0, 0.0, -G])


# --- velocity aiding (SPEC "Optional aiding") ----------------------------------------------
def _accelerating(rate: float, seconds: float = 8.0):
    """Level, heading north, accelerating north at 4 m/s² from 2 to 5 s: the accelerometer
    sees a 22° false tilt for 3 s. Returns gyro, acc, mag, truth and the true velocity."""
    n = int(seconds * rate)
    a = np.zeros((n, 3))
    a[int(2 * rate):int(5 * rate), 0] = 4.0
    truth = Q.identity(n)
    # f = R^T (a - g) with R = I, plus noise: with exact data a normalised gradient
    # (Madgwick) turns rounding-level residuals into full-size steps
    rng = np.random.default_rng(5)
    acc = np.tile([0.0, 0.0, -G], (n, 1)) + a + rng.normal(0.0, 0.05, (n, 3))
    mag = np.tile(FIELD_NED, (n, 1)) + rng.normal(0.0, 0.002, (n, 3))
    vel = np.cumsum(a, axis=0) / rate
    return np.zeros((n, 3)), acc, mag, truth, vel


def _gps(vel: np.ndarray, rate: float, hz: float = 10.0, latency_s: float = 0.05):
    """Velocity measured at ``hz`` and delivered ``latency_s`` late, as the API takes it."""
    n = len(vel)
    out, age = np.full((n, 3), np.nan), np.zeros(n)
    late = round(latency_s * rate)
    for k in range(0, n - late, round(rate / hz)):
        out[k + late] = vel[k]
        age[k + late] = late / rate
    return out, age


@pytest.mark.parametrize("name", sorted(set(NAMES) - GYRO_ONLY))
def test_velocity_aiding_removes_the_vehicles_acceleration(name):
    """Every estimator that takes the accelerometer for gravity is pulled toward the false
    tilt while unaided; aided with the velocity (10 Hz, 50 ms late) its peak inclination
    error is a third of that or less (the derivative of a delayed, sampled velocity is not
    the acceleration at every instant: what remains is at the ramp edges)."""
    rate = 200.0
    gyr, acc, mag, truth, vel = _accelerating(rate)
    v, age = _gps(vel, rate)
    plain = estimators.batch(name, gyr, acc, mag, rate_hz=rate, q0=Q.identity())
    aided = estimators.batch(name, gyr, acc, mag, rate_hz=rate, q0=Q.identity(), vel=v,
                             vel_age=age)
    tilt = {k: np.degrees(attitude_errors(q, truth).inclination)
            for k, q in (("plain", plain), ("aided", aided))}
    assert tilt["plain"].max() > 1.0, tilt["plain"].max()
    assert tilt["aided"].max() < tilt["plain"].max() / 3.0, (tilt["aided"].max(),
                                                             tilt["plain"].max())


@pytest.mark.parametrize("world", ["NED", "ENU", "NED+declination"])
@pytest.mark.parametrize("name", sorted(set(NAMES) - GYRO_ONLY))
def test_horizontal_only_velocity_aids_in_every_world_frame(name, world):
    """GPS_RAW_INT has no vertical speed (vz NaN): the horizontal pair must still aid,
    in every output frame, as well as the full velocity does in this level manoeuvre
    (re-expressing the velocity once multiplied the missing vertical into all axes)."""
    rate = 200.0
    gyr, acc, mag, truth, vel = _accelerating(rate)
    v, age = _gps(vel, rate)
    dec = math.radians(10.0) if world.endswith("declination") else 0.0
    frame = world.split("+")[0]
    if dec:
        c, s = math.cos(dec), math.sin(dec)
        v = np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]], 1)
    if frame == "ENU":
        v = v[:, [1, 0, 2]] * np.array([1.0, 1.0, -1.0])
        truth = Q.ned_to_enu(truth)
    if dec:
        truth = Q.multiply(Q.from_axis_angle(np.array([0.0, 0.0, 1.0]), dec), truth)
    horizontal = v.copy()
    horizontal[:, 2] = np.nan
    q0 = truth[0]

    def peak_tilt(velocity):
        q = estimators.batch(name, gyr, acc, mag, rate_hz=rate, q0=q0, world=frame,
                             declination=dec, vel=velocity, vel_age=age)
        return np.degrees(attitude_errors(q, truth).inclination).max()

    plain, full, horiz = peak_tilt(None), peak_tilt(v), peak_tilt(horizontal)
    assert horiz < plain / 3.0, (horiz, plain)
    assert horiz <= 1.2 * full, (horiz, full)


@pytest.mark.parametrize("name", NAMES)
def test_batch_equals_update_with_aiding(name):
    rate = 200.0
    gyr, acc, mag, _, vel = _accelerating(rate, 4.0)
    v, age = _gps(vel, rate)
    one = estimators.create(name, rate_hz=rate)
    q_update = np.array([one.update(gyr[i], acc[i], mag[i], vel=v[i], vel_age=age[i])
                         for i in range(len(gyr))])
    q_batch = estimators.batch(name, gyr, acc, mag, rate_hz=rate, vel=v, vel_age=age)
    assert np.abs(q_batch - q_update).max() <= 1e-9


@pytest.mark.parametrize("name", sorted(set(NAMES) - GYRO_ONLY))
def test_aiding_velocity_is_taken_in_the_output_world_frame(name):
    """The same motion described in ENU (and with a declination, in true north) gives the
    same estimate as in NED: the velocity is re-expressed in the estimator's frame."""
    rate = 200.0
    gyr, acc, mag, _, vel = _accelerating(rate, 6.0)
    v, age = _gps(vel, rate)
    ned = estimators.batch(name, gyr, acc, mag, rate_hz=rate, vel=v, vel_age=age)
    v_enu = v[:, [1, 0, 2]] * np.array([1.0, 1.0, -1.0])
    enu = estimators.batch(name, gyr, acc, mag, rate_hz=rate, vel=v_enu, vel_age=age,
                           world="ENU")
    assert np.abs(enu - Q.ned_to_enu(ned)).max() < 1e-9
    dec = math.radians(10.0)  # true north = magnetic + 10°: a north velocity is turned
    c, s = math.cos(dec), math.sin(dec)
    v_true = np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]], 1)
    true_north = estimators.batch(name, gyr, acc, mag, rate_hz=rate, vel=v_true,
                                  vel_age=age, declination=dec)
    turn = Q.from_axis_angle(np.array([0.0, 0.0, 1.0]), dec)
    assert np.abs(Q.multiply(Q.conjugate(turn), true_north) - ned).max() < 1e-9


@pytest.mark.parametrize("name", NAMES)
def test_bad_aiding_input_is_ignored_or_refused(name):
    """NaN velocity = no measurement; an age beyond the aiding timeout or negative is not
    used (same result as no aiding); a wrong shape is a ValueError."""
    rate = 200.0
    gyr, acc, mag, _, vel = _accelerating(rate, 3.0)
    plain = estimators.batch(name, gyr, acc, mag, rate_hz=rate)
    stale = estimators.batch(name, gyr, acc, mag, rate_hz=rate, vel=vel, vel_age=5.0)
    backwards = estimators.batch(name, gyr, acc, mag, rate_hz=rate, vel=vel, vel_age=-0.1)
    nan = estimators.batch(name, gyr, acc, mag, rate_hz=rate, vel=np.full_like(vel, np.nan))
    for q in (stale, backwards, nan):
        assert np.abs(q - plain).max() == 0.0
    with pytest.raises(ValueError, match="vel"):
        estimators.batch(name, gyr, acc, mag, rate_hz=rate, vel=vel[:, :2])
    with pytest.raises(ValueError, match="vel"):
        estimators.create(name).update(gyr[0], acc[0], mag[0], vel=[1.0, 2.0])
