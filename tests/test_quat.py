"""Quaternion algebra and frame conversions, checked against scipy as an oracle."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimators import quat as Q


@pytest.fixture
def random_q() -> np.ndarray:
    return Q.normalize(np.random.default_rng(7).normal(size=(500, 4)))


def _scipy(q: np.ndarray) -> Rotation:
    return Rotation.from_quat(q[:, [1, 2, 3, 0]])


def test_dcm_matches_scipy(random_q):
    assert np.allclose(Q.to_dcm(random_q), _scipy(random_q).as_matrix(), atol=1e-12)
    back = Q.from_dcm(_scipy(random_q).as_matrix())
    assert Q.angle_between(back, random_q).max() < 1e-12


def test_multiply_matches_scipy_composition(random_q):
    p, q = random_q[:250], random_q[250:]
    expected = (_scipy(p) * _scipy(q)).as_quat()[:, [3, 0, 1, 2]]
    assert Q.angle_between(Q.multiply(p, q), expected).max() < 1e-12


def test_rotate_is_body_to_world(random_q):
    v = np.random.default_rng(1).normal(size=(500, 3))
    assert np.allclose(Q.rotate(random_q, v), _scipy(random_q).apply(v), atol=1e-12)


def test_euler_zyx_matches_scipy(random_q):
    roll_pitch_yaw = _scipy(random_q).as_euler("ZYX")[:, ::-1]
    assert np.allclose(Q.to_euler(random_q), roll_pitch_yaw, atol=1e-10)
    assert Q.angle_between(Q.from_euler(*roll_pitch_yaw.T), random_q).max() < 1e-12


@pytest.mark.parametrize("pitch", [np.pi / 2, -np.pi / 2])
def test_euler_gimbal_lock_is_finite_and_round_trips(pitch):
    q = Q.from_euler(0.3, pitch, 1.0)
    e = Q.to_euler(q)
    assert np.all(np.isfinite(e))
    assert e[0] == 0.0  # roll folded into yaw where only their combination is observable
    assert abs(e[1] - pitch) < 1e-6
    assert Q.angle_between(Q.from_euler(*e), q) < 1e-7


def test_rotvec_and_axis_angle_match_scipy(random_q):
    assert np.allclose(Q.to_rotvec(random_q), _scipy(random_q).as_rotvec(), atol=1e-12)
    v = np.random.default_rng(3).normal(size=(100, 3))
    assert Q.angle_between(Q.from_rotvec(v), _scipy(Q.from_rotvec(v)).as_quat()[:, [3, 0, 1, 2]]
                           ).max() < 1e-12
    axis, angle = Q.to_axis_angle(random_q)
    assert Q.angle_between(Q.from_axis_angle(axis, angle), random_q).max() < 1e-12
    assert np.allclose(Q.from_rotvec(np.zeros(3)), [1, 0, 0, 0])


def test_ned_enu_and_frd_rfu_conversions_match_scipy(random_q):
    swap = Rotation.from_matrix([[0, 1, 0], [1, 0, 0], [0, 0, -1]])
    enu = (swap * _scipy(random_q)).as_quat()[:, [3, 0, 1, 2]]
    assert Q.angle_between(Q.ned_to_enu(random_q), enu).max() < 1e-12
    assert Q.angle_between(Q.enu_to_ned(Q.ned_to_enu(random_q)), random_q).max() < 1e-12
    frd = (_scipy(random_q) * swap).as_quat()[:, [3, 0, 1, 2]]
    assert Q.angle_between(Q.rfu_to_frd_body(random_q), frd).max() < 1e-12
    # An RFU board's x (right) is FRD's y.
    assert np.allclose(Q.rfu_to_frd_vector([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])


@pytest.mark.parametrize("world", ["NED", "ENU"])
def test_from_acc_mag_recovers_attitude(random_q, world):
    g_ned, m_ned = np.array([0, 0, -9.81]), np.array([0.2, 0.0, 0.45])  # north, down
    acc = np.einsum("nji,j->ni", Q.to_dcm(random_q), g_ned)
    mag = np.einsum("nji,j->ni", Q.to_dcm(random_q), m_ned)
    expected = Q.ned_to_enu(random_q) if world == "ENU" else random_q
    assert Q.angle_between(Q.from_acc_mag(acc, mag, world), expected).max() < 1e-9


def test_world_name_is_validated():
    with pytest.raises(ValueError, match="NED"):
        Q.world_is_enu("NWU")


def test_bracket_takes_a_time_on_a_sample_whatever_the_gap_after_it():
    t_src = np.array([0.0, 0.01, 0.02, 0.10, 0.11])
    i0, frac, inside = Q.bracket(t_src, np.array([0.02, 0.05, 0.10, 0.105, 0.11, 0.12]),
                                 max_gap=0.015)
    assert inside.tolist() == [True, False, True, True, True, False]
    assert i0[0] == 2 and frac[0] == 0.0  # on the sample before the gap: itself
    assert i0[2] == 3 and frac[2] == 0.0
