"""Independent scoring for the replay tests: scipy rotations, no replay code.

Given raw arrays read by the test itself, run an estimator through the public
``estimators.run`` API and score it the BROAD way with scipy's Rotation/Slerp, so that
replay's readers, alignment and metrics are checked against a separate implementation.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

import estimators

MAX_GAP_S = 1.0  # replay's documented default: longer reference gaps are not scored


def wxyz_to_rot(q: np.ndarray) -> Rotation:
    return Rotation.from_quat(np.asarray(q)[:, [1, 2, 3, 0]])


def reference_on(t_ref: np.ndarray, q_ref: np.ndarray, t: np.ndarray
                 ) -> tuple[Rotation, np.ndarray]:
    """scipy Slerp of the reference at ``t`` and the mask of times it covers."""
    slerp = Slerp(t_ref, wxyz_to_rot(q_ref))
    inside = (t >= t_ref[0]) & (t <= t_ref[-1])
    idx = np.clip(np.searchsorted(t_ref, t, side="right") - 1, 0, len(t_ref) - 2)
    inside &= (t_ref[idx + 1] - t_ref[idx]) <= MAX_GAP_S
    rot = slerp(np.clip(t, t_ref[0], t_ref[-1]))
    return rot, inside


def run_and_score(name: str, t: np.ndarray, gyr: np.ndarray, acc: np.ndarray,
                  mag: np.ndarray | None, ref: Rotation, valid: np.ndarray,
                  world: str = "NED", declination_deg: float = 0.0,
                  imu_delay_s: float = 0.0) -> dict[str, float]:
    """RMS total/heading/inclination [deg] and Euler-angle RMS of estimator ``name``;
    ``imu_delay_s``: the sender's low-pass delay, passed to the estimator (which then
    also takes its magnetometer as that much newer) and carried forward here."""
    dt = np.diff(t, prepend=np.nan)
    rate = 1.0 / np.median(np.diff(t))
    dt[0] = 1.0 / rate
    if imu_delay_s > 0.0:
        # the estimate itself, then turned on by the body rate over the delay
        est_cls = estimators.estimator_class(name)
        inner = est_cls(rate_hz=rate, world=world, declination=np.radians(declination_deg),
                        imu_delay=imu_delay_s)
        res = inner.run(gyr, acc, mag, dt=dt)
        own = ({"mag_delay": est_cls.Params().mag_delay - imu_delay_s}
               if "mag_delay" in est_cls.param_names() else {})
        base = estimators.run(name, gyr, acc, mag, rate_hz=rate, world=world, dt=dt,
                              declination=np.radians(declination_deg), **own)
        forward = Rotation.from_rotvec(np.nan_to_num(gyr - base.bias) * imu_delay_s)
        q = (wxyz_to_rot(base.q) * forward).as_quat()[:, [3, 0, 1, 2]]
        assert np.allclose(np.abs(np.sum(q * res.q, axis=1)), 1.0, atol=1e-9)
        res = type(res)(q=q, bias=base.bias, flags=base.flags)
    else:
        res = estimators.run(name, gyr, acc, mag, rate_hz=rate, world=world, dt=dt,
                             declination=np.radians(declination_deg))
    keep = valid & ((res.flags & 1) != 0)
    est = wxyz_to_rot(res.q[keep])
    err = (est * ref[keep].inv()).as_quat()  # x, y, z, w
    w, z = np.abs(err[:, 3]), err[:, 2]
    total = est.inv() * ref[keep]
    heading = 2 * np.arctan2(np.abs(z), w)
    incl = 2 * np.arccos(np.clip(np.sqrt(w**2 + z**2), 0, 1))
    e_est = est.as_euler("ZYX")[:, ::-1]
    e_ref = ref[keep].as_euler("ZYX")[:, ::-1]
    d = np.angle(np.exp(1j * (e_est - e_ref)))

    def rms(x: np.ndarray) -> float:
        return float(np.degrees(np.sqrt(np.mean(x**2))))

    return {"total_deg": rms(total.magnitude()), "heading_deg": rms(heading),
            "inclination_deg": rms(incl), "roll_deg": rms(d[:, 0]), "pitch_deg": rms(d[:, 1]),
            "yaw_deg": rms(d[:, 2]), "samples": int(keep.sum())}
