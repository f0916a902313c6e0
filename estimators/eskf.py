"""Strong estimator ("eskf"): a multiplicative error-state Kalman filter with the
vehicle's velocity as a state, so that linear acceleration is modelled, not guessed.

Why velocity: an accelerometer measures specific force ``f = a − g``, never gravity
alone. A filter that takes ``f`` for gravity is pulled toward "level" whenever the
vehicle accelerates — for seconds at a time on a multirotor, whose accelerometer sees
thrust. Integrating ``R·f + g`` gives the velocity instead, and a velocity is something
we can say things about: it is measured (GPS, the autopilot's estimate), it stays small
for a hand-held device, and a multirotor's rotor drag makes the accelerometer's
horizontal axes read it directly. A tilt error ``δθ`` makes the integrated velocity
drift at ``g × δθ``; every velocity statement therefore corrects the tilt, with the
lag and weight the Kalman filter works out, and bounded accelerations (manoeuvres,
vibration, taps) only ever move the velocity by a bounded amount.

**Nominal state** (every sample): attitude ``q`` (body → magnetic NED), gyro bias ``b``,
velocity ``v`` (NED), drag coefficient ``μ``. Strapdown ``q ← q ⊗ exp((ω − b)·dt)``,
``v ← v + (R·f + g)·dt``.

**Error state** (Kalman, every ``update_period`` — the filter's cost does not grow with
the IMU rate): ``x = [δθ (world frame, 3), δb (3), δv (3), δλ]``, true attitude
``exp(δθ) ⊗ q``. Over a period ``T`` with the specific force integrated to ``ΔV``
(world frame): ``δθ' = δθ − R·T·δb``, ``δv' = δv − [ΔV]×·δθ``; process noise from the
gyro (angle random walk, covering its noise and unmodelled errors, plus a part that
grows with the rotation rate: scale-factor and axis-misalignment errors only turn into
attitude error while the body turns, so a fast turn is when the filter must lean on
the velocity information), the bias random walk and a velocity random walk.

**Measurements** (noise given as densities, so the numbers hold from 100 Hz to 8 kHz):

* *Velocity aiding* (``vel=`` on ``update``/``run``): each finite component is a
  measurement of ``v`` at ``age`` seconds before the sample, predicted as
  ``v − age·(R·f + g)``; chi-square gated, and the velocity is re-anchored to the
  measurement after ``velocity_reset_time`` of rejections (a GPS that jumped). Its noise
  is a density (``aid_density``) divided by the time between measurements: a 50 Hz
  autopilot estimate is not 10 independent GPS fixes. It corrects tilt, velocity and
  bias but not the heading (``aid_heading``): an autopilot's velocity was integrated
  with the autopilot's own heading, and together with the drag model (``Rᵀv``) it
  would pull our heading toward the autopilot's errors.
* *Rotor drag* (multirotors, ``drag`` > 0, *while airborne*): a flying multirotor's
  horizontal specific force is rotor drag, ``f_xy = −μ·(Rᵀv)_xy`` (the thrust is along
  body z). This makes tilt and velocity observable without any aiding. ``μ`` (1/s)
  differs per vehicle, so it is a state, estimated in logarithm (``λ = ln μ``, started
  at ``ln drag`` ± ``drag_sigma_init``): a linear μ can be driven to zero by a velocity
  error early in a flight (the body tilted on the ground before lift-off reads as
  speed) and then, its variance spent, cannot come back, whereas a relative error is
  as easy to undo as to make. The
  vertical velocity gets a weak zero prior (``vertical_velocity_prior``) so that it
  cannot wander into ``Rᵀv``. On the bench, carried by hand or on the ground between
  flights the accelerometer sees gravity and the model is wrong, so it runs only while
  the vehicle says it is airborne (``set_flight_state`` / ``run(airborne=)``, from its
  armed flag and landed state: ``imu.flight_state``); when nothing says, a two-state
  hidden Markov model decides from the data (``_drag_model_on``) and the flags of each
  sample (``F_AIR_MODEL``) tell which model ran.
* *Bounded velocity* (otherwise: hand-held, an unknown vehicle, or any vehicle on the
  ground, aided or not — it moves at walking pace at most; a multirotor whose state
  nobody reports is on the ground while its detector says so): ``v ≈ 0`` with
  density ``velocity_prior``; the velocity random walk lets it wander slowly, so a steady
  motion is not mistaken for a tilt. The faster the vehicle seems to move (squared speed
  low-passed over ``velocity_scale_tau``), the weaker the statement (noise ×
  ``1 + |v|²/velocity_scale²``): an unknown vehicle that flies away at 10 m/s is carried
  by the gyro instead of being pulled level. Not at rest, where nothing accelerates: a
  velocity left over from a knock is then refused like any outlier. Chi-square gated;
  after ``velocity_reset_time`` of rejections the velocity is re-anchored at zero, which
  changes no attitude.
* *Rest* (VQF's rest detector and thresholds: gyro and accelerometer within
  ``rest_gyr_th``/``rest_acc_th`` of their low-pass for ``rest_time``, and the low-passed
  gyro within ``rest_bias_th`` of the bias estimate, so that a steady turn is not rest):
  unaided or while the drag model runs, the mean specific force measures the tilt
  (otherwise the measured velocity tells a sustained acceleration, which is just as
  steady, from rest), and, unless the vehicle flies, the low-passed gyro measures the
  bias (a hover is steady but not still: a slow yaw, the position hold's corrections).
  Not the velocity: a multirotor cruising at constant speed is exactly as steady as one
  standing on the ground. At the start — a vehicle is powered up at rest, as the
  flight-state detector assumes too — the wait is waived while the body has been steady
  since its first sample: the mean specific force levels the estimate from the first
  update, as an inertial system levels before it navigates, aided or not (nothing is
  powered up in a sustained acceleration, and an autopilot's velocity is then its own
  filter settling). Started from one sample,
  the tilt was otherwise left to the bounded-velocity prior for half a second, and the
  heading, averaged from readings turned by that tilt, kept its trace for seconds. The
  bias still waits for ``rest_time``: its low-pass must settle first.
* *Magnetometer, heading only*: the heading of the field rotated into the world frame
  is a measurement of ``δθ_z``; its gain on ``δθ_x, δθ_y`` is zeroed (Joseph form keeps
  ``P`` consistent), so a disturbed field cannot tilt the estimate, while the bias
  along the vertical still learns from it. Chi-square gated, and paused while the
  field's norm or dip departs from the reference learned while undisturbed (VQF's
  10 % / 10°; a new field consistent for ``mag_new_time`` becomes the reference). An
  undisturbed field rejected by the chi-square test for ``mag_reset_time`` resets the
  heading to it (as PX4's EKF2 resets its yaw): our heading is what went wrong.
  A magnetometer reading is older than the gyro sample it comes with (its own
  filter, slower sampling): in a fast turn a few milliseconds are degrees of heading,
  so the reading is turned back by the rotation since (``mag_delay`` × the body rate).
  Behind a sender's IMU low-pass (``imu_delay``, ArduPilot) the gyro is the older one:
  the reading is then turned by (``mag_delay`` − ``imu_delay``) × the rate, forward.

* *A gyro that repeats one reading*: a quantised gyro without noise (a simulator at
  rest: ArduPilot SITL's RAW_IMU, in whole mrad/s truncated toward zero) hides its bias
  within one step, and repeating the reading narrows nothing; the first vibration
  dithers the quantiser and shows the bias as it is. While the reading has not changed
  for ``rest_time``, the bias variance is kept at ``gyro_resolution``²/3 at least. A
  gyro with noise, any real one, never triggers it.

Every Kalman step leaves its prediction and its result (state, covariance, the
transition's ingredients) in the state's ``TAP`` block, and flags the re-anchorings done
outside the update: what :mod:`estimators.smoother` reads to smooth a whole recording
afterwards with the same model. The online filter writes it and never reads it.

Defaults, and on which data they were chosen (none of this is "data never seen"):
rest and magnetic-disturbance thresholds are VQF's published values. The noise
densities and ``mag_delay`` on ``benchmarks/accuracy.py``'s grid were chosen on all of its
22 dev recordings (9 BROAD trials, 4 PX4 SIH and 2 ArduPilot SITL flights, 4 emulator
flights, 3 emulator hand-held recordings), and the same script cross-validates that
choice leaving one recording out at a time. Everything else — the model's structure,
the drag prior, the flight-state detector's constants, ``aid_heading`` /
``drag_heading``, ``gyro_resolution`` (MAVLink's mrad/s) and the remaining noise
values — was set by hand while looking at those same recordings (docs/accuracy.md
lists them), so it is in-sample.
"""

from __future__ import annotations

import dataclasses
import math
from collections import namedtuple
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from . import _core
from .base import MAX_IMU_DELAY_S, CommonParams, Estimator, G, param
from .registry import register

_DEG = math.pi / 180.0
#: ``drag`` for a vehicle known to be a multirotor (MAVLink MAV_TYPE quadrotor, hexarotor,
#: ...): the prior mean of μ. Small multirotors have 0.3-1 1/s; μ is estimated from there,
#: so the value only has to be the right order of magnitude.
MULTIROTOR_DRAG_PER_S = 0.5
#: The flight-state detector's belief "airborne" when the estimator starts (on the ground).
P_AIR_AT_START = 0.01
# Chi-square 99.9 % points for 1, 2 and 3 degrees of freedom: a measurement further from
# its prediction than this, in its own predicted uncertainty, is an outlier.
_GATE = (0.0, 10.828, 13.816, 16.266)
#: A repeated magnetometer reading stops being used once the body has turned this far
#: since it was taken (the heading error a stale reading would bring in) [rad].
_MAG_STALE_RAD = 0.1 * math.pi / 180.0
_NX = 10  # error state: δθ(3), δb(3), δv(3), δλ = δ ln μ
_TH, _BI, _VE, _MU = 0, 3, 6, 9


@dataclass(frozen=True)
class EskfParams(CommonParams):
    BOUNDS: ClassVar[dict[str, tuple[float, float]]] = {
        # durations and time constants [s]
        "update_period": (1e-4, 1.0), "velocity_scale_tau": (0.0, 1e4),
        "velocity_reset_time": (0.01, 1e4), "flight_evidence_time": (1e-3, 1e4),
        "flight_switch_time": (0.1, 1e6), "mag_delay": (0.0, MAX_IMU_DELAY_S),
        "mag_ref_time": (0.0, 1e4), "mag_provisional_time": (0.0, math.inf),
        "mag_new_time": (0.0, 1e4), "mag_reset_time": (0.0, 1e4),
        "mag_ref_tau": (0.01, 1e6), "rest_time": (1e-3, 1e4),
        "rest_tau": (1e-3, 1e4), "rest_prefilter_tau": (1e-4, 10.0),
        # noise densities and standard deviations: squared, so within 1e-9..1e6 (a large
        # one turns a measurement off, as the tests do)
        "gyro_noise": (1e-9, 1e6), "gyro_rate_noise": (0.0, 1e6), "bias_rw": (0.0, 1e6),
        "bias_init": (1e-9, 1e6), "tilt_init": (1e-9, math.pi),
        "heading_init": (1e-9, math.pi), "velocity_rw": (0.0, 1e6),
        "velocity_prior": (1e-9, 1e6), "vel_aid_noise": (1e-9, 1e6),
        "aid_density": (0.0, 1e6), "drag_sigma_init": (1e-9, 5.0),
        "drag_noise": (1e-9, 1e6), "vertical_velocity_prior": (1e-9, 1e6),
        "flight_accel_noise": (1e-3, 1e6), "mag_noise": (1e-9, 1e6),
        "rest_noise": (1e-9, 1e6), "rest_gravity_noise": (1e-9, 1e6),
        # thresholds and scales (inf: the test is off)
        "velocity_scale": (1e-3, math.inf), "bias_max": (1e-3, math.inf),
        "mag_norm_th": (1e-3, math.inf), "mag_dip_th": (1e-3, math.inf),
        "rest_gyr_th": (1e-6, math.inf), "rest_acc_th": (1e-6, math.inf),
        "rest_bias_th": (1e-6, math.inf), "rest_mag_th": (1e-6, math.inf),
        # the vehicle
        "gravity": (1.0, 30.0), "drag": (0.0, 100.0), "gyro_resolution": (0.0, 1.0),
        # switches
        "aid_heading": (0.0, 1.0), "drag_heading": (0.0, 1.0),
    }

    update_period: float = param(0.01, "Kalman update period [s]: samples in between are "
                                       "integrated, so the filter's cost and behaviour do "
                                       "not depend on the IMU rate")
    gravity: float = param(G, "gravity [m/s^2]")
    gyro_noise: float = param(0.005, "attitude random walk [rad/sqrt(s)]: gyro noise plus "
                                     "its unmodelled errors (scale, misalignment)")
    gyro_rate_noise: float = param(0.005, "attitude random walk per rotation rate [sqrt(s)]: "
                                        "a gyro's scale-factor and axis-misalignment "
                                        "errors turn into attitude error in proportion "
                                        "to how fast it turns")
    bias_rw: float = param(1e-4, "gyro-bias random walk [rad/s/sqrt(s)]")
    bias_init: float = param(0.5 * _DEG, "initial gyro-bias standard deviation [rad/s]")
    bias_max: float = param(20.0 * _DEG, "bias estimate clip per axis [rad/s] (the "
                                         "MPU6050's zero-rate offset range)")
    gyro_resolution: float = param(1e-3, "a gyro reading that stays exactly the same at "
                                         "rest hides its bias to within this step [rad/s] "
                                         "(MAVLink's RAW_IMU / SCALED_IMU: 1 mrad/s): the "
                                         "bias learned from it is kept this uncertain")
    tilt_init: float = param(20.0 * _DEG, "initial tilt standard deviation [rad] (a start "
                                          "from one sample of a vibrating vehicle can be "
                                          "this far off)")
    heading_init: float = param(30.0 * _DEG, "initial heading standard deviation [rad]")
    velocity_rw: float = param(0.1, "velocity random walk [m/s/sqrt(s)]: how fast the "
                                     "velocity may drift from what the accelerometer says "
                                     "(accelerometer noise, scale errors, lever arm)")
    velocity_prior: float = param(0.2, "bounded-velocity pseudo-measurement v ≈ 0, noise "
                                       "density [m/s·sqrt(s)] (no aiding, no drag model)")
    velocity_scale: float = param(0.5, "bounded-velocity prior: speeds well above this "
                                            "[m/s] weaken it (noise × (1 + |v|²/scale²))")
    velocity_scale_tau: float = param(0.5, "time constant [s] of the low-pass of the squared "
                                           "speed that velocity_scale judges (0: the "
                                           "speed now)")
    velocity_reset_time: float = param(3.0, "velocity re-anchored after this long [s] of "
                                            "rejected velocity information")
    vel_aid_noise: float = param(0.8, "velocity aiding noise per measurement [m/s], used "
                                      "only with aid_density=0 (GPS or the autopilot's "
                                      "estimate: their errors are correlated over "
                                      "seconds, so more than the white noise)")
    drag: float = param(0.0, "multirotor rotor-drag model: initial drag coefficient "
                             "μ [1/s] (f_xy = −μ·v_body,xy); 0 = not a multirotor")
    drag_sigma_init: float = param(0.7, "initial standard deviation of ln μ (μ is "
                                        "estimated in logarithm: 0.7 is a factor of two)")
    drag_noise: float = param(0.2, "drag measurement noise density [m/s^2·sqrt(s)]")
    vertical_velocity_prior: float = param(1.0, "multirotor: vertical velocity ≈ 0 "
                                                "pseudo-measurement density [m/s·sqrt(s)]")
    aid_heading: float = param(0.0, "1: velocity aiding also corrects the heading; 0: "
                                    "tilt, velocity and bias only (an autopilot's velocity "
                                    "was integrated with its own heading and shares its "
                                    "errors)")
    aid_density: float = param(1.6, "velocity aiding noise density [m/s·sqrt(s)]: the "
                                    "noise of one measurement is this over sqrt(time "
                                    "since the last), so 5 Hz GPS and a 50 Hz autopilot "
                                    "estimate carry the same information per second "
                                    "(0: vel_aid_noise per measurement)")
    drag_heading: float = param(0.0, "1: the drag measurement also corrects the heading; "
                                     "0: tilt, velocity, drag coefficient and bias only "
                                     "(Rᵀv couples heading to a velocity error, which "
                                     "must not turn into a heading error)")
    flight_accel_noise: float = param(1.5, "flight-state detector (flight state unknown): "
                                           "how far the horizontal specific force strays "
                                           "from what either state predicts (hand "
                                           "accelerations, drag-model error) [m/s^2]")
    flight_evidence_time: float = param(0.5, "flight-state detector: correlation time of "
                                             "those strays [s]; evidence counts once per it")
    flight_switch_time: float = param(30.0, "flight-state detector: mean time between "
                                            "take-offs and landings [s] (the two-state "
                                            "Markov chain's switching rate)")
    mag_noise: float = param(0.25, "magnetometer heading noise density [rad·sqrt(s)]")
    mag_delay: float = param(0.01, "how much older [s] a magnetometer reading is than the "
                                  "instant its IMU message describes (a magnetometer's "
                                  "filter and slower sampling): the reading is turned "
                                  "back by the rotation since (less imu_delay: the gyro "
                                  "behind a sender's low-pass is older still)")
    mag_norm_th: float = param(0.1, "magnetic disturbance: relative field-norm deviation")
    mag_dip_th: float = param(10.0 * _DEG, "magnetic disturbance: dip-angle deviation [rad]")
    mag_ref_time: float = param(5.0, "a field consistent this long [s] becomes the first "
                                     "reference")
    mag_provisional_time: float = param(math.inf, "before that, a field consistent this "
                                                  "long [s] is a provisional reference "
                                                  "(opt-in, e.g. 0.5: magnets near a board "
                                                  "at start-up; inf: off)")
    mag_new_time: float = param(20.0, "a disturbed but consistent field becomes the new "
                                      "reference after this long [s]")
    mag_reset_time: float = param(5.0, "an undisturbed field whose heading innovations are "
                                       "rejected this long [s] resets the heading to it")
    mag_ref_tau: float = param(20.0, "time constant [s] with which undisturbed field "
                                     "norm/dip refine the reference")
    rest_gyr_th: float = param(2.0 * _DEG, "rest: gyro deviation from its low-pass below "
                                           "this [rad/s]")
    rest_acc_th: float = param(0.5, "rest: accelerometer deviation from its low-pass below "
                                    "this [m/s^2]")
    rest_time: float = param(1.5, "rest: conditions hold this long [s]")
    rest_bias_th: float = param(2.0 * _DEG, "rest: low-passed gyro within this of the bias "
                                            "estimate, per axis [rad/s] (VQF's bias clip: a "
                                            "steady turn is not rest), or within bias_max "
                                            "while the magnetometer's direction is steady")
    rest_mag_th: float = param(0.5 * _DEG, "rest: the magnetometer's direction is steady "
                                           "within this of its low-pass [rad]")
    rest_tau: float = param(0.5, "time constant [s] of the rest-detection low-passes")
    rest_noise: float = param(0.03 * _DEG, "rest: gyro-bias measurement noise density "
                                           "[rad/s·sqrt(s)]")
    rest_gravity_noise: float = param(0.2, "rest: the mean specific force is gravity, noise "
                                           "density [m/s^2·sqrt(s)]")
    rest_prefilter_tau: float = param(0.05, "rest: time constant [s] of the pre-filter "
                                            "(attenuates 70 Hz vibration 20×)")


#: The kernels' parameter vector, declared once: every EskfParams field (in declaration
#: order) plus the common aid_timeout; kernels read ``params[_I.<name>]``.
_PARAM_FIELDS = (*(f.name for f in dataclasses.fields(EskfParams)
                   if f.name not in {c.name for c in dataclasses.fields(CommonParams)}),
                 "aid_timeout")
_I = namedtuple("_ParamIndex", _PARAM_FIELDS)(*range(len(_PARAM_FIELDS)))

# --- private state layout -------------------------------------------------------------
def _layout(*sizes: int) -> tuple[int, ...]:
    """Consecutive offsets after the common state for blocks of the given sizes."""
    offsets, at = [], _core.PRIVATE
    for size in sizes:
        offsets.append(at)
        at += size
    return (*offsets, at)


(_V,  # 3: velocity, magnetic NED [m/s]
 _MUS,  # drag coefficient μ [1/s]
 _P,  # covariance of the error state, row-major _NX × _NX
 _ACC_T,  # time integrated since the last Kalman update [s]
 _TURN2,  # ∫|ω − b|² dt over that time [rad²/s]
 _FB_T,  # the part of it covered by usable accelerometer samples [s]
 _DV,  # 3: ∫R·f dt over that time (world)
 _FB,  # 3: ∫f dt (body, as measured), for the drag measurement
 _FW,  # 3: the last sample's specific force in the world frame (trapezoidal integration)
 _FW_OK,  # 1 when _FW holds one
 _GPF,  # 3: gyro pre-filter (rest detection: vibration out)
 _GLP,  # 3: its low-pass (rest detection; the bias it measures)
 _APF,  # 3: accelerometer pre-filter
 _ALP,  # 3: its low-pass
 _MPF,  # 3: magnetometer direction pre-filter
 _MLP,  # 3: its low-pass
 _MAG_STEADY,  # 1 while the magnetometer's direction in the body is steady
 _REST_T,  # how long rest conditions have held [s]
 _REST_ANCHORED,  # 1 once the velocity was re-anchored in this rest period
 _LP_OK,  # 1 once the rest low-passes are seeded
 _MN_REF, _MD_REF, _REF_OK,  # field norm/dip reference, 1 once set
 _MN_C, _MD_C, _CAND_T,  # candidate field norm/dip, how long it has held [s]
 _V_OK_T,  # RUN_T when velocity information was last accepted
 _SPEED2,  # low-passed squared speed [m²/s²] (how far from bounded the motion is)
 _AID_T,  # RUN_T of the last velocity aiding measurement (-inf: none)
 _PEND,  # 3: velocity aiding measurement waiting for the next update (NaN: none)
 _PEND_AGE,  # its age at the update [s]
 _AID_DT,  # time between the last two velocity measurements [s]
 _MAG,  # 3: newest magnetometer reading of the period
 _MAG_W,  # 3: the body rate (bias removed) when it came [rad/s]
 _MAG_OK,  # 1 if _MAG holds one
 _MAG_PREV,  # 3: the previous magnetometer sample as given
 _MAG_TURN,  # how far the body has turned since that reading was first seen [rad]
 _MAG_DT,  # time since the last magnetometer update [s]
 _MAG_REJ_T,  # heading innovations rejected for this long [s]
 _FROM_SAMPLE,  # 1 until the first step after starting from one sample (see _first_step)
 _P_AIR,  # flight-state detector: probability that the vehicle is in the air
 _STILL_FROM_START,  # 1 while the body has been steady since the first sample
 _G_PREV,  # 3: the previous gyro sample as given
 _G_SAME_T,  # how long the gyro sample has stayed exactly the same [s]
 _H,  # scratch: measurement rows (3 × _NX)
 _PHT,  # scratch: P·Hᵀ (_NX × 3)
 _K,  # scratch: gain (_NX × 3)
 _X,  # scratch: error-state correction (_NX)
 _JA, _JB,  # scratch: Joseph form's I − K·H and (I − K·H)·P (_NX × _NX each)
 TAP,  # what the smoother needs of the last Kalman step (TAP_* below)
 _STATE_SIZE) = _layout(3, 1, _NX * _NX, 1, 1, 1, 3, 3, 3, 1, 3, 3, 3, 3, 3, 3, 1, 1, 1, 1,
                        1, 1, 1, 1, 1, 1, 1, 1, 1, 3, 1, 1, 3, 3, 1, 3, 1, 1, 1, 1, 1, 1, 3, 1,
                        3 * _NX, 3 * _NX, 3 * _NX, _NX, _NX * _NX, _NX * _NX,
                        15 + 2 * (11 + _NX * _NX))

# The tap (offsets in the TAP block): every Kalman step leaves here what a
# Rauch-Tung-Striebel pass over the recording needs (estimators.smoother), and the
# tapped driver copies it out; the online filter writes it and never reads it.
#: 1 once a Kalman step has written the tap (the tapped driver clears it).
TAP_FLAG = 0
#: 1 when the step re-anchored a state outside the Kalman update (velocity, heading):
#: the smoother does not carry corrections across it.
TAP_BREAK = 1
TAP_T = 2  # the update period [s]
TAP_R = 3  # 9: R (row-major) the prediction used
TAP_DV = 12  # 3: ∫R·f dt over the period (world)
#: nominal state after the prediction: q (4), b (3), v (3), μ, then P (_NX × _NX)
TAP_PRIOR = 15
TAP_NOMINAL = 11
#: the same after the step's updates
TAP_POST = TAP_PRIOR + TAP_NOMINAL + _NX * _NX
TAP_SIZE = TAP_POST + TAP_NOMINAL + _NX * _NX


@_core.kernel(inline="always")
def _pi(i: int, j: int) -> int:
    return _P + i * _NX + j


@_core.kernel
def _init_covariance(state: np.ndarray, params: np.ndarray) -> None:
    for k in range(_NX * _NX):
        state[_P + k] = 0.0
    for i in range(3):
        state[_pi(_TH + i, _TH + i)] = params[_I.tilt_init] ** 2
        state[_pi(_BI + i, _BI + i)] = params[_I.bias_init] ** 2
        state[_pi(_VE + i, _VE + i)] = params[_I.velocity_prior] ** 2
    state[_pi(_TH + 2, _TH + 2)] = params[_I.heading_init] ** 2
    if params[_I.drag] > 0.0:
        state[_pi(_MU, _MU)] = params[_I.drag_sigma_init] ** 2


@_core.kernel(inline="always")
def _rotation(state: np.ndarray) -> tuple:
    """R(q) row-major for the attitude in state[0:4]."""
    w, x, y, z = state[0], state[1], state[2], state[3]
    return (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


@_core.kernel
def _predict_covariance(state: np.ndarray, params: np.ndarray, T: float) -> None:
    """P ← F·P·Fᵀ + Q over one update period,
    F = I + [δθ ← −R·T·δb, δv ← −[ΔV]×·δθ].

    In place: the velocity rows/columns are updated first because they read the attitude
    rows/columns as they were; the attitude ones then read the (unchanged) bias ones."""
    r = _rotation(state)
    dvx, dvy, dvz = state[_DV], state[_DV + 1], state[_DV + 2]
    # [ΔV]× rows
    s0 = (0.0, -dvz, dvy)
    s1 = (dvz, 0.0, -dvx)
    s2 = (-dvy, dvx, 0.0)
    for c in range(_NX):  # rows: F·P
        t0, t1, t2 = state[_pi(0, c)], state[_pi(1, c)], state[_pi(2, c)]
        state[_pi(_VE, c)] -= s0[0] * t0 + s0[1] * t1 + s0[2] * t2
        state[_pi(_VE + 1, c)] -= s1[0] * t0 + s1[1] * t1 + s1[2] * t2
        state[_pi(_VE + 2, c)] -= s2[0] * t0 + s2[1] * t1 + s2[2] * t2
        b0, b1, b2 = state[_pi(3, c)], state[_pi(4, c)], state[_pi(5, c)]
        state[_pi(0, c)] -= T * (r[0] * b0 + r[1] * b1 + r[2] * b2)
        state[_pi(1, c)] -= T * (r[3] * b0 + r[4] * b1 + r[5] * b2)
        state[_pi(2, c)] -= T * (r[6] * b0 + r[7] * b1 + r[8] * b2)
    for i in range(_NX):  # columns: (F·P)·Fᵀ
        t0, t1, t2 = state[_pi(i, 0)], state[_pi(i, 1)], state[_pi(i, 2)]
        state[_pi(i, _VE)] -= s0[0] * t0 + s0[1] * t1 + s0[2] * t2
        state[_pi(i, _VE + 1)] -= s1[0] * t0 + s1[1] * t1 + s1[2] * t2
        state[_pi(i, _VE + 2)] -= s2[0] * t0 + s2[1] * t1 + s2[2] * t2
        b0, b1, b2 = state[_pi(i, 3)], state[_pi(i, 4)], state[_pi(i, 5)]
        state[_pi(i, 0)] -= T * (r[0] * b0 + r[1] * b1 + r[2] * b2)
        state[_pi(i, 1)] -= T * (r[3] * b0 + r[4] * b1 + r[5] * b2)
        state[_pi(i, 2)] -= T * (r[6] * b0 + r[7] * b1 + r[8] * b2)
    qa = params[_I.gyro_noise] ** 2 * T + params[_I.gyro_rate_noise] ** 2 * state[_TURN2]
    qb = params[_I.bias_rw] ** 2 * T
    qv = params[_I.velocity_rw] ** 2 * T
    for i in range(3):
        state[_pi(_TH + i, _TH + i)] += qa
        state[_pi(_BI + i, _BI + i)] += qb
        state[_pi(_VE + i, _VE + i)] += qv
    res = params[_I.gyro_resolution]
    if res > 0.0 and state[_G_SAME_T] >= params[_I.rest_time]:
        # A quantised gyro without noise (a simulator at rest) repeats one reading: the
        # bias under it is anywhere within a step of it (truncation: either side), and
        # no number of repeats narrows that, while the first vibration dithers the
        # quantiser and shows the bias as it is. Keep its variance at a step's².
        floor = res * res / 3.0
        for i in range(3):
            short = floor - state[_pi(_BI + i, _BI + i)]
            if short > 0.0:
                state[_pi(_BI + i, _BI + i)] += short


@_core.kernel
def _inject(state: np.ndarray, params: np.ndarray) -> None:
    """Fold the error-state correction in state[_X:] into the nominal state."""
    x = _X
    rx, ry, rz = state[x], state[x + 1], state[x + 2]
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle > 1e-12:
        s = math.sin(0.5 * angle) / angle
        cw, cx, cy, cz = math.cos(0.5 * angle), rx * s, ry * s, rz * s
        w, qx, qy, qz = state[0], state[1], state[2], state[3]
        state[0] = cw * w - cx * qx - cy * qy - cz * qz
        state[1] = cw * qx + cx * w + cy * qz - cz * qy
        state[2] = cw * qy - cx * qz + cy * w + cz * qx
        state[3] = cw * qz + cx * qy - cy * qx + cz * w
        _core.normalize_q(state)
    bmax = params[_I.bias_max]
    for j in range(3):
        b = state[_core.B0 + j] + state[x + _BI + j]
        state[_core.B0 + j] = min(max(b, -bmax), bmax)
        state[_V + j] += state[x + _VE + j]
    # μ is kept in logarithm: δλ = δ ln μ, so μ stays positive and a factor-two error is
    # as easy to correct in either direction; the clip keeps one bad step from wiping it out
    state[_MUS] *= math.exp(min(max(state[x + _MU], -1.0), 1.0))
    for j in range(_NX):
        state[x + j] = 0.0


@_core.kernel
def _tap_state(state: np.ndarray, at: int) -> None:
    """Nominal state and covariance into the tap at ``at``."""
    for j in range(4):
        state[at + j] = state[j]
    for j in range(3):
        state[at + 4 + j] = state[_core.B0 + j]
        state[at + 7 + j] = state[_V + j]
    state[at + 10] = state[_MUS]
    for j in range(_NX * _NX):
        state[at + TAP_NOMINAL + j] = state[_P + j]


@_core.kernel
def _tap_prediction(state: np.ndarray, T: float, r: tuple) -> None:
    """The prediction's ingredients (F = I + [δθ ← −R·T·δb, δv ← −[ΔV]×·δθ]) and the
    predicted state."""
    t = TAP
    state[t + TAP_T] = T
    for j in range(9):
        state[t + TAP_R + j] = r[j]
    for j in range(3):
        state[t + TAP_DV + j] = state[_DV + j]
    _tap_state(state, t + TAP_PRIOR)


@_core.kernel
def _joseph(state: np.ndarray, m: int, r0: float, r1: float, r2: float) -> None:
    """P ← (I − K·H)·P·(I − K·H)ᵀ + K·R·Kᵀ for a gain K that is not the optimal one
    (rows zeroed): the short form P − K·H·P only holds for the optimal gain."""
    for i in range(_NX):  # A = I − K·H
        for j in range(_NX):
            a = 1.0 if i == j else 0.0
            for r in range(m):
                a -= state[_K + i * 3 + r] * state[_H + r * _NX + j]
            state[_JA + i * _NX + j] = a
    for i in range(_NX):  # B = A·P
        for j in range(_NX):
            acc = 0.0
            for k in range(_NX):
                acc += state[_JA + i * _NX + k] * state[_pi(k, j)]
            state[_JB + i * _NX + j] = acc
    for i in range(_NX):  # P = B·Aᵀ + K·R·Kᵀ
        for j in range(i, _NX):
            acc = 0.0
            for k in range(_NX):
                acc += state[_JB + i * _NX + k] * state[_JA + j * _NX + k]
            acc += state[_K + i * 3] * r0 * state[_K + j * 3]
            if m > 1:
                acc += state[_K + i * 3 + 1] * r1 * state[_K + j * 3 + 1]
            if m > 2:
                acc += state[_K + i * 3 + 2] * r2 * state[_K + j * 3 + 2]
            state[_pi(i, j)] = acc
            state[_pi(j, i)] = acc


@_core.kernel
def _kalman_update(state: np.ndarray, params: np.ndarray, m: int, nu0: float, nu1: float,
                   nu2: float, r0: float, r1: float, r2: float, gate: float,
                   keep_heading: bool = False) -> bool:
    """Update with m ≤ 3 rows in state[_H:] (10 wide), innovation ν and diagonal noise R.

    Returns False (and changes nothing) when the innovation's chi-square exceeds ``gate``
    (gate ≤ 0: no test). The correction is injected at once. ``keep_heading``: the gain
    on the heading error δθ_z is zeroed (a measurement whose errors share another
    heading's, see _velocity_aiding), with the covariance in Joseph form."""
    for r in range(m):
        for i in range(_NX):
            acc = 0.0
            for j in range(_NX):
                h = state[_H + r * _NX + j]
                if h != 0.0:
                    acc += state[_pi(i, j)] * h
            state[_PHT + i * 3 + r] = acc
    # S = H·P·Hᵀ + R (symmetric, m ≤ 3)
    s00 = s01 = s02 = s11 = s12 = s22 = 0.0
    for j in range(_NX):
        h0 = state[_H + j]
        s00 += h0 * state[_PHT + j * 3]
        if m > 1:
            h1 = state[_H + _NX + j]
            s01 += h0 * state[_PHT + j * 3 + 1]
            s11 += h1 * state[_PHT + j * 3 + 1]
            if m > 2:
                h2 = state[_H + 2 * _NX + j]
                s02 += h0 * state[_PHT + j * 3 + 2]
                s12 += h1 * state[_PHT + j * 3 + 2]
                s22 += h2 * state[_PHT + j * 3 + 2]
    s00 += r0
    if m == 1:
        if s00 <= 0.0:
            return False
        i00, i01, i02, i11, i12, i22 = 1.0 / s00, 0.0, 0.0, 0.0, 0.0, 0.0
    elif m == 2:
        s11 += r1
        det = s00 * s11 - s01 * s01
        if det <= 0.0:
            return False
        i00, i01, i11 = s11 / det, -s01 / det, s00 / det
        i02 = i12 = i22 = 0.0
    else:
        s11 += r1
        s22 += r2
        c00 = s11 * s22 - s12 * s12
        c01 = s02 * s12 - s01 * s22
        c02 = s01 * s12 - s02 * s11
        det = s00 * c00 + s01 * c01 + s02 * c02
        if det <= 0.0:
            return False
        i00, i01, i02 = c00 / det, c01 / det, c02 / det
        i11 = (s00 * s22 - s02 * s02) / det
        i12 = (s02 * s01 - s00 * s12) / det
        i22 = (s00 * s11 - s01 * s01) / det
    # whitened innovation y = S⁻¹ν and the chi-square ν·y
    y0 = i00 * nu0 + i01 * nu1 + i02 * nu2
    y1 = i01 * nu0 + i11 * nu1 + i12 * nu2
    y2 = i02 * nu0 + i12 * nu1 + i22 * nu2
    d2 = nu0 * y0 + (nu1 * y1 if m > 1 else 0.0) + (nu2 * y2 if m > 2 else 0.0)
    if gate > 0.0 and not d2 <= gate:
        return False
    for i in range(_NX):
        p0, p1, p2 = state[_PHT + i * 3], state[_PHT + i * 3 + 1], state[_PHT + i * 3 + 2]
        if m == 1:
            p1 = p2 = 0.0
        elif m == 2:
            p2 = 0.0
        state[_K + i * 3] = p0 * i00 + p1 * i01 + p2 * i02
        state[_K + i * 3 + 1] = p0 * i01 + p1 * i11 + p2 * i12
        state[_K + i * 3 + 2] = p0 * i02 + p1 * i12 + p2 * i22
        state[_X + i] = p0 * y0 + p1 * y1 + p2 * y2
    if keep_heading:
        for r in range(3):
            state[_K + (_TH + 2) * 3 + r] = 0.0
        state[_X + _TH + 2] = 0.0
        _joseph(state, m, r0, r1, r2)
        _inject(state, params)
        return True
    # P ← P − K·(P·Hᵀ)ᵀ, symmetrised
    for i in range(_NX):
        for j in range(i, _NX):
            d = 0.0
            for r in range(m):
                d += state[_K + i * 3 + r] * state[_PHT + j * 3 + r]
            v = 0.5 * (state[_pi(i, j)] + state[_pi(j, i)]) - d
            state[_pi(i, j)] = v
            state[_pi(j, i)] = v
    _inject(state, params)
    return True


@_core.kernel(inline="always")
def _clear_rows(state: np.ndarray, m: int) -> None:
    for k in range(m * _NX):
        state[_H + k] = 0.0


@_core.kernel
def _reset_velocity(state: np.ndarray, vx: float, vy: float, vz: float, sigma: float) -> None:
    """Re-anchor the velocity (attitude untouched): v ← given, its correlations forgotten."""
    state[_V], state[_V + 1], state[_V + 2] = vx, vy, vz
    state[TAP + TAP_BREAK] = 1.0
    for i in range(3):
        for j in range(_NX):
            state[_pi(_VE + i, j)] = 0.0
            state[_pi(j, _VE + i)] = 0.0
        state[_pi(_VE + i, _VE + i)] = sigma * sigma
    state[_V_OK_T] = state[_core.RUN_T]


@_core.kernel
def _recover_velocity(state: np.ndarray, params: np.ndarray, r: tuple, aided: bool,
                      drag: bool) -> None:
    """Velocity information refused for velocity_reset_time: the filter is inconsistent
    (a wrong start, a vehicle that left the bounded-velocity world, a GPS that jumped), so
    the velocity is re-anchored to what the information says and the tilt's variance is
    raised by its initial value, so that the information is taken again and can correct
    the tilt instead of being refused for ever."""
    if aided and (math.isfinite(state[_PEND]) or math.isfinite(state[_PEND + 1])
                  or math.isfinite(state[_PEND + 2])):
        vx = state[_PEND] if math.isfinite(state[_PEND]) else state[_V]
        vy = state[_PEND + 1] if math.isfinite(state[_PEND + 1]) else state[_V + 1]
        vz = state[_PEND + 2] if math.isfinite(state[_PEND + 2]) else state[_V + 2]
        sigma = params[_I.vel_aid_noise]
    elif drag and state[_MUS] > 0.0 and state[_FB_T] > 0.0:
        # the body velocity the drag reading implies (vertical kept), back to the world
        ux = -state[_FB] / state[_FB_T] / state[_MUS]
        uy = -state[_FB + 1] / state[_FB_T] / state[_MUS]
        uz = r[2] * state[_V] + r[5] * state[_V + 1] + r[8] * state[_V + 2]
        vx = r[0] * ux + r[1] * uy + r[2] * uz
        vy = r[3] * ux + r[4] * uy + r[5] * uz
        vz = r[6] * ux + r[7] * uy + r[8] * uz
        sigma = params[_I.vertical_velocity_prior]
    else:
        vx = vy = vz = 0.0
        sigma = params[_I.velocity_prior]
    _reset_velocity(state, vx, vy, vz, sigma)
    tilt = params[_I.tilt_init] ** 2
    state[_pi(_TH, _TH)] += tilt
    state[_pi(_TH + 1, _TH + 1)] += tilt


@_core.kernel
def _velocity_aiding(state: np.ndarray, params: np.ndarray, T: float, r: tuple) -> bool:
    """Fuse the pending velocity measurement; True if it was used."""
    age = state[_PEND_AGE]
    grav = params[_I.gravity]
    # v at the measurement's time ≈ v − age·(R·f̄ + g)
    ax = state[_DV] / T
    ay = state[_DV + 1] / T
    az = state[_DV + 2] / T + grav
    m = 0
    nu0 = nu1 = nu2 = 0.0
    _clear_rows(state, 3)
    for i in range(3):
        z = state[_PEND + i]
        if math.isfinite(z):
            a_i = ax if i == 0 else (ay if i == 1 else az)
            nu = z - (state[_V + i] - age * a_i)
            state[_H + m * _NX + _VE + i] = 1.0
            if m == 0:
                nu0 = nu
            elif m == 1:
                nu1 = nu
            else:
                nu2 = nu
            m += 1
    if m == 0:
        return False
    rn = params[_I.vel_aid_noise] ** 2
    if params[_I.aid_density] > 0.0:
        rn = params[_I.aid_density] ** 2 / min(max(state[_AID_DT], T), params[_I.aid_timeout])
    return _kalman_update(state, params, m, nu0, nu1, nu2, rn, rn, rn, _GATE[m],
                          params[_I.aid_heading] <= 0.0)


@_core.kernel
def _drag_update(state: np.ndarray, params: np.ndarray, T: float, r: tuple) -> bool:
    """Rotor drag: f̄_xy = −μ·(Rᵀv)_xy, linearised in δθ, δv and δλ = δ ln μ."""
    vx, vy, vz = state[_V], state[_V + 1], state[_V + 2]
    mu = state[_MUS]
    # body velocity u = Rᵀv; with R_true = (I + [δθ]×)R: u_true = u + Rᵀ[v]×δθ
    ux = r[0] * vx + r[3] * vy + r[6] * vz
    uy = r[1] * vx + r[4] * vy + r[7] * vz
    # rows of Rᵀ[v]×: Rᵀ column k dotted with [v]× columns
    # [v]× = [[0,-vz,vy],[vz,0,-vx],[-vy,vx,0]]
    _clear_rows(state, 2)
    for row in range(2):
        c0, c1, c2 = r[row], r[3 + row], r[6 + row]  # column `row` of R = row of Rᵀ
        j0 = c1 * vz - c2 * vy
        j1 = -c0 * vz + c2 * vx
        j2 = c0 * vy - c1 * vx
        base = _H + row * _NX
        state[base + _TH] = -mu * j0
        state[base + _TH + 1] = -mu * j1
        state[base + _TH + 2] = -mu * j2
        state[base + _VE] = -mu * c0
        state[base + _VE + 1] = -mu * c1
        state[base + _VE + 2] = -mu * c2
        state[base + _MU] = -mu * (ux if row == 0 else uy)  # ∂f/∂ln μ
    fx, fy = state[_FB] / state[_FB_T], state[_FB + 1] / state[_FB_T]
    rn = params[_I.drag_noise] ** 2 / T
    return _kalman_update(state, params, 2, fx + mu * ux, fy + mu * uy, 0.0, rn, rn, 0.0,
                          _GATE[2], params[_I.drag_heading] <= 0.0)


@_core.kernel
def _velocity_prior(state: np.ndarray, params: np.ndarray, T: float, sigma: float,
                    axes: int, weaken: bool = False) -> bool:
    """Pseudo-measurement v ≈ 0 on the last ``axes`` axes (3: all, 1: vertical).
    ``weaken``: by the speed (``velocity_scale``), so that a vehicle moving fast is not
    pulled level; not at rest, where nothing accelerates and a velocity left over from a
    knock must be refused (and then re-anchored) rather than kept."""
    _clear_rows(state, axes)
    first = 3 - axes
    for k in range(axes):
        state[_H + k * _NX + _VE + first + k] = 1.0
    rn = sigma * sigma / T
    if axes == 1:
        return _kalman_update(state, params, 1, -state[_V + 2], 0.0, 0.0, rn, 0.0, 0.0,
                              _GATE[1])
    scale = params[_I.velocity_scale]
    v2 = state[_V] ** 2 + state[_V + 1] ** 2 + state[_V + 2] ** 2
    tau = params[_I.velocity_scale_tau]
    if tau > 0.0:
        state[_SPEED2] += (1.0 - math.exp(-T / tau)) * (v2 - state[_SPEED2])
        v2 = state[_SPEED2]
    if weaken:
        rn *= 1.0 + v2 / (scale * scale)
    return _kalman_update(state, params, 3, -state[_V], -state[_V + 1], -state[_V + 2],
                          rn, rn, rn, _GATE[3])


@_core.kernel
def _mag_disturbed(state: np.ndarray, params: np.ndarray, norm: float, dip: float,
                   T: float) -> bool:
    """Field norm/dip against the learned reference; True while disturbed."""
    kc = 1.0 - math.exp(-T / params[_I.mag_ref_tau])
    nth, dth = params[_I.mag_norm_th], params[_I.mag_dip_th]
    if state[_MN_C] <= 0.0:
        state[_MN_C], state[_MD_C] = norm, dip
    if abs(norm - state[_MN_C]) < nth * state[_MN_C] and abs(dip - state[_MD_C]) < dth:
        state[_CAND_T] += T
        state[_MN_C] += kc * (norm - state[_MN_C])
        state[_MD_C] += kc * (dip - state[_MD_C])
    else:
        state[_MN_C], state[_MD_C], state[_CAND_T] = norm, dip, 0.0
    if state[_REF_OK] < 1.0:
        if state[_CAND_T] >= params[_I.mag_ref_time]:
            state[_MN_REF], state[_MD_REF] = state[_MN_C], state[_MD_C]
            state[_REF_OK] = 1.0
            return False
        # Until then, a field that has been consistent for a moment is a provisional
        # reference: a magnet near the vehicle in its first seconds is a disturbance too.
        if state[_REF_OK] <= 0.0 and state[_CAND_T] >= params[_I.mag_provisional_time]:
            state[_MN_REF], state[_MD_REF] = state[_MN_C], state[_MD_C]
            state[_REF_OK] = 0.5
        if state[_REF_OK] <= 0.0:
            return False
        disturbed = abs(norm - state[_MN_REF]) > nth * state[_MN_REF] or \
            abs(dip - state[_MD_REF]) > dth
        if not disturbed:
            state[_MN_REF], state[_MD_REF] = state[_MN_C], state[_MD_C]
        return disturbed
    disturbed = abs(norm - state[_MN_REF]) > nth * state[_MN_REF] or \
        abs(dip - state[_MD_REF]) > dth
    if disturbed and state[_CAND_T] >= params[_I.mag_new_time]:
        state[_MN_REF], state[_MD_REF] = state[_MN_C], state[_MD_C]
        disturbed = False
    if not disturbed:
        state[_MN_REF] += kc * (norm - state[_MN_REF])
        state[_MD_REF] += kc * (dip - state[_MD_REF])
    return disturbed


@_core.kernel(inline="always")
def _mag_reading_now(state: np.ndarray, params: np.ndarray) -> tuple:
    """The period's reading where the field is in the body now. One mag_delay old, it
    saw the body as it was then, m = R(t − τ)ᵀ·m_w = exp(τ[ω]×)·R(t)ᵀ·m_w: turned by
    −τ·ω (the rate when it came). Done here, once per update, not on every sample."""
    mx, my, mz = state[_MAG], state[_MAG + 1], state[_MAG + 2]
    wx, wy, wz = state[_MAG_W], state[_MAG_W + 1], state[_MAG_W + 2]
    rate = math.sqrt(wx * wx + wy * wy + wz * wz)
    angle = params[_I.mag_delay] * rate  # < 0: a reading newer than the gyro, turned on
    if abs(angle) <= 1e-12:
        return mx, my, mz
    kx, ky, kz = wx / rate, wy / rate, wz / rate
    c, s = math.cos(angle), -math.sin(angle)
    kdot = (kx * mx + ky * my + kz * mz) * (1.0 - c)
    return (mx * c + (ky * mz - kz * my) * s + kx * kdot,
            my * c + (kz * mx - kx * mz) * s + ky * kdot,
            mz * c + (kx * my - ky * mx) * s + kz * kdot)


@_core.kernel
def _heading_update(state: np.ndarray, params: np.ndarray, T: float) -> None:
    """Heading-only magnetometer update (gain on the tilt errors zeroed, Joseph form)."""
    state[_core.MAG_REJ] = 0.0
    mx, my, mz = _mag_reading_now(state, params)
    ex, ey, ez = _core.body_to_world(state, mx, my, mz)
    horiz = math.sqrt(ex * ex + ey * ey)
    norm = math.sqrt(horiz * horiz + ez * ez)
    if horiz < 1e-9 * (norm + 1e-300):
        return
    if _mag_disturbed(state, params, norm, math.atan2(ez, horiz), T):
        state[_core.MAG_REJ] = 1.0
        return
    nu = -math.atan2(ey, ex)  # magnetic north is +x: the field's heading is the error
    # noise density over the time this reading stands for (one per update at most)
    rn = params[_I.mag_noise] ** 2 / max(state[_MAG_DT], T)
    state[_MAG_DT] = 0.0
    p22 = state[_pi(2, 2)]
    s = p22 + rn
    if nu * nu > _GATE[1] * s:
        state[_core.MAG_REJ] = 1.0
        state[_MAG_REJ_T] += T
        if state[_MAG_REJ_T] > params[_I.mag_reset_time]:
            _reset_heading(state, params, nu)
        return
    state[_MAG_REJ_T] = 0.0
    # K = P[:, 2]/s with K[0] = K[1] = 0; P ← (I − K e₂ᵀ) P (I − K e₂ᵀ)ᵀ + K·r·Kᵀ,
    # from a copy c of column 2 (= row 2) since P is overwritten in place.
    for i in range(_NX):
        c = state[_pi(i, 2)]
        state[_PHT + i] = c
        state[_K + i] = 0.0 if i < 2 else c / s
        state[_X + i] = state[_K + i] * nu
    for i in range(_NX):
        ki, ci = state[_K + i], state[_PHT + i]
        for j in range(i, _NX):
            kj, cj = state[_K + j], state[_PHT + j]
            v = state[_pi(i, j)] - ki * cj - kj * ci + ki * kj * s
            state[_pi(i, j)] = v
            state[_pi(j, i)] = v
    _inject(state, params)


@_core.kernel
def _reset_heading(state: np.ndarray, params: np.ndarray, nu: float) -> None:
    """Turn to the magnetometer's heading and forget the heading's correlations: an
    undisturbed field (norm and dip as learned) that has disagreed for
    ``mag_reset_time`` means our heading is wrong, not the field (a gyro-bias step)."""
    for j in range(_NX):
        state[_X + j] = 0.0
        state[_pi(2, j)] = 0.0
        state[_pi(j, 2)] = 0.0
    state[_pi(2, 2)] = params[_I.heading_init] ** 2
    state[_X + 2] = nu
    _inject(state, params)
    state[TAP + TAP_BREAK] = 1.0
    state[_MAG_REJ_T] = 0.0


@_core.kernel(inline="always")
def _rest_detection(state: np.ndarray, params: np.ndarray, gx: float, gy: float,
                    gz: float, ax: float, ay: float, az: float, acc_ok: bool,
                    dt: float) -> None:
    """VQF's rest test, on pre-filtered samples: motor vibration (tens of Hz) is not
    motion of the vehicle and must not hide its rest."""
    k = 1.0 - math.exp(-dt / params[_I.rest_tau])
    kp = 1.0 - math.exp(-dt / params[_I.rest_prefilter_tau])
    if state[_LP_OK] <= 0.0:
        for j in range(3):
            g = (gx, gy, gz)[j]
            state[_GPF + j] = state[_GLP + j] = g
        if acc_ok:
            for j in range(3):
                a = (ax, ay, az)[j]
                state[_APF + j] = state[_ALP + j] = a
            state[_LP_OK] = 1.0
    dg = 0.0
    for j in range(3):
        state[_GPF + j] += kp * ((gx, gy, gz)[j] - state[_GPF + j])
        state[_GLP + j] += k * (state[_GPF + j] - state[_GLP + j])
        dg += (state[_GPF + j] - state[_GLP + j]) ** 2
    # The low-passed gyro must be near the bias estimate (VQF's bias clip: a steady slow
    # turn is not rest), unless the magnetometer shows the body is not turning: then
    # any offset an uncalibrated gyro may have (bias_max) is taken for what it is.
    lim = params[_I.bias_max] if state[_MAG_STEADY] > 0.0 else params[_I.rest_bias_th]
    steady = acc_ok and state[_LP_OK] > 0.0 and dg < params[_I.rest_gyr_th] ** 2 \
        and abs(state[_GLP] - state[_core.B0]) < lim \
        and abs(state[_GLP + 1] - state[_core.B0 + 1]) < lim \
        and abs(state[_GLP + 2] - state[_core.B0 + 2]) < lim
    if acc_ok:
        da = 0.0
        for j in range(3):
            state[_APF + j] += kp * ((ax, ay, az)[j] - state[_APF + j])
            state[_ALP + j] += k * (state[_APF + j] - state[_ALP + j])
            da += (state[_APF + j] - state[_ALP + j]) ** 2
        steady = steady and da < params[_I.rest_acc_th] ** 2
    state[_REST_T] = state[_REST_T] + dt if steady else 0.0
    if not steady and state[_LP_OK] > 0.0:
        state[_STILL_FROM_START] = 0.0


@_core.kernel(inline="always")
def _mag_steadiness(state: np.ndarray, params: np.ndarray, mx: float, my: float, mz: float,
                    mag_ok: bool, dt: float) -> None:
    """Whether the field's direction in the body has stayed put (pre-filtered, against
    its low-pass, like the rest test): the one sensor that sees a turn about the
    vertical without trusting the gyro."""
    if not mag_ok:
        state[_MAG_STEADY] = 0.0
        return
    n = math.sqrt(mx * mx + my * my + mz * mz)
    ux, uy, uz = mx / n, my / n, mz / n
    k = 1.0 - math.exp(-dt / params[_I.rest_tau])
    kp = 1.0 - math.exp(-dt / params[_I.rest_prefilter_tau])
    if state[_MLP] == 0.0 and state[_MLP + 1] == 0.0 and state[_MLP + 2] == 0.0:
        for j in range(3):
            state[_MPF + j] = state[_MLP + j] = (ux, uy, uz)[j]
    d2 = 0.0
    for j in range(3):
        state[_MPF + j] += kp * ((ux, uy, uz)[j] - state[_MPF + j])
        state[_MLP + j] += k * (state[_MPF + j] - state[_MLP + j])
        d2 += (state[_MPF + j] - state[_MLP + j]) ** 2
    state[_MAG_STEADY] = 1.0 if d2 < params[_I.rest_mag_th] ** 2 else 0.0


@_core.kernel
def _rest_update(state: np.ndarray, params: np.ndarray, T: float, aided: bool,
                 still: bool) -> None:
    """At rest the vehicle is not accelerating, so the mean specific force is gravity: a
    tilt measurement (rest holds only while the specific force is steady, and a
    multirotor's changes with its speed through rotor drag, so a steady cruise qualifies
    too — it is not accelerating either; a vehicle with aiding leaves this to its
    measured velocity — a steady specific force is also what a sustained acceleration
    gives — unless the drag model runs: a flying multirotor's specific force changes
    with its speed, so steady means not accelerating). Not a zero-velocity update: that
    cruise is not standing still. ``aided`` is False while the body has been still since
    the estimator started: powered up at rest, it is not accelerating.

    ``still`` (not flying): the low-passed gyro is also the bias. A flying vehicle is
    never held still: a steady gyro in a hover is a slow yaw or the position hold's
    corrections as much as a bias, and taking it for the bias turns that motion into
    attitude error; in the air the bias is left to the drag model, the aiding and the
    magnetometer."""
    if still:
        _clear_rows(state, 3)
        for i in range(3):
            state[_H + i * _NX + _BI + i] = 1.0
        rn = params[_I.rest_noise] ** 2 / T
        _kalman_update(state, params, 3, state[_GLP] - state[_core.B0],
                       state[_GLP + 1] - state[_core.B0 + 1],
                       state[_GLP + 2] - state[_core.B0 + 2], rn, rn, rn, 0.0)
    if aided:
        return  # the measured velocity knows better whether it is accelerating
    # world-frame mean specific force: R̂·f̄ = (g·δθ_y, −g·δθ_x, −g) for a tilt error δθ
    ft = state[_FB_T]
    fx, fy, fz = state[_FB] / ft, state[_FB + 1] / ft, state[_FB + 2] / ft
    wx, wy, _ = _core.body_to_world(state, fx, fy, fz)
    grav = params[_I.gravity]
    _clear_rows(state, 2)
    state[_H + _TH + 1] = grav
    state[_H + _NX + _TH] = -grav
    rn = params[_I.rest_gravity_noise] ** 2 / T
    _kalman_update(state, params, 2, wx, wy, 0.0, rn, rn, 0.0, _GATE[2])


@_core.kernel
def _drag_model_on(state: np.ndarray, params: np.ndarray, T: float, r: tuple) -> bool:
    """Whether the rotor-drag model holds now: only for a multirotor (``drag`` > 0) in
    the air. On the ground, on a bench or carried by hand its accelerometer sees gravity
    and the hand's pushes, and the drag model would read the tilt as a speed.

    The vehicle's own word wins (``set_flight_state``). Without it a two-state hidden
    Markov model decides: "in the air" predicts a horizontal specific force that is
    rotor drag, ``−μ·u_xy``; "on the ground" predicts gravity seen through the
    attitude, ``(Rᵀ·(0, 0, −g))_xy``. The two differ only while the body is tilted,
    which is when the choice matters; the evidence of each period is the Gaussian
    log-likelihood ratio of the mean specific force under the two predictions, counted
    once per ``flight_evidence_time`` (what strays from either prediction — a hand's
    push, drag-model error — lasts that long), and the chain switches state at a rate
    of one per ``flight_switch_time``. The chain starts on the ground (a vehicle is
    powered up there), and a tie stays on the ground, where the model is the one that
    never needs the vehicle to fly."""
    if params[_I.drag] <= 0.0:
        state[_core.AIR_MODEL] = 0.0
        return False
    if state[_FB_T] > 0.0:
        ft = state[_FB_T]
        fx, fy = state[_FB] / ft, state[_FB + 1] / ft
        grav = params[_I.gravity]
        gx, gy = -grav * r[6], -grav * r[7]  # (Rᵀ·(0, 0, −g))_xy
        vx, vy, vz = state[_V], state[_V + 1], state[_V + 2]
        mu = state[_MUS]
        dx = -mu * (r[0] * vx + r[3] * vy + r[6] * vz)
        dy = -mu * (r[1] * vx + r[4] * vy + r[7] * vz)
        e_ground = (fx - gx) ** 2 + (fy - gy) ** 2
        e_air = (fx - dx) ** 2 + (fy - dy) ** 2
        llr = (e_ground - e_air) / (2.0 * params[_I.flight_accel_noise] ** 2) * \
            min(T / params[_I.flight_evidence_time], 1.0)
        eps = min(T / params[_I.flight_switch_time], 0.5)
        p = state[_P_AIR] * (1.0 - eps) + (1.0 - state[_P_AIR]) * eps
        llr = max(min(llr, 50.0), -50.0)
        odds = p / (1.0 - p) * math.exp(llr)
        state[_P_AIR] = min(max(odds / (1.0 + odds), 1e-12), 1.0 - 1e-12)
    given = state[_core.FLIGHT]
    on = state[_P_AIR] > 0.5 if given == _core.FLIGHT_UNKNOWN else given == _core.FLIGHT_AIRBORNE
    state[_core.AIR_MODEL] = 1.0 if on else 0.0
    return on


@_core.kernel
def _kalman_step(state: np.ndarray, params: np.ndarray, T: float) -> None:
    """Everything done once per update period."""
    r = _rotation(state)
    _predict_covariance(state, params, T)
    _tap_prediction(state, T, r)
    state[_core.ACC_REJ] = 0.0
    if state[_FB_T] <= 0.0:
        # Nothing measured the specific force: the velocity says nothing about the tilt.
        _reset_velocity(state, state[_V], state[_V + 1], state[_V + 2],
                        math.sqrt(max(state[_pi(_VE, _VE)], 0.0)) + params[_I.velocity_prior])
        state[_PEND] = state[_PEND + 1] = state[_PEND + 2] = math.nan
        state[_core.ACC_REJ] = 1.0
    now = state[_core.RUN_T]
    aided = now - state[_AID_T] <= params[_I.aid_timeout]
    # (steady since the first sample: at rest without the wait, see the module doc)
    powered_up_still = state[_STILL_FROM_START] > 0.0 and state[_REST_T] > 0.0
    at_rest = state[_REST_T] >= params[_I.rest_time] or powered_up_still
    drag = _drag_model_on(state, params, T, r)
    if at_rest:
        flying = drag or state[_core.FLIGHT] == _core.FLIGHT_AIRBORNE
        _rest_update(state, params, T, aided and not drag and not powered_up_still,
                     not flying and state[_REST_T] >= params[_I.rest_time])
        r = _rotation(state)
    else:
        state[_REST_ANCHORED] = 0.0
    if state[_FB_T] > 0.0:
        # Velocity information: aiding, rotor drag, or the bounded-velocity prior.
        if math.isfinite(state[_PEND]) or math.isfinite(state[_PEND + 1]) or \
                math.isfinite(state[_PEND + 2]):
            if _velocity_aiding(state, params, T, r):
                state[_V_OK_T] = now
            else:
                state[_core.ACC_REJ] = 1.0
            r = _rotation(state)
        if drag:
            # (at rest a multirotor stands on the ground or hovers: no drag to read)
            if at_rest or _drag_update(state, params, T, r):
                state[_V_OK_T] = now
            else:
                state[_core.ACC_REJ] = 1.0
            if not aided:
                _velocity_prior(state, params, T, params[_I.vertical_velocity_prior], 1)
        elif not aided or state[_core.FLIGHT] == _core.FLIGHT_GROUND or (
                state[_core.FLIGHT] == _core.FLIGHT_UNKNOWN and params[_I.drag] > 0.0):
            # On the ground a vehicle moves at walking pace at most, whatever a GPS says;
            # a multirotor whose state nobody tells is on the ground when the data says so
            # (the drag model is off): an autopilot's velocity is least trustworthy in
            # the seconds before it reports its state, while its own filter settles.
            if _velocity_prior(state, params, T, params[_I.velocity_prior], 3, not at_rest):
                state[_V_OK_T] = now
            else:
                state[_core.ACC_REJ] = 1.0
                if at_rest and state[_REST_ANCHORED] <= 0.0:
                    # A body at rest does not move: a velocity refused as the rest begins
                    # is what a knock or a fast motion left in the integral, not a tilt,
                    # so it is re-anchored now instead of after velocity_reset_time.
                    _recover_velocity(state, params, r, aided, drag)
                    state[_REST_ANCHORED] = 1.0
        if now - state[_V_OK_T] > params[_I.velocity_reset_time]:
            _recover_velocity(state, params, _rotation(state), aided, drag)
    state[_PEND] = state[_PEND + 1] = state[_PEND + 2] = math.nan
    if state[_MAG_OK] > 0.0:
        _heading_update(state, params, T)
        state[_MAG_OK] = 0.0
    else:
        state[_core.MAG_REJ] = 0.0
    _tap_state(state, TAP + TAP_POST)
    state[TAP + TAP_FLAG] = 1.0


@_core.kernel
def _first_step(state: np.ndarray, params: np.ndarray, mx: float, my: float, mz: float,
                mag_ok: bool) -> None:
    """After starting from one accelerometer + magnetometer sample, the heading error is
    not independent of the tilt error: the start takes the heading that puts the field's
    east component at zero, so a tilt error δθ_N about north turns the heading by
    tan(dip)·δθ_N. Putting that correlation into P lets every later tilt correction fix
    the heading with it (a vibrating first sample: 14° of tilt became 24° of heading)."""
    state[_FROM_SAMPLE] = 0.0
    if not mag_ok:
        return
    en, ee, ed = _core.body_to_world(state, mx, my, mz)
    horiz = math.sqrt(en * en + ee * ee)
    if horiz < 1e-9 * (abs(ed) + 1e-300):
        return
    k = ed / horiz  # tan(dip)
    p00 = state[_pi(_TH, _TH)]
    state[_pi(_TH, _TH + 2)] += k * p00
    state[_pi(_TH + 2, _TH)] += k * p00
    state[_pi(_TH + 2, _TH + 2)] += k * k * p00


@_core.kernel
def _step(state, params, gx, gy, gz, ax, ay, az, mx, my, mz, acc_ok, mag_ok, dt,
          vx, vy, vz, v_age) -> None:
    if state[_FROM_SAMPLE] > 0.0:
        _first_step(state, params, mx, my, mz, mag_ok)
    b0, b1, b2 = state[_core.B0], state[_core.B0 + 1], state[_core.B0 + 2]
    turn2 = (gx - b0) ** 2 + (gy - b1) ** 2 + (gz - b2) ** 2  # |ω − b|²
    grav = params[_I.gravity]
    if acc_ok:
        state[_FB] += ax * dt
        state[_FB + 1] += ay * dt
        state[_FB + 2] += az * dt
        state[_FB_T] += dt
        _core.integrate_exact(state, gx - b0, gy - b1, gz - b2, dt)
        # velocity: trapezoid of the world-frame specific force of this and the last
        # sample, each rotated with the attitude it was measured at
        f1x, f1y, f1z = _core.body_to_world(state, ax, ay, az)
        if state[_FW_OK] > 0.0:
            fx = 0.5 * (state[_FW] + f1x)
            fy = 0.5 * (state[_FW + 1] + f1y)
            fz = 0.5 * (state[_FW + 2] + f1z)
        else:
            fx, fy, fz = f1x, f1y, f1z
        state[_FW], state[_FW + 1], state[_FW + 2] = f1x, f1y, f1z
        state[_FW_OK] = 1.0
    else:
        # No usable specific force (NaN, saturated): the gyro alone carries the attitude;
        # a period without any usable sample makes no velocity statement (_kalman_step).
        _core.integrate_exact(state, gx - b0, gy - b1, gz - b2, dt)
        fx, fy, fz = 0.0, 0.0, -grav
        state[_FW_OK] = 0.0
    state[_V] += fx * dt
    state[_V + 1] += fy * dt
    state[_V + 2] += (fz + grav) * dt
    state[_DV] += fx * dt
    state[_DV + 1] += fy * dt
    state[_DV + 2] += fz * dt
    state[_ACC_T] += dt
    state[_TURN2] += turn2 * dt
    _mag_steadiness(state, params, mx, my, mz, mag_ok, dt)
    _rest_detection(state, params, gx, gy, gz, ax, ay, az, acc_ok, dt)
    if gx == state[_G_PREV] and gy == state[_G_PREV + 1] and gz == state[_G_PREV + 2]:
        state[_G_SAME_T] += dt
    else:
        state[_G_SAME_T] = 0.0
        state[_G_PREV], state[_G_PREV + 1], state[_G_PREV + 2] = gx, gy, gz
    state[_MAG_DT] += dt
    if mag_ok:
        # A magnetometer slower than the IMU is often repeated in every IMU message
        # (RAW_IMU): a repeat describes the body as it was when the reading was taken,
        # so it is used only while the body has not turned since.
        if mx == state[_MAG_PREV] and my == state[_MAG_PREV + 1] and mz == state[_MAG_PREV + 2]:
            state[_MAG_TURN] += math.sqrt(turn2) * dt
        else:
            state[_MAG_TURN] = 0.0
            state[_MAG_PREV], state[_MAG_PREV + 1], state[_MAG_PREV + 2] = mx, my, mz
        if state[_MAG_TURN] <= _MAG_STALE_RAD:
            state[_MAG], state[_MAG + 1], state[_MAG + 2] = mx, my, mz
            state[_MAG_W], state[_MAG_W + 1], state[_MAG_W + 2] = gx - b0, gy - b1, gz - b2
            state[_MAG_OK] = 1.0
    if math.isfinite(vx) or math.isfinite(vy) or math.isfinite(vz):
        state[_PEND], state[_PEND + 1], state[_PEND + 2] = vx, vy, vz
        state[_PEND_AGE] = v_age
        state[_AID_DT] = state[_core.RUN_T] - state[_AID_T]
        state[_AID_T] = state[_core.RUN_T]
    elif math.isfinite(state[_PEND]) or math.isfinite(state[_PEND + 1]) or \
            math.isfinite(state[_PEND + 2]):
        state[_PEND_AGE] += dt  # a measurement waiting for the update grows older
    if state[_ACC_T] + 1e-9 * dt < params[_I.update_period]:
        return
    T = state[_ACC_T]
    _kalman_step(state, params, T)
    state[_ACC_T] = 0.0
    state[_TURN2] = 0.0
    state[_FB_T] = 0.0
    for j in range(3):
        state[_DV + j] = 0.0
        state[_FB + j] = 0.0


@register
class Eskf(Estimator):
    """Multiplicative error-state Kalman filter: attitude, gyro bias, velocity (and a
    multirotor's drag coefficient) in one filter; velocity aiding, rotor drag or a
    bounded-velocity prior correct the tilt, the magnetometer only the heading."""

    name = "eskf"
    Params = EskfParams
    _state_size = _STATE_SIZE
    _update_one, _run_batch = (staticmethod(k) for k in
                               _core.make_kernels(_step, takes_velocity=True))

    def _pack_params(self, p: EskfParams) -> np.ndarray:
        packed = np.array([float(getattr(p, f)) for f in _PARAM_FIELDS])
        # The filter lives at the gyro's time, imu_delay behind now; a magnetometer that
        # is not low-passed with the gyro (ArduPilot's compass) is that much newer than it.
        packed[_I.mag_delay] = p.mag_delay - p.imu_delay
        return packed

    def _init_private(self, state: np.ndarray, p: EskfParams) -> None:
        _init_covariance(state, self._params_vec)
        state[_FROM_SAMPLE] = 0.0 if state[_core.INIT] > 0.0 else 1.0  # no q0 given
        state[_MUS] = p.drag
        state[_AID_T] = -math.inf
        state[_PEND:_PEND + 3] = math.nan
        state[_P_AIR] = P_AIR_AT_START
        state[_STILL_FROM_START] = 1.0
        state[_G_PREV:_G_PREV + 3] = math.nan

    @property
    def velocity(self) -> np.ndarray:
        """The filter's velocity [m/s], internal frame (magnetic NED)."""
        return self._state[_V:_V + 3].copy()

    @property
    def covariance(self) -> np.ndarray:
        """Covariance of the error state [δθ (world), δb, δv, δλ = δ ln μ], 10×10."""
        return self._state[_P:_P + _NX * _NX].reshape(_NX, _NX).copy()

    @property
    def drag_coefficient(self) -> float:
        """The multirotor drag coefficient μ [1/s] (0 when the drag model is off)."""
        return float(self._state[_MUS])
