"""The navigation EKF: IMU-driven prediction, optical displacement, airspeed, sideslip, angle-of-attack, baro and GNSS
updates.

Usage (every method documents its units; frames as in :mod:`gsoe`)::

    ekf = NavEkf(cfg, t_us=t0, pos_ned_m=p0, vel_ned_m_s=v0)      # fully configured when built
    ekf.predict(imu, att)                 # every IMU sample, with the AHRS attitude valid at (about) imu.t_us
    ekf.fuse_airspeed(t_us, tas_m_s)      # whenever a sample arrives, in any order within the fusion delay
    ekf.fuse_baro(t_us, alt_m)
    ekf.fuse_gnss(t_us, pos_ned_m, vel_ned_m_s)
    ekf.fuse_optical(step)                # every common.samples.GsoeStep, including the new-cycle (base) steps
    est = ekf.estimate()                  # NavEstimate with one-sigma uncertainties and a validity flag
    st = ekf.status()                     # per aid source: innovation, variance, test ratio, fused/rejected

Numerical core
    filterpy's :class:`~filterpy.kalman.ExtendedKalmanFilter` holds ``x`` and ``P`` and does the covariance
    prediction ``P = F P F' + Q``; its documented extension point ``predict_x`` runs our (nonlinear) mean
    propagation and sets ``F`` (written in place into one preallocated matrix: only its IMU-dependent entries
    change).  The update is ours, because filterpy's inverts ``S`` and has no gating; it works on the filterpy
    object's ``x`` and ``P`` arrays directly (the hot path: about 150 updates per second, where every NumPy call
    costs 1-3 µs whatever its size, so the count of calls is the cost).  The NIS is gated against a named threshold.
    The covariance is the Joseph form ``(I - K H) P (I - K H)' + K R K'`` of the gain actually used, which with the
    partial-update gain ``K = D K_opt`` (below; ``D = diag(g)``) expands exactly to ``P - A o G`` with
    ``A = P H' S^-1 H P`` and ``G_ij = 1 - (1 - g_i)(1 - g_j)``: the optimal-gain update everywhere except the
    block of the partial-update states.  ``A = L L'`` is formed from
    ``L = P H' C^-T`` (``S = C C'``, Cholesky in closed form for the scalar, 2-D and GNSS updates), so the
    update is two small products and a subtraction, and ``P`` stays symmetric to the last bit (``L L'`` is, with
    every BLAS that sums each entry's products in one order; the prediction symmetrises in any case).  Nothing is
    committed unless the update's factors are finite (the prior is kept otherwise).  When an innovation variance
    falls below its observation variance (``H P H' < 0``: ``P`` has lost positive definiteness) the states the
    measurement touches get their initial covariance back and the measurement is skipped (PX4 EKF2).

Prediction
    ``v' = R_z(-yaw_bias) R_nb_ahrs (I + [omega_b x] att_delay) (f_b - accel_bias_b) + g_n`` and ``p' = v``: the
    AHRS attitude stamped ``t`` describes the body at ``t - att_delay``, and the gyro's body rates ``omega_b``
    carry it forward (first order; the ``att_delay omega_b x accel_bias_b`` term is dropped).  The per-IMU-sample
    work is a few floating-point additions: samples with the same AHRS attitude are summed as ``sum f_b dt``,
    ``sum (omega_b x f_b) dt`` and their first moments ``... dt t_mid`` (``t_mid``: the sample interval's midpoint
    from the start of the prediction); when the attitude changes, or when the covariance is predicted, these sums
    are rotated once by ``R_nb`` into ``sum R_nb f dt``, ``sum R_nb dt``, ``sum R_nb (omega x f) dt`` and their
    moments (:class:`ImuIncrement`).  With the first moments the mean of one prediction over many samples equals
    the sample-by-sample integration of a piecewise constant specific force (velocity and position, bias, heading
    and delay Jacobians included; tests check it), so the covariance rate is a free choice: the covariance is
    predicted at most every ``predict_period_s`` while only IMU samples arrive, and once at the stamp of a
    measurement (all measurements with one stamp share it).  Process noise from :class:`~fusion.config.EkfConfig`
    (white acceleration on each NED axis, random walks on the slow states).  The wind is a walking mean
    ``wind_mean_ne`` plus first-order Gauss-Markov turbulence: over a prediction of ``dt`` the total wind relaxes as
    ``wind' = e wind + (1 - e) wind_mean`` (``e = exp(-dt / wind_turb_corr_time_s)``) with the turbulence's noise
    ``sigma^2 (1 - e^2)``; ``sigma^2`` is estimated in flight (``wind_turb_adapt_time_s``) from the estimated
    turbulence ``wind - wind_mean`` and its variance, so the wind's covariance follows the day's turbulence level.
    IMU samples wait in their FIFO until
    something needs them (a due measurement, a reader, a prediction period behind the horizon) and are then
    processed in one loop; the result does not depend on when that happens.

Time (STYLE section 6)
    Every input carries its ``t_us``.  IMU samples (in stamp order) wait in a FIFO, measurements in a time-ordered
    heap, and the filter runs on a *delayed fusion horizon* ``fusion_delay_s`` behind the newest IMU sample (PX4
    EKF2's ``pop_first_older_than``): a measurement is fused at its own stamp, the state being predicted from the
    last IMU sample to it (zero-order hold).  An input older than what the filter has already processed is rejected
    with reason ``late`` in its status.  The estimate refers to the horizon's time ``NavEstimate.t_us`` (at most
    ``fusion_delay_s + predict_period_s`` behind the newest IMU sample); give ``fusion_delay_s = 0`` when samples are
    fed in time order.  Samples with the same stamp are processed in a fixed order (IMU, GNSS, baro, airspeed +
    sideslip + angle of attack, optical, clone) whatever their arrival order, so a replay with other latencies gives
    the same filter.  The synthetic sideslip and the lift-model angle of attack use the AHRS attitude of the last
    IMU sample at or before their stamp.  ``estimate()`` is computed once per filter state (repeated calls without a
    state change return the same object, whose arrays are read-only).

Optical cycles (stochastic cloning)
    When a step of a new cycle (a new ``cycle_id``) is pushed, a *clone event* is scheduled at the cycle's
    ``base_t_us``: when the horizon reaches it, ``base_pos_ne``/``base_pos_d`` become copies of the position and
    their covariance rows copies of the position's (exact joint covariance of "position then" and "state now").
    Every later step of the cycle measures ``pos - base_pos`` in the base-heading frame over the base image's
    ground sample distance (:class:`fusion.measurements.OpticalDisplacement`).  Steps are fused at their exposure
    time ``t_us``; the base step itself (``t_us == base_t_us``) carries no displacement and is skipped.  If the
    horizon had already passed ``base_t_us`` when the cycle's first step arrived (fusion delay shorter than the
    camera latency, or base steps not pushed), the first valid step of the cycle *anchors* it: the base position is
    reconstructed from it (current position minus its displacement) with its pixel noise in the clone's
    covariance, so that error is correctly shared by the cycle's later steps, which are then fused as usual.  Cycle
    ids must increase; a step of a cycle older than the clone's is rejected (``stale cycle``).

Partial-update (Schmidt) airspeed scale
    Every update multiplies the airspeed scale's row of the gain ``K`` by ``tas_scale_update_fraction`` (Brink's
    partial-update Schmidt-Kalman filter, JGCD 2017; 0 is a pure *consider* state, 1 the full EKF update).  The
    Joseph form is the right covariance for any gain, so the scale's variance and its correlations with the wind stay
    honest while its estimate moves only by that fraction of the optimal correction.  In turbulence the scale and the
    along-heading wind are nearly degenerate and a fully updated scale walks away (strong-wind simulator scenario:
    +5 % against a true -3.9 %, the wind 1.4 m/s off); a near-fixed scale prior instead (0.3 %) made the wind
    sigma ignore a 2-4 % pitot error (0.4-0.8 m/s of headwind at 20 m/s).  With the calibration's prior (2 %) and
    a small fraction the pitot error is in the wind sigma and the airspeed innovation variance, and a constant
    scale is still learnt over a few minutes of turns in smooth air.

Gating replaces the paper's data filter (eq. 6) and integrity filter (2.7): a bad match is rejected by its NIS (or
by its quality verdict), the clone is kept, and the next steps of the cycle are measured against the same base.
GNSS rejected continuously for ``gnss_reset_after_s`` (e.g. back after a long outage) resets the position
(velocity) to it, as PX4 does; a position reset re-anchors the current optical cycle.

Bad input never reaches the state: a non-finite value, a wrong shape, a stamp out of order or a stale attitude is
rejected and the source's status says why; the filter carries on from the model.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import ExtendedKalmanFilter
from numpy.typing import ArrayLike, NDArray
from scipy.constants import g as STANDARD_GRAVITY_M_S2

from common.angles import angle_diff, wrap_2pi
from common.samples import AttitudeSample, GsoeStep, ImuSample
from fusion.config import EkfConfig
from fusion.measurements import (
    BaroAltitude,
    GnssPosition,
    GnssVelocity,
    LiftAngleOfAttack,
    OpticalDisplacement,
    SyntheticSideslip,
    TrueAirspeed,
)
from fusion.state import S

log = logging.getLogger(__name__)

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]

US_PER_S = 1_000_000
S_PER_US = 1e-6
#: Relative tolerance of the covariance-health check: ``H P H'`` counts as negative (the PX4 condition "innovation
#: variance below observation variance") when a diagonal element is below ``-COV_RESET_REL_TOL * R``; smaller
#: negatives are rounding of an exactly zero variance (e.g. a clone taken this instant).
COV_RESET_REL_TOL = 1e-9
#: Process-noise matrices kept per prediction length (µs); the cache is emptied when it grows beyond this (the
#: lengths are few when samples come on a clock grid, arbitrary in replays of jittery logs).
Q_CACHE_MAX = 256

#: ``|cos(pitch)|`` below which the 3-2-1 yaw rate is undefined (pitch within 0.06 deg of +-90 deg) and taken as 0.
MIN_COS_PITCH = 1e-3

#: Aid sources with a status record, in logging order.
AID_SOURCES: tuple[str, ...] = ("imu", "optical", "airspeed", "sideslip", "aoa", "baro", "gnss_pos", "gnss_vel")

# Status reasons (the ``reason`` field of :class:`AidStatus`).
REASON_NON_FINITE = "non-finite input"
REASON_BAD_SHAPE = "wrong shape"
REASON_BAD_TIME = "bad timestamp"
REASON_BAD_SIGMA = "sigma not a positive finite number"
REASON_NOT_INCREASING = "timestamp not increasing"
REASON_LATE = "late (older than the fusion horizon)"
REASON_BUFFER_FULL = "buffer full"
REASON_ATT_STALE = "attitude too far from the IMU stamp"
REASON_IMU_GAP = "gap before this IMU sample"
REASON_GATE = "innovation gate"
REASON_COV_RESET = "covariance reset (innovation variance below observation variance)"
REASON_NUMERIC = "non-finite update result"
REASON_RESET_TO_MEAS = "state reset to the measurement after continuous rejection"
REASON_BASE_FRAME = "base frame (no displacement yet)"
REASON_INVALID_MATCH = "invalid match"
REASON_ANCHORED = "anchored the cycle: base position reconstructed from this step (base time already processed)"
REASON_STALE_CYCLE = "stale cycle"
REASON_LOW_HEIGHT = "height above ground below optical_min_height_m"
REASON_BAD_FOCAL = "focal_px not positive"
REASON_LOW_AIRSPEED = "airspeed below tas_min_m_s"
REASON_NO_ATTITUDE = "no attitude yet"
REASON_WIND_RESET = "wind reset from the wind triangle (first airspeed sample)"
REASON_AOA_RANGE = "lift-model angle of attack outside aoa_max_deg (lift curve not linear there)"

# Processing order of buffered events with the same stamp (independent of arrival order, so a replay with other
# latencies gives the same filter): the IMU sample first (the state is predicted to the stamp), then GNSS, baro,
# airspeed, optical, and last the clone of a cycle starting at this stamp (after the previous cycle's last step).
_PRIO = {"imu": 0, "gnss_pos": 1, "gnss_vel": 2, "baro": 3, "airspeed": 4, "optical": 5, "clone": 6}


def _is_int(t: Any) -> bool:
    return type(t) is int or (isinstance(t, int | np.integer) and not isinstance(t, bool))


def _finite(*values: Any) -> bool:
    """All values (numbers or arrays of numbers) finite; anything that is not numeric counts as not finite."""
    for v in values:
        if isinstance(v, float | int) and not isinstance(v, bool):
            if not math.isfinite(v):
                return False
            continue
        try:
            a = np.asarray(v, dtype=float)
        except (TypeError, ValueError):
            return False
        if not np.isfinite(a).all():
            return False
    return True


def _rot_rows(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, ...]:
    """The nine entries (row by row) of the body-to-NED rotation from 3-2-1 Euler angles."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return (cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr,
            sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr,
            -sp, cp * sr, cp * cr)


def _yaw_rate(att: AttitudeSample, rates_b: tuple[float, float, float]) -> float:
    """Rate of the 3-2-1 yaw angle (rad/s) from body rates ``(p, q, r)``: ``(q sin(roll) + r cos(roll)) / cos(pitch)``
    (0 at the 3-2-1 singularity, ``|cos(pitch)| < MIN_COS_PITCH``)."""
    cp = math.cos(att.pitch_rad)
    if abs(cp) < MIN_COS_PITCH:
        return 0.0
    return (rates_b[1] * math.sin(att.roll_rad) + rates_b[2] * math.cos(att.roll_rad)) / cp


def R_nb_321(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Mat:
    """Body-to-NED rotation from 3-2-1 Euler angles; the same as :func:`gsoe.rotation.R_nb_from_euler` (a test
    checks it) written out, because building a scipy ``Rotation`` per IMU sample costs more than the EKF step."""
    return np.array(_rot_rows(roll_rad, pitch_rad, yaw_rad)).reshape(3, 3)


# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class AidStatus:
    """Status of one aid source after the last measurement it processed (PX4 EKF2's ``estimator_aid_source``).

    ``t_us``: stamp of that measurement (-1: none yet).  ``innovation`` (measurement minus prediction, in the
    measurement's units) and ``innovation_var`` (diagonal of ``S``) are empty when the measurement was rejected
    before an innovation was formed.  ``test_ratio`` = NIS / gate (> 1: rejected by the gate; NaN when not
    computed).  ``fused`` and ``rejected`` are both false when a sample was deliberately not used (e.g. the base
    frame of an optical cycle, airspeed below the minimum).  ``reason`` says why it was not fused.
    ``t_last_fuse_us``: stamp of the last fused measurement (-1: never).
    """

    source: str
    t_us: int = -1
    innovation: tuple[float, ...] = ()
    innovation_var: tuple[float, ...] = ()
    test_ratio: float = math.nan
    fused: bool = False
    rejected: bool = False
    reason: str = ""
    t_last_fuse_us: int = -1
    n_fused: int = 0
    n_rejected: int = 0

    def as_record(self, max_dim: int = 3) -> dict[str, Any]:
        """Flat record for ``aid_status.csv`` (columns with units: innovations in the measurement's units)."""
        rec: dict[str, Any] = {"source": self.source, "t_us": self.t_us}
        for i in range(max_dim):
            rec[f"innov_{i}"] = self.innovation[i] if i < len(self.innovation) else math.nan
            rec[f"innov_var_{i}"] = self.innovation_var[i] if i < len(self.innovation_var) else math.nan
        rec.update(test_ratio=self.test_ratio, fused=self.fused, rejected=self.rejected, reason=self.reason,
                   t_last_fuse_us=self.t_last_fuse_us, n_fused=self.n_fused, n_rejected=self.n_rejected)
        return rec


class _StatusRow:
    """Mutable twin of :class:`AidStatus` updated at sample rate (the frozen record is built, and kept until the next
    change, only when ``status()`` asks for it)."""

    __slots__ = ("source", "t_us", "innovation", "innovation_var", "test_ratio", "fused", "rejected", "reason",
                 "t_last_fuse_us", "n_fused", "n_rejected", "_snap")

    def __init__(self, source: str) -> None:
        self.source = source
        self.t_us = -1
        self.innovation: tuple[float, ...] = ()
        self.innovation_var: tuple[float, ...] = ()
        self.test_ratio = math.nan
        self.fused = self.rejected = False
        self.reason = ""
        self.t_last_fuse_us = -1
        self.n_fused = self.n_rejected = 0
        self._snap: AidStatus | None = None

    def set(self, t_us: int, *, fused: bool = False, rejected: bool = False, reason: str = "",
            innovation: tuple[float, ...] = (), innovation_var: tuple[float, ...] = (),
            test_ratio: float = math.nan) -> None:
        """Record one processed sample; ``innovation``/``innovation_var`` are tuples of floats (measurement units)."""
        self.t_us = t_us
        self.fused, self.rejected, self.reason = fused, rejected, reason
        self.innovation, self.innovation_var, self.test_ratio = innovation, innovation_var, test_ratio
        if fused:
            self.t_last_fuse_us = t_us
            self.n_fused += 1
        if rejected:
            self.n_rejected += 1
        self._snap = None

    def fused_now(self, t_us: int, innovation: tuple[float, ...], innovation_var: tuple[float, ...],
                  test_ratio: float) -> None:
        """``set(t_us, fused=True, ...)`` without keyword handling (the per-update path)."""
        self.t_us = self.t_last_fuse_us = t_us
        self.fused, self.rejected, self.reason = True, False, ""
        self.innovation, self.innovation_var, self.test_ratio = innovation, innovation_var, test_ratio
        self.n_fused += 1
        self._snap = None

    def snapshot(self) -> AidStatus:
        if self._snap is None:
            self._snap = AidStatus(
                self.source, t_us=self.t_us, innovation=self.innovation, innovation_var=self.innovation_var,
                test_ratio=float(self.test_ratio), fused=self.fused, rejected=self.rejected, reason=self.reason,
                t_last_fuse_us=self.t_last_fuse_us, n_fused=self.n_fused, n_rejected=self.n_rejected)
        return self._snap


@dataclass(frozen=True, slots=True)
class NavEstimate:
    """The filter's output at ``t_us`` (the fusion horizon), with one-sigma uncertainties.

    Positions in the local NED frame (m); ``height_m`` above the reference ground, ``height_agl_m`` above the ground
    under the aircraft.  Velocities are ground velocities (m/s).  Angles in radians, clockwise from north:
    ``course_rad`` (of the ground velocity, [0, 2 pi)), ``heading_rad`` (AHRS yaw corrected by the estimated
    heading error and, with the yaw rate, by the estimated AHRS delay), ``drift_rad`` = course - heading in
    [-pi, pi) (positive: track to the right of the heading), ``ata_rad`` = the paper's eq. 12 actual tracking angle
    ``beta + psi + drift``, i.e. the EKF's course over ground.  ``wind_ne_m_s`` is the velocity of the air (blowing
    *to*); ``wind_from_rad`` the direction it blows *from* (MAVLink WIND); ``wind_d_m_s`` the vertical wind (down
    positive, turbulence: :mod:`fusion.state`).  Angle sigmas are capped at pi where the angle is undefined (speed
    near zero).
    ``yaw_bias_rad``, ``opt_rot_rad``, ``baro_bias_m``, ``terrain_h_m``, ``tas_scale``, ``accel_bias_b_m_s2``,
    ``side_force_ofs_m_s2``, ``aoa_ofs_rad``: the calibration states (:mod:`fusion.state`).
    ``wind_turb_sigma_m_s``: the
    turbulence level the wind model uses now (per axis, adapted in flight).  ``cov_pvw`` is the 6x6 covariance of
    ``[pos_ne, vel_ne, wind_ne]`` (for NEES).  ``valid`` is false with ``invalid_reason`` when the output should not
    be used (see :class:`~fusion.config.EkfConfig`).
    """

    t_us: int
    pos_ne_m: Vec
    pos_ne_sigma_m: Vec
    height_m: float
    height_sigma_m: float
    height_agl_m: float
    height_agl_sigma_m: float
    vel_ned_m_s: Vec
    vel_ned_sigma_m_s: Vec
    ground_speed_m_s: float
    ground_speed_sigma_m_s: float
    course_rad: float
    course_sigma_rad: float
    wind_ne_m_s: Vec
    wind_ne_sigma_m_s: Vec
    wind_speed_m_s: float
    wind_speed_sigma_m_s: float
    wind_from_rad: float
    wind_from_sigma_rad: float
    wind_d_m_s: float
    wind_d_sigma_m_s: float
    heading_rad: float
    heading_sigma_rad: float
    drift_rad: float
    drift_sigma_rad: float
    ata_rad: float
    ata_sigma_rad: float
    accel_bias_b_m_s2: Vec
    yaw_bias_rad: float
    opt_rot_rad: float
    baro_bias_m: float
    terrain_h_m: float
    tas_scale: float
    side_force_ofs_m_s2: float
    aoa_ofs_rad: float
    wind_turb_sigma_m_s: float
    cov_pvw: Mat
    valid: bool
    invalid_reason: str = ""

    def as_record(self) -> dict[str, Any]:
        """Flat record for ``ekf.csv`` (unit suffixes in the column names)."""
        r: dict[str, Any] = {"t_us": self.t_us}
        for i, ax in enumerate("ne"):
            r[f"pos_{ax}_m"] = float(self.pos_ne_m[i])
            r[f"pos_{ax}_sigma_m"] = float(self.pos_ne_sigma_m[i])
        r.update(height_m=self.height_m, height_sigma_m=self.height_sigma_m, height_agl_m=self.height_agl_m,
                 height_agl_sigma_m=self.height_agl_sigma_m)
        for i, ax in enumerate("ned"):
            r[f"vel_{ax}_m_s"] = float(self.vel_ned_m_s[i])
            r[f"vel_{ax}_sigma_m_s"] = float(self.vel_ned_sigma_m_s[i])
        for i, ax in enumerate("ne"):
            r[f"wind_{ax}_m_s"] = float(self.wind_ne_m_s[i])
            r[f"wind_{ax}_sigma_m_s"] = float(self.wind_ne_sigma_m_s[i])
        r.update(
            ground_speed_m_s=self.ground_speed_m_s, ground_speed_sigma_m_s=self.ground_speed_sigma_m_s,
            course_rad=self.course_rad, course_sigma_rad=self.course_sigma_rad,
            wind_speed_m_s=self.wind_speed_m_s, wind_speed_sigma_m_s=self.wind_speed_sigma_m_s,
            wind_from_rad=self.wind_from_rad, wind_from_sigma_rad=self.wind_from_sigma_rad,
            wind_d_m_s=self.wind_d_m_s, wind_d_sigma_m_s=self.wind_d_sigma_m_s,
            heading_rad=self.heading_rad, heading_sigma_rad=self.heading_sigma_rad,
            drift_rad=self.drift_rad, drift_sigma_rad=self.drift_sigma_rad,
            ata_rad=self.ata_rad, ata_sigma_rad=self.ata_sigma_rad,
            accel_bias_x_m_s2=float(self.accel_bias_b_m_s2[0]), accel_bias_y_m_s2=float(self.accel_bias_b_m_s2[1]),
            accel_bias_z_m_s2=float(self.accel_bias_b_m_s2[2]), yaw_bias_rad=self.yaw_bias_rad,
            opt_rot_rad=self.opt_rot_rad,
            baro_bias_m=self.baro_bias_m, terrain_h_m=self.terrain_h_m, tas_scale=self.tas_scale,
            side_force_ofs_m_s2=self.side_force_ofs_m_s2, aoa_ofs_rad=self.aoa_ofs_rad,
            wind_turb_sigma_m_s=self.wind_turb_sigma_m_s,
            valid=self.valid, invalid_reason=self.invalid_reason,
        )
        return r


# --------------------------------------------------------------------------------------------------------------
@dataclass(slots=True)
class ImuIncrement:
    """IMU input of one prediction over ``dt_s`` (AHRS-NED, no gravity, no bias correction).

    ``dv_ahrs_n = sum(R_nb f_b dt)`` (m/s) and ``int_R_nb = sum(R_nb dt)`` (s), and their first moments
    ``dv_moment_n = sum(R_nb f_b dt t_mid)`` (m) and ``int_R_nb_moment = sum(R_nb dt t_mid)`` (s^2), ``t_mid`` being
    each sample interval's midpoint measured from the start of the increment.  The moments make the position change
    of a piecewise constant specific force exact: ``sum(R f dt (T - t_mid)) = T dv - moment``.  ``None`` (the
    default): the increment is spread evenly over ``dt_s`` (moment = value * dt_s / 2, e.g. one sample held).
    Arrays, or (the filter's own per-sample path) nested sequences of floats of the same shapes.

    ``dv_delay_n = sum(R_nb (omega_b x f_b) dt)`` (m/s^2; ``omega_b`` the gyro's body rates) and its first moment
    ``dv_delay_moment_n`` (m/s): the velocity (position) change per second of AHRS delay ``att_delay``, since the
    true attitude is ``R_nb (I + [omega x] att_delay)``.  ``None``: no rates (the delay has no effect).
    """

    dt_s: float = 0.0
    dv_ahrs_n: Vec | Sequence[float] = field(default_factory=lambda: np.zeros(3))
    int_R_nb: Mat | Sequence[Sequence[float]] = field(default_factory=lambda: np.zeros((3, 3)))
    dv_moment_n: Vec | Sequence[float] | None = None
    int_R_nb_moment: Mat | Sequence[Sequence[float]] | None = None
    dv_delay_n: Vec | Sequence[float] | None = None
    dv_delay_moment_n: Vec | Sequence[float] | None = None


_I_POS = S.idx("pos_ned")
_I_VEL = S.idx("vel_ned")
_I_CLONE = S.idx("base_pos_ned")
_I_YAW = S.yaw_bias.start
_I_PVW = S.idx("pos_ne", "vel_ne", "wind_ne")
_I_WIND = S.idx("wind_ne")
_I_WMEAN = S.idx("wind_mean_ne")
# flat indices of the wind's Gauss-Markov entries of F: d wind / d wind (N, E), then d wind / d wind_mean (N, E)
_F_WIND = np.concatenate([np.ravel_multi_index((_I_WIND, _I_WIND), (S.dim, S.dim)),
                          np.ravel_multi_index((_I_WIND, _I_WMEAN), (S.dim, S.dim))])
# flat indices of the wind's process-noise entries: (wind, wind), (wind, mean), (mean, wind)
_Q_WW = np.ravel_multi_index((_I_WIND, _I_WIND), (S.dim, S.dim))
_Q_WM = np.ravel_multi_index((_I_WIND, _I_WMEAN), (S.dim, S.dim))
_Q_MW = np.ravel_multi_index((_I_WMEAN, _I_WIND), (S.dim, S.dim))
# indices of what the turbulence adaptation reads: wind (N, E) and its mean (N, E) in x; in P the variance of
# wind - mean per axis, (wind, wind) - 2 (wind, mean) + (mean, mean), N then E
_P_TURB = np.ravel_multi_index(([_I_WIND[0], _I_WIND[0], _I_WMEAN[0], _I_WIND[1], _I_WIND[1], _I_WMEAN[1]],
                                [_I_WIND[0], _I_WMEAN[0], _I_WMEAN[0], _I_WIND[1], _I_WMEAN[1], _I_WMEAN[1]]),
                               (S.dim, S.dim))
_X_TURB = np.array([_I_WIND[0], _I_WIND[1], _I_WMEAN[0], _I_WMEAN[1]])
_I_WD = S.wind_d.start
_F_WD = _I_WD * S.dim + _I_WD                             # flat index of d wind_d / d wind_d in F
_IX_PVW = np.ix_(_I_PVW, _I_PVW)
_POS, _VEL, _BA = S.pos_ned, S.vel_ned, S.accel_bias_b
_EYE = np.eye(S.dim)
_EYE.flags.writeable = False
_I_BA = S.idx("accel_bias_b")
_I_DELAY = S.att_delay.start
_I_SCALE = S.tas_scale.start
# flat indices of the IMU-dependent entries of F, in the order _propagate_into lists them: d pos / d vel (N, E, D),
# d pos / d accel_bias_b (3 x 3, row by row), d vel / d accel_bias_b, d(pos_n, pos_e, vel_n, vel_e) / d yaw_bias,
# d pos / d att_delay, d vel / d att_delay
_F_IMU = np.concatenate([
    np.ravel_multi_index((_I_POS, _I_VEL), (S.dim, S.dim)),
    np.ravel_multi_index((np.repeat(_I_POS, 3), np.tile(_I_BA, 3)), (S.dim, S.dim)),
    np.ravel_multi_index((np.repeat(_I_VEL, 3), np.tile(_I_BA, 3)), (S.dim, S.dim)),
    np.ravel_multi_index(([S.pos_ne.start, S.pos_ne.start + 1, S.vel_ne.start, S.vel_ne.start + 1], [_I_YAW] * 4),
                         (S.dim, S.dim)),
    np.ravel_multi_index((_I_POS, [S.att_delay.start] * 3), (S.dim, S.dim)),
    np.ravel_multi_index((_I_VEL, [S.att_delay.start] * 3), (S.dim, S.dim)),
])
# flat indices of the position/velocity blocks of Q (north, east, down in turn)
_Q_PP = np.ravel_multi_index((_I_POS, _I_POS), (S.dim, S.dim))
_Q_PV = np.ravel_multi_index((_I_POS, _I_VEL), (S.dim, S.dim))
_Q_VP = np.ravel_multi_index((_I_VEL, _I_POS), (S.dim, S.dim))
_Q_VV = np.ravel_multi_index((_I_VEL, _I_VEL), (S.dim, S.dim))
_HALF_G = 0.5 * STANDARD_GRAVITY_M_S2
_ACC_LEN = 30           # floats of the accumulated increment (see NavEkf.__init__)
_SEG_LEN = 14           # floats of an open segment (see NavEkf.__init__)
# flat indices of the covariance entries NavEkf._estimate reads, in its order: velocity N/E (nn, ne, ee), yaw bias
# (yy, vel_n-yaw, vel_e-yaw), wind (nn, ne, ee), down position, terrain, down position-terrain, AHRS delay (dd,
# yaw-delay, vel_n-delay, vel_e-delay)
_EST_FLAT = np.ravel_multi_index(tuple(np.array([
    (S.vel_ne.start, S.vel_ne.start), (S.vel_ne.start, S.vel_ne.start + 1), (S.vel_ne.start + 1, S.vel_ne.start + 1),
    (_I_YAW, _I_YAW), (S.vel_ne.start, _I_YAW), (S.vel_ne.start + 1, _I_YAW),
    (S.wind_ne.start, S.wind_ne.start), (S.wind_ne.start, S.wind_ne.start + 1),
    (S.wind_ne.start + 1, S.wind_ne.start + 1),
    (S.pos_d.start, S.pos_d.start), (S.terrain_h.start, S.terrain_h.start), (S.pos_d.start, S.terrain_h.start),
    (S.att_delay.start, S.att_delay.start), (_I_YAW, S.att_delay.start),
    (S.vel_ne.start, S.att_delay.start), (S.vel_ne.start + 1, S.att_delay.start),
]).T), (S.dim, S.dim))


def _floats(a: Any) -> Any:
    """Python floats (nested lists) of an array; sequences pass unchanged."""
    return a.tolist() if isinstance(a, np.ndarray) else a


def _chol_inv(Sm: list[list[float]]) -> list[list[float]] | None:
    """``C^-1`` (lower triangular, nested lists) of the Cholesky factor ``S = C C'`` of a small symmetric matrix;
    ``None`` if ``S`` is not positive definite.  Floats: for m <= 3 this is cheaper than NumPy's calls."""
    m = len(Sm)
    C = [[0.0] * m for _ in range(m)]
    for i in range(m):
        for j in range(i + 1):
            v = Sm[i][j] - sum(C[i][k] * C[j][k] for k in range(j))
            if i == j:
                if not v > 0.0:
                    return None
                C[i][i] = math.sqrt(v)
            else:
                C[i][j] = v / C[j][j]
    Ci = [[0.0] * m for _ in range(m)]
    for i in range(m):
        Ci[i][i] = 1.0 / C[i][i]
        for j in range(i):
            Ci[i][j] = -sum(C[i][k] * Ci[k][j] for k in range(j, i)) / C[i][i]
    return Ci


def _propagate_into(x: Vec, inc: ImuIncrement, F: Mat, wind_decay: float = 1.0) -> Vec:
    """Mean propagation over one increment; returns the new state and writes the IMU-dependent entries of the Jacobian
    ``F = d x_new / d x`` into ``F`` (its other entries must be those of the identity).

    Scalar arithmetic on Python floats: the 3-vectors and 3 x 3 blocks here cost ~1-2 µs per NumPy call."""
    T = inc.dt_s
    (u0, u1, u2), (w0, w1, w2), (z0, z1, z2) = M = _floats(inc.int_R_nb)     # sum R dt
    dv0, dv1, dv2 = _floats(inc.dv_ahrs_n)                                    # sum R f dt
    if inc.dv_moment_n is None or inc.int_R_nb_moment is None:
        h = 0.5 * T
        (a0, a1, a2), (e0, e1, e2), (d0, d1, d2) = [[h * v for v in r] for r in M]
        dq0, dq1, dq2 = h * dv0, h * dv1, h * dv2
    else:                                                 # sum R dt (T - t_mid), sum R f dt (T - t_mid)
        (a0, a1, a2), (e0, e1, e2), (d0, d1, d2) = _floats(inc.int_R_nb_moment)
        a0, a1, a2, e0, e1, e2 = T * u0 - a0, T * u1 - a1, T * u2 - a2, T * w0 - e0, T * w1 - e1, T * w2 - e2
        d0, d1, d2 = T * z0 - d0, T * z1 - d1, T * z2 - d2
        n0, n1, n2 = _floats(inc.dv_moment_n)
        dq0, dq1, dq2 = T * dv0 - n0, T * dv1 - n1, T * dv2 - n2
    xl = x.tolist()
    b0, b1, b2 = xl[_BA.start], xl[_BA.start + 1], xl[_BA.start + 2]
    m0 = dv0 - (u0 * b0 + u1 * b1 + u2 * b2)              # sum R (f - b) dt
    m1 = dv1 - (w0 * b0 + w1 * b1 + w2 * b2)
    m2 = dv2 - (z0 * b0 + z1 * b1 + z2 * b2)
    q0 = dq0 - (a0 * b0 + a1 * b1 + a2 * b2)              # sum R (f - b) dt (T - t_mid)
    q1 = dq1 - (e0 * b0 + e1 * b1 + e2 * b2)
    q2 = dq2 - (d0 * b0 + d1 * b1 + d2 * b2)
    # the AHRS delay: + tau sum R (omega x f) dt (and its position moment); the tau omega x b term is negligible
    if inc.dv_delay_n is None:
        k0 = k1 = k2 = j0 = j1 = j2 = 0.0
    else:
        k0, k1, k2 = _floats(inc.dv_delay_n)
        if inc.dv_delay_moment_n is None:
            j0, j1, j2 = 0.5 * T * k0, 0.5 * T * k1, 0.5 * T * k2
        else:
            n0, n1, n2 = _floats(inc.dv_delay_moment_n)
            j0, j1, j2 = T * k0 - n0, T * k1 - n1, T * k2 - n2
        tau = xl[_I_DELAY]
        m0, m1, m2 = m0 + tau * k0, m1 + tau * k1, m2 + tau * k2
        q0, q1, q2 = q0 + tau * j0, q1 + tau * j1, q2 + tau * j2
    yb = xl[_I_YAW]
    c, s = math.cos(yb), math.sin(yb)                     # R_z(-yaw_bias) = [[c, s], [-s, c]]
    mn, me = c * m0 + s * m1, -s * m0 + c * m1            # velocity change without gravity, N/E
    qn, qe = c * q0 + s * q1, -s * q0 + c * q1            # position change beyond v T, without gravity, N/E
    ip, iv = _POS.start, _VEL.start
    vn, ve, vd = xl[iv], xl[iv + 1], xl[iv + 2]
    xl[ip] += vn * T + qn
    xl[ip + 1] += ve * T + qe
    xl[ip + 2] += vd * T + q2 + _HALF_G * T * T
    xl[iv] = vn + mn
    xl[iv + 1] = ve + me
    xl[iv + 2] = vd + m2 + STANDARD_GRAVITY_M_S2 * T
    # -R_z(-yaw_bias) @ Mq (position rows; Mq = [a; e; d]) and -R_z(-yaw_bias) @ M (velocity rows; M = [u; w; z])
    F.flat[_F_IMU] = (
        T, T, T,
        -(c * a0 + s * e0), -(c * a1 + s * e1), -(c * a2 + s * e2),
        s * a0 - c * e0, s * a1 - c * e1, s * a2 - c * e2,
        -d0, -d1, -d2,
        -(c * u0 + s * w0), -(c * u1 + s * w1), -(c * u2 + s * w2),
        s * u0 - c * w0, s * u1 - c * w1, s * u2 - c * w2,
        -z0, -z1, -z2,
        qe, -qn, me, -mn,                                 # d R_z(-b) u / d b = (u_E', -u_N') of the rotated u
        c * j0 + s * j1, -s * j0 + c * j1, j2,            # d pos / d att_delay = R_z(-b) sum R (w x f) dt (T - t)
        c * k0 + s * k1, -s * k0 + c * k1, k2,            # d vel / d att_delay = R_z(-b) sum R (w x f) dt
    )
    if wind_decay != 1.0:                                 # turbulence relaxing to the mean (see _FilterCore)
        iw, im = _I_WIND[0], _I_WMEAN[0]
        xl[iw] = wind_decay * xl[iw] + (1.0 - wind_decay) * xl[im]
        xl[iw + 1] = wind_decay * xl[iw + 1] + (1.0 - wind_decay) * xl[im + 1]
    return np.array(xl)


def propagate(x: Vec, inc: ImuIncrement) -> tuple[Vec, Mat]:
    """Mean propagation over one increment and its Jacobian ``F = d x_new / d x`` (n x n)."""
    F = _EYE.copy()
    return _propagate_into(x, inc, F), F


class _FilterCore(ExtendedKalmanFilter):
    """filterpy's EKF with our mean propagation: ``predict(u=ImuIncrement)`` runs :func:`propagate` (which also sets
    ``F`` at the prior state) and the process noise for the increment's length, then filterpy's ``P = F P F' + Q``."""

    def __init__(self, x0: Vec, P0: Mat, cfg: EkfConfig) -> None:
        super().__init__(dim_x=S.dim, dim_z=1)
        self.x = x0
        self.P = P0
        self.F = np.eye(S.dim)             # identity apart from the entries _propagate_into writes every time
        self._cfg = cfg
        self._q_cache: dict[int, tuple[Mat, float, float, float, float, float, float]] = {}
        self._decay = 1.0                  # the wind turbulence's decay over the current prediction
        self._q_turb = 0.0                 # the turbulence's noise over the current prediction (m^2/s^2 per axis)
        self._q_wd = 0.0                   # the vertical wind's noise over the current prediction (m^2/s^2)
        self._decay_wd = 1.0               # the vertical wind's decay over the current prediction
        self._wd_ratio2 = cfg.wind_d_sigma_ratio**2    # vertical / horizontal turbulence variance
        #: the turbulence variance in use (m^2/s^2 per axis): ``wind_turb_sigma_m_s^2``, adapted (see predict_x)
        self.turb_var = cfg.wind_turb_sigma_m_s**2
        self._turb_var_lo = cfg.wind_turb_sigma_min_m_s**2
        self._turb_var_hi = cfg.wind_turb_sigma_max_m_s**2
        rw = np.zeros(S.dim)               # random-walk variance rates of the slow states (per second)
        for name, q in (("wind_mean_ne", cfg.wind_rw_m_s_per_rt_s), ("wind_ne", cfg.wind_rw_m_s_per_rt_s),
                        ("accel_bias_b", cfg.accel_bias_rw_m_s2_per_rt_s),
                        ("yaw_bias", cfg.yaw_bias_rw_rad_per_rt_s), ("opt_rot", cfg.opt_rot_rw_rad_per_rt_s),
                        ("baro_bias", cfg.baro_bias_rw_m_per_rt_s), ("terrain_h", cfg.terrain_rw_m_per_rt_s),
                        ("tas_scale", cfg.tas_scale_rw_per_rt_s), ("att_delay", cfg.att_delay_rw_s_per_rt_s),
                        ("side_force_ofs", cfg.side_force_ofs_rw_m_s2_per_rt_s),
                        ("aoa_ofs", cfg.aoa_ofs_rw_rad_per_rt_s)):
            rw[getattr(S, name)] = q * q
        self._rw_var_rate = rw
        self.n_predictions = 0

    def process_noise(self, dt_s: float) -> Mat:
        """``Q`` over a prediction of ``dt_s`` with the turbulence variance now in use."""
        Q, _, g, _, _, _, g_w = self._noise_and_decay(dt_s)
        Q = Q.copy()
        Q.flat[_Q_WW] += self.turb_var * g
        Q[_I_WD, _I_WD] += self._wd_ratio2 * self.turb_var * g_w
        return Q

    def _noise_and_decay(self, dt_s: float) -> tuple[Mat, float, float, float, float, float, float]:
        """``Q`` without the turbulence's own term, the turbulence decay ``e = exp(-dt / tau)``, ``1 - e^2``, the
        adaptation's decay ``a = exp(-dt / A)`` (``A = wind_turb_adapt_time_s``; 1 when not adapting),
        ``c = (2 / tau) / (2 / tau - 1 / A) (a - e^2)``, the vertical wind's decay ``e_w = exp(-dt / tau_w)`` and
        ``1 - e_w^2`` over a prediction of ``dt_s`` (cached per length).

        Wind: ``wind = mean + turb``, the mean a random walk (rate ``q``), the turbulence first-order Gauss-Markov
        (``sigma``, ``tau``), so over ``dt`` ``Q_mean = q dt``, ``Q_wind = q dt + sigma^2 (1 - e^2)`` and
        ``Q_wind,mean = q dt`` (the mean's walk moves the total wind as well).  The ``sigma^2 (1 - e^2)`` term is
        added in :meth:`predict` (``sigma`` may adapt)."""
        key = round(dt_s * US_PER_S)
        hit = self._q_cache.get(key)
        if hit is None:
            cfg = self._cfg
            Q = np.diag(self._rw_var_rate * dt_s)
            qpv = Q_continuous_white_noise(dim=2, dt=dt_s, spectral_density=cfg.accel_noise_m_s2_per_rt_hz**2)
            Q.flat[_Q_PP] = qpv[0, 0]
            Q.flat[_Q_PV] = qpv[0, 1]
            Q.flat[_Q_VP] = qpv[1, 0]
            Q.flat[_Q_VV] = qpv[1, 1]
            decay = math.exp(-dt_s / cfg.wind_turb_corr_time_s)
            q_mean = cfg.wind_rw_m_s_per_rt_s**2 * dt_s
            Q.flat[_Q_WW] = q_mean
            Q.flat[_Q_WM] = q_mean
            Q.flat[_Q_MW] = q_mean
            tau, adapt = cfg.wind_turb_corr_time_s, cfg.wind_turb_adapt_time_s
            e2 = math.exp(-2.0 * dt_s / tau)
            if adapt > 0.0:
                a = math.exp(-dt_s / adapt)
                k = 2.0 / tau - 1.0 / adapt
                # int_0^dt exp(-t / A) (2 / tau) exp(-2 (dt - t) / tau) dt (its limit where 2 / tau = 1 / A)
                c = (2.0 / tau) * (a - e2) / k if abs(k * dt_s) > 1e-9 else (2.0 * dt_s / tau) * e2
            else:
                a, c = 1.0, 0.0
            if len(self._q_cache) >= Q_CACHE_MAX:
                self._q_cache.clear()
            Q.flags.writeable = False
            tau_w = cfg.wind_d_corr_time_s
            hit = self._q_cache[key] = (Q, decay, -math.expm1(-2.0 * dt_s / tau), a, c, math.exp(-dt_s / tau_w),
                                        -math.expm1(-2.0 * dt_s / tau_w))
        return hit

    def predict_x(self, u: ImuIncrement = None) -> None:  # type: ignore[assignment]
        self.Q, e, g, a, c, e_w, g_w = self._noise_and_decay(u.dt_s)
        v0 = self.turb_var
        if self._cfg.wind_turb_adapt_time_s > 0.0:
            # turbulence intensity: E[d^2] of the estimated turbulence d = wind - mean (its square plus its variance
            # from P), per axis, averaged over the adaptation time A (exponentially), within [sigma_min, sigma_max]^2.
            # Where the airspeed cannot split the wind into mean and turbulence, var(d) stays near the sigma^2 in use,
            # which holds sigma up.  Without the var(d) term (measured on 32 recorded Monte Carlo runs): NEES in
            # bounds over featureless ground 0.70-0.72 -> 0.81-0.90 (3 runs), but 0.74 -> 0.61 with a 5.6 % pitot
            # error, 0.862 -> 0.859 over all, and the paper_sil flight's 84 -> 79 %; so it stays.  With the side-force
            # sideslip, half the var(d) term: 0.870 -> 0.874, but from more overconfident steps (above the bound
            # 5.2 -> 6.8 %, below 7.7 -> 5.7 %); none: 0.855 (10.3 % above).  With the vertical wind and the tighter
            # sideslip the filter leant the other way (below 6.3 %, above 3.2 %), and half the term
            # (wind_turb_adapt_var_weight 0.5) brought it to 5.0 / 4.1 %: NEES in bounds 0.9035 -> 0.9067 on the
            # campaign's first 40 runs (EkfConfig).
            # Over the prediction the variance moves as
            # v(t) = d2 + (v0 - d2) exp(-t / A), and the noise is the exact integral of v(t) (2 / tau) exp(-2 (dt - t)
            # / tau): d2 (1 - e^2) + (v0 - d2) c, so the result does not depend on the prediction rate.
            wn, we, mn, me = self.x.take(_X_TURB).tolist()
            ann, anm, amm, aee, aem, bmm = self.P.take(_P_TURB).tolist()
            dn, de = wn - mn, we - me
            d2 = 0.5 * (dn * dn + de * de + self._cfg.wind_turb_adapt_var_weight
                        * (ann - 2.0 * anm + amm + aee - 2.0 * aem + bmm))
            self._q_turb = d2 * g + (v0 - d2) * c
            self.turb_var = min(self._turb_var_hi, max(self._turb_var_lo, d2 + (v0 - d2) * a))
        else:
            self._q_turb = v0 * g
        # the vertical wind's turbulence (sigma a fixed ratio of the horizontal one's in use)
        self._q_wd = self._wd_ratio2 * self.turb_var * g_w
        # the turbulence relaxes towards the mean: wind' = e wind + (1 - e) mean; the vertical wind towards 0
        self.x = _propagate_into(self.x, u, self.F, e)
        self.x[_I_WD] *= e_w
        if e != self._decay:
            self.F.flat[_F_WIND] = (e, e, 1.0 - e, 1.0 - e)
            self._decay = e
        if e_w != self._decay_wd:
            self.F.flat[_F_WD] = e_w
            self._decay_wd = e_w

    def predict(self, u: ImuIncrement = None) -> None:  # type: ignore[assignment]
        """filterpy's prediction, then ``P`` symmetrised (``F P F'`` is symmetric only up to rounding)."""
        super().predict(u)
        P = self.P
        P += P.T
        P *= 0.5
        q_turb = self._q_turb                              # the turbulence's process noise (its sigma adapts)
        iw = _I_WIND[0]
        P[iw, iw] += q_turb
        P[iw + 1, iw + 1] += q_turb
        P[_I_WD, _I_WD] += self._q_wd
        self.n_predictions += 1


def _read_only(a: Vec) -> Vec:
    a.flags.writeable = False
    return a


# --------------------------------------------------------------------------------------------------------------
class NavEkf:
    """Navigation EKF (state: :data:`fusion.state.S`; design: module docstring).

    Parameters
    ----------
    cfg
        What the filter assumes (:class:`~fusion.config.EkfConfig`).
    t_us
        Time of the initial state (µs, the clock of every later sample).
    pos_ned_m
        Initial position in the local NED frame (m), ``pos_ned_m[2] = -height above the reference ground``.
    vel_ned_m_s
        Initial ground velocity (m/s).
    wind_ne_m_s
        Initial wind (velocity of the air, N/E, m/s).  ``None`` (default): the wind is reset from the wind triangle
        at the first usable airspeed sample (ground velocity minus the airspeed along the heading, PX4 EKF2's
        ``resetWindUsingAirspeed``), which avoids a wind far outside its initial sigma (strong winds) being
        explained away by the airspeed scale state.
    terrain_h_m
        Height of the ground under the aircraft above the reference ground (m, up).

    The initial sigmas come from ``cfg.init_*``.  Raises ``ValueError`` naming the argument on non-finite or
    misshapen initial values.
    """

    def __init__(self, cfg: EkfConfig, *, t_us: int, pos_ned_m: ArrayLike, vel_ned_m_s: ArrayLike,
                 wind_ne_m_s: ArrayLike | None = None, terrain_h_m: float = 0.0) -> None:
        if not _is_int(t_us):
            raise ValueError(f"t_us: must be an integer (µs), got {t_us!r}")
        self._wind_reset_pending = wind_ne_m_s is None
        vals = {"pos_ned_m": (pos_ned_m, 3), "vel_ned_m_s": (vel_ned_m_s, 3),
                "wind_ne_m_s": ((0.0, 0.0) if wind_ne_m_s is None else wind_ne_m_s, 2),
                "terrain_h_m": ([terrain_h_m], 1)}
        arr: dict[str, Vec] = {}
        for name, (v, n) in vals.items():
            try:
                a = np.asarray(v, dtype=float).reshape(-1)
            except (TypeError, ValueError):
                raise ValueError(f"{name}: must be {n} finite numbers, got {v!r}") from None
            if a.shape != (n,) or not np.all(np.isfinite(a)):
                raise ValueError(f"{name}: must be {n} finite numbers, got {v!r}")
            arr[name] = a
        self.cfg = cfg
        x0 = np.zeros(S.dim)
        x0[S.pos_ned] = arr["pos_ned_m"]
        x0[S.vel_ned] = arr["vel_ned_m_s"]
        x0[S.wind_ne] = arr["wind_ne_m_s"]
        x0[S.wind_mean_ne] = arr["wind_ne_m_s"]
        x0[S.terrain_h] = arr["terrain_h_m"]
        x0[S.base_pos_ned] = arr["pos_ned_m"]
        self._init_var = self._initial_variances()
        # partial-update (Schmidt) states: their rows of every gain are scaled down (see the module docstring)
        self._gain_scale = np.ones(S.dim)
        self._schmidt: list[tuple[int, int, float]] = []
        self._set_scale_fraction(cfg.tas_scale_update_fraction)
        P0 = np.diag(self._init_var)
        # the total wind is the mean plus independent turbulence: cov(wind, mean) = var(mean)
        P0[_I_WIND, _I_WMEAN] = P0[_I_WMEAN, _I_WIND] = self._init_var[_I_WMEAN]
        P0[_I_WIND, _I_WIND] += cfg.wind_turb_sigma_m_s**2
        P0[np.ix_(_I_CLONE, _I_POS)] = P0[np.ix_(_I_POS, _I_POS)]
        P0[np.ix_(_I_POS, _I_CLONE)] = P0[np.ix_(_I_POS, _I_POS)]
        self._kf = _FilterCore(x0, P0, cfg)
        self._t_x_us = int(t_us)           # time of the filter state (the fusion horizon)
        # the turbulence sigma is a measurement only after one adaptation time: before, calm air is not known
        self._calm_known_us = int(t_us) + round(cfg.wind_turb_adapt_time_s * US_PER_S)
        self._t_in_us = int(t_us)          # inputs consumed up to here (>= _t_x_us; the rest is accumulated)
        # The covariance prediction being accumulated over [_t_x_us, _t_in_us] (ImuIncrement), as floats: sum R f dt
        # (3), sum R f dt t_mid (3), sum R dt (9, row by row), sum R dt t_mid (9), sum R (w x f) dt (3), sum R (w x f)
        # dt t_mid (3).  Python floats throughout the per-sample path: a NumPy call on a 3-vector costs more than the
        # arithmetic.
        self._acc = [0.0] * _ACC_LEN
        # the open segment of samples under the attitude _Rl: sum f dt (3), sum f dt t_mid (3), sum dt,
        # sum dt t_mid, sum (w x f) dt (3), sum (w x f) dt t_mid (3) (rotated into _acc when the attitude changes or
        # the covariance is predicted)
        self._seg = [0.0] * _SEG_LEN
        self._seg_open = False
        # specific force (FRD) and gyro rate x specific force of the last IMU sample
        self._f_held: tuple[float, float, float, float, float, float] | None = None
        self._rates_held = (0.0, 0.0, 0.0)               # body rates of the last IMU sample (rad/s, FRD)
        # lateral specific force (body y, m/s^2), low-passed over sideslip_accel_tau_s: the side-force sideslip
        self._lat_f = math.nan                           # NaN until the first IMU sample
        self._lat_rate_per_s = 1.0 / cfg.sideslip_accel_tau_s if cfg.sideslip_accel_tau_s > 0.0 else math.inf
        self._beta_gain_m = cfg.sideslip_accel_gain_m if cfg.sideslip_fusion else 0.0
        # normal specific force (body z, m/s^2), low-passed alike: the lift-model angle of attack
        self._nrm_f = math.nan
        self._alpha_gain_m = cfg.aoa_accel_gain_m if cfg.aoa_fusion else 0.0
        self._alpha_max_rad = math.radians(cfg.aoa_max_deg)
        self._att: AttitudeSample | None = None          # AHRS attitude of the last processed IMU sample
        self._att_out: AttitudeSample | None = None      # first pushed attitude (output before any is processed)
        self._Rl: tuple[float, ...] | None = None        # its rotation (body to AHRS-NED), row by row
        self._R_nb: Mat | None = None                    # the same as a matrix (built when a model needs it)
        self._newest_imu_us: int | None = None
        self._imu_q: deque[tuple[int, float, float, float, float, float, float, AttitudeSample]] = deque()
        self._heap: list[tuple[int, int, int, str, Any]] = []
        self._seq = itertools.count()
        self._n_meas_buffered = 0
        self._delay_us = round(cfg.fusion_delay_s * US_PER_S)
        self._period_us = round(cfg.predict_period_s * US_PER_S)
        self._gap_us = round(cfg.imu_max_gap_s * US_PER_S)
        self._att_age_us = round(cfg.att_max_age_s * US_PER_S)
        self._r_baro = float(BaroAltitude.noise(cfg)[0, 0])
        self._clone_cycle: int | None = None
        self._last_cycle_pushed: int | None = None
        self._reject_since: dict[str, int | None] = {"gnss_pos": None, "gnss_vel": None}
        self._st: dict[str, _StatusRow] = {s: _StatusRow(s) for s in AID_SOURCES}
        self._st_imu = self._st["imu"]
        self._buffer_full_warned = False
        self._gnss_pos_last_us: int | None = None
        self._est: NavEstimate | None = None             # estimate() of the current state (None: to be computed)

    # ----------------------------------------------------------------------------------------------------------
    # public API
    @property
    def t_us(self) -> int:
        """Time of the filter state (the fusion horizon), µs."""
        self._process_due()
        return self._t_x_us

    @property
    def x(self) -> Vec:
        """Copy of the state vector (layout :data:`fusion.state.S`)."""
        self._process_due()
        return self._kf.x.copy()

    @property
    def P(self) -> Mat:
        """Copy of the state covariance."""
        self._process_due()
        return self._kf.P.copy()

    @property
    def wind_turb_sigma_m_s(self) -> float:
        """The turbulence standard deviation the wind model uses now (m/s per axis; adapted in flight)."""
        self._process_due()
        return math.sqrt(self._kf.turb_var)

    @property
    def covariance_predictions(self) -> int:
        """Number of covariance predictions so far (for the cost figures)."""
        self._process_due()
        return self._kf.n_predictions

    def covariance(self, *names: str) -> Mat:
        """Covariance block of the named state fields (in that order)."""
        self._process_due()
        i = S.idx(*names)
        return self._kf.P[np.ix_(i, i)].copy()

    def status(self) -> dict[str, AidStatus]:
        """Per aid source (:data:`AID_SOURCES`) the status after its last processed sample."""
        self._process_due()
        return {name: row.snapshot() for name, row in self._st.items()}

    def predict(self, imu: ImuSample, att: AttitudeSample) -> None:
        """Push one IMU sample (specific force m/s^2 and body rates rad/s, FRD, at ``imu.t_us``) with the AHRS
        attitude (3-2-1 Euler, rad) valid within ``att_max_age_s`` of it.  IMU stamps must increase.  The sample
        drives the prediction of the interval that ends at its stamp (its rates only through the AHRS delay)."""
        # the checks are written out here (not in a helper): this is the per-sample path
        reason = ""
        try:
            t, ta = imu.t_us, att.t_us
            if not (_is_int(t) and _is_int(ta)):
                reason = REASON_BAD_TIME
            else:
                a, g = imu.accel_b_m_s2, imu.gyro_b_rad_s
                if not (type(a) is np.ndarray and type(g) is np.ndarray):
                    a, g = np.asarray(a, dtype=float), np.asarray(g, dtype=float)
                # unpacking checks the shape: anything but 3 numbers raises (or gives lists, which do not add up)
                fx, fy, fz = a.tolist()
                gx, gy, gz = g.tolist()
                # the sum of finite numbers is finite (an overflow at absurd magnitudes is rejected as well)
                if not math.isfinite(fx + fy + fz + gx + gy + gz + att.roll_rad + att.pitch_rad + att.yaw_rad):
                    reason = REASON_NON_FINITE
        except (AttributeError, TypeError, ValueError, IndexError):
            reason = REASON_BAD_SHAPE
        if not reason:
            t = int(t)
            newest = self._newest_imu_us
            if newest is not None and t <= newest:
                reason = REASON_NOT_INCREASING
            elif t < self._t_in_us:
                reason = REASON_LATE
            elif abs(int(ta) - t) > self._att_age_us:
                reason = REASON_ATT_STALE
        if reason:
            t = getattr(imu, "t_us", -1)
            self._st_imu.set(int(t) if _is_int(t) else -1, rejected=True, reason=reason)
            return
        self._newest_imu_us = t
        if self._att is None:
            self._att_out = att             # heading for the output until the horizon reaches an IMU sample
            self._est = None
        q = self._imu_q
        q.append((t, fx, fy, fz, gx, gy, gz, att))
        # Due samples are processed in batches (the result is the same as one by one): now if a measurement is
        # due, or the oldest waiting sample is a prediction period behind the horizon; otherwise when anything
        # reads the filter (estimate, status, the properties) or a measurement arrives.
        horizon = t - self._delay_us
        heap = self._heap
        if (heap and heap[0][0] <= horizon) or q[0][0] <= horizon - self._period_us:
            self._process_due()

    def fuse_airspeed(self, t_us: int, tas_m_s: float) -> None:
        """Push a true airspeed sample (m/s) measured at ``t_us``; the sideslip pseudo-measurement (side-force
        sideslip, or zero) is fused with it (``cfg.sideslip_fusion``), and so is the lift-model angle of attack
        (``cfg.aoa_fusion``)."""
        if self._admit("airspeed", t_us, tas_m_s):
            self._push(t_us, "airspeed", float(tas_m_s))

    def fuse_baro(self, t_us: int, alt_m: float) -> None:
        """Push a barometric altitude (m above the reference ground, up) measured at ``t_us``."""
        if self._admit("baro", t_us, alt_m):
            self._push(t_us, "baro", float(alt_m))

    def fuse_gnss(self, t_us: int, pos_ned_m: ArrayLike | None, vel_ned_m_s: ArrayLike | None, *,
                  pos_sigma_ne_m: float | None = None, pos_sigma_d_m: float | None = None,
                  vel_sigma_ne_m_s: float | None = None, vel_sigma_d_m_s: float | None = None) -> None:
        """Push a GNSS fix at ``t_us``: position in the local NED frame (m; 3 values, or 2 for north/east only) and/or
        ground velocity (m/s; 3 values NED, or 2 for north/east), either may be ``None``.  The optional one-sigma
        accuracies (the receiver's hacc/vacc/sacc) replace the configured ones."""
        sig = (pos_sigma_ne_m, pos_sigma_d_m, vel_sigma_ne_m_s, vel_sigma_d_m_s)
        for src, val in (("gnss_pos", pos_ned_m), ("gnss_vel", vel_ned_m_s)):
            if val is None:
                continue
            tt = int(t_us) if _is_int(t_us) else -1
            a = np.asarray(val, dtype=float).reshape(-1) if _finite(val) else None
            if a is not None and a.shape not in ((2,), (3,)):
                self._st[src].set(tt, rejected=True, reason=REASON_BAD_SHAPE)
                continue
            s_used = sig[:2] if src == "gnss_pos" else sig[2:]
            if a is None:
                self._st[src].set(tt, rejected=True, reason=REASON_NON_FINITE)
                continue
            if not all(s is None or (_finite(s) and float(s) > 0.0) for s in s_used):
                self._st[src].set(tt, rejected=True, reason=REASON_BAD_SIGMA)
                continue
            if self._admit(src, t_us, 0.0):
                self._push(t_us, src, (a, s_used))

    def fuse_optical(self, step: GsoeStep) -> None:
        """Push one optical step (a :class:`GsoeStep` fused at its exposure time ``step.t_us``); push every
        step in order, including each cycle's base step (``new_cycle``) so the clone is taken at the base time."""
        row = self._st["optical"]
        try:
            ints_ok = _is_int(step.t_us) and _is_int(step.base_t_us) and _is_int(step.cycle_id)
            # a sum is finite only if every term is (NaN and inf propagate); non-numbers raise
            vals_ok = math.isfinite(step.dx_px + step.dy_px + step.base_yaw_rad + step.focal_px)
            # used by the noise model: must be numbers (NaN allowed: they fall back to conservative values)
            float(step.quality.psr), float(step.rel_rot_rad), bool(step.quality.valid), bool(step.valid)
        except (AttributeError, TypeError, ValueError):
            row.set(-1, rejected=True, reason=REASON_BAD_SHAPE)
            return
        if not ints_ok or step.base_t_us > step.t_us:
            row.set(int(step.t_us) if _is_int(getattr(step, "t_us", None)) else -1, rejected=True,
                    reason=REASON_BAD_TIME)
            return
        if not vals_ok:
            row.set(int(step.t_us), rejected=True, reason=REASON_NON_FINITE)
            return
        if step.focal_px <= 0.0:
            row.set(int(step.t_us), rejected=True, reason=REASON_BAD_FOCAL)
            return
        if not self._admit("optical", step.t_us, 0.0):
            return
        if step.cycle_id != self._last_cycle_pushed:
            self._last_cycle_pushed = int(step.cycle_id)
            if step.base_t_us >= self._t_in_us:
                heapq.heappush(self._heap, (int(step.base_t_us), _PRIO["clone"], next(self._seq), "clone",
                                            int(step.cycle_id)))
                self._n_meas_buffered += 1
        self._push(step.t_us, "optical", step)

    def estimate(self) -> NavEstimate:
        """The current estimate (at :attr:`t_us`), with one-sigma uncertainties and the validity flag.  Computed once
        per filter state: until the state changes, calls return the same object (its arrays are read-only)."""
        if self._imu_q:
            self._process_due()
        e = self._est
        if e is None:
            e = self._est = self._estimate()
        return e

    # ----------------------------------------------------------------------------------------------------------
    # input checks and the buffer
    def _admit(self, source: str, t_us: Any, value: Any) -> bool:
        if self._imu_q:
            self._process_due()                  # what is due is processed first: "late" means the same as ever
        if not _is_int(t_us):
            self._st[source].set(-1, rejected=True, reason=REASON_BAD_TIME)
            return False
        if not _finite(value):
            self._st[source].set(int(t_us), rejected=True, reason=REASON_NON_FINITE)
            return False
        if t_us < self._t_in_us:
            self._st[source].set(int(t_us), rejected=True, reason=REASON_LATE)
            return False
        if self._n_meas_buffered >= self.cfg.buffer_max_events:
            self._st[source].set(int(t_us), rejected=True, reason=REASON_BUFFER_FULL)
            if not self._buffer_full_warned:
                log.warning("EKF buffer full (%d measurements waiting: IMU stopped, or samples stamped ahead of "
                            "the IMU clock?): dropping %s samples", self._n_meas_buffered, source)
                self._buffer_full_warned = True
            return False
        self._buffer_full_warned = False
        return True

    def _push(self, t_us: int, kind: str, payload: Any) -> None:
        t = int(t_us)
        newest = self._newest_imu_us
        if (not self._heap and not self._imu_q and newest is not None and t <= newest - self._delay_us):
            self._process(t, kind, payload)        # nothing waits before it: due now (the usual case without delay)
            return
        heapq.heappush(self._heap, (t, _PRIO[kind], next(self._seq), kind, payload))
        self._n_meas_buffered += 1
        self._process_due()

    def _process_due(self) -> None:
        """Process, in time order, every buffered input at or before the horizon (the IMU samples up to a
        measurement's stamp before it)."""
        if self._newest_imu_us is None:
            return
        horizon = self._newest_imu_us - self._delay_us
        q, heap = self._imu_q, self._heap
        while True:
            if q and q[0][0] <= horizon:
                limit = min(horizon, heap[0][0]) if heap else horizon
                if q[0][0] <= limit:
                    self._run_imu(limit)
                    continue
            if not heap or heap[0][0] > horizon:
                return
            t, _, _, kind, payload = heapq.heappop(heap)
            self._n_meas_buffered -= 1
            self._process(t, kind, payload)

    def _process(self, t: int, kind: str, payload: Any) -> None:
        """Predict to the stamp ``t`` of a due measurement (or clone event) and fuse it."""
        self._predict_to(t)
        if kind == "optical":
            self._do_optical(payload)
        elif kind == "airspeed":
            self._do_airspeed(t, payload)
        elif kind == "baro":
            z_hat, h = BaroAltitude.row(self._kf.x)
            self._fuse1(self._st["baro"], t, z_hat, h, payload, self._r_baro, self.cfg.gate_baro_nis)
        elif kind in ("gnss_pos", "gnss_vel"):
            self._do_gnss(kind, t, *payload)
        elif kind == "clone":
            self._clone(payload)

    # ----------------------------------------------------------------------------------------------------------
    # prediction
    def _run_imu(self, t_end: int) -> None:
        """Process the queued IMU samples stamped at or before ``t_end``, in order.  Each sample covers the interval
        since the previous one with its own specific force, body rates and attitude: it is added to the open segment
        (a new attitude closes the segment first, :meth:`_fold`), and the covariance is predicted once
        ``predict_period_s`` has accumulated.  One loop over local floats: this is the per-sample path."""
        q = self._imu_q
        s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, s10, s11, s12, s13 = self._seg
        opened = self._seg_open
        t_in, t_x = self._t_in_us, self._t_x_us
        period_us, gap_us = self._period_us, self._gap_us
        a0 = self._att
        row = self._st_imu
        n_fused = row.n_fused
        gap = False
        fx = fy = fz = wx = wy = wz = gx = gy = gz = 0.0
        lat, lat_rate, nrm = self._lat_f, self._lat_rate_per_s, self._nrm_f
        if math.isnan(lat) and q:
            lat = q[0][2]                                 # the low-pass starts at the first sample's f_y
            nrm = q[0][3]                                 # ... and f_z
        t = t_in
        while q and q[0][0] <= t_end:
            t, fx, fy, fz, gx, gy, gz, att = q.popleft()
            if att is not a0:
                if (a0 is None or att.yaw_rad != a0.yaw_rad or att.roll_rad != a0.roll_rad
                        or att.pitch_rad != a0.pitch_rad):
                    if opened:
                        self._seg = [s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, s10, s11, s12, s13]
                        self._fold()
                        s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = s9 = s10 = s11 = s12 = s13 = 0.0
                        opened = False
                    self._Rl = _rot_rows(att.roll_rad, att.pitch_rad, att.yaw_rad)
                    self._R_nb = None
                    self._est = None       # the output heading follows the AHRS
                a0 = att
            wx, wy, wz = gy * fz - gz * fy, gz * fx - gx * fz, gx * fy - gy * fx     # omega x f (body)
            dt_us = t - t_in
            gap = dt_us > gap_us and n_fused > 0
            n_fused += 1
            if dt_us > 0:
                dt = dt_us * S_PER_US
                k_lp = min(1.0, dt * lat_rate)
                lat += (fy - lat) * k_lp
                nrm += (fz - nrm) * k_lp
                mid = (t + t_in - 2 * t_x) * (0.5 * S_PER_US)
                ax, ay, az = fx * dt, fy * dt, fz * dt
                s0 += ax
                s1 += ay
                s2 += az
                s3 += ax * mid
                s4 += ay * mid
                s5 += az * mid
                s6 += dt
                s7 += dt * mid
                ax, ay, az = wx * dt, wy * dt, wz * dt
                s8 += ax
                s9 += ay
                s10 += az
                s11 += ax * mid
                s12 += ay * mid
                s13 += az * mid
                opened = True
                t_in = t
                if t_in - t_x >= period_us:
                    self._seg = [s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, s10, s11, s12, s13]
                    self._seg_open, self._t_in_us = opened, t_in
                    self._flush()
                    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = s9 = s10 = s11 = s12 = s13 = 0.0
                    opened = False
                    t_x = self._t_x_us
        self._seg = [s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, s10, s11, s12, s13]
        self._seg_open, self._t_in_us = opened, t_in
        self._att = a0
        self._lat_f = lat
        self._nrm_f = nrm
        if n_fused == row.n_fused:
            return
        self._f_held = (fx, fy, fz, wx, wy, wz)
        self._rates_held = (gx, gy, gz)
        self._est = None                      # the output heading uses the newest body rates
        if row.fused and not row.reason:      # the record already says "fused": only the stamp and count move
            row.t_us = row.t_last_fuse_us = t
            row._snap = None
        else:
            row.fused_now(t, (), (), math.nan)
        row.n_fused = n_fused
        if gap:
            row.reason = REASON_IMU_GAP

    def _fold(self) -> None:
        """Rotate the open segment's sums by its attitude into the prediction's increment."""
        f0, f1, f2, n0, n1, n2, sdt, sdm, k0, k1, k2, j0, j1, j2 = self._seg
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = self._Rl   # type: ignore[misc]
        a = self._acc
        a[0] += r00 * f0 + r01 * f1 + r02 * f2
        a[1] += r10 * f0 + r11 * f1 + r12 * f2
        a[2] += r20 * f0 + r21 * f1 + r22 * f2
        a[3] += r00 * n0 + r01 * n1 + r02 * n2
        a[4] += r10 * n0 + r11 * n1 + r12 * n2
        a[5] += r20 * n0 + r21 * n1 + r22 * n2
        a[6] += r00 * sdt
        a[7] += r01 * sdt
        a[8] += r02 * sdt
        a[9] += r10 * sdt
        a[10] += r11 * sdt
        a[11] += r12 * sdt
        a[12] += r20 * sdt
        a[13] += r21 * sdt
        a[14] += r22 * sdt
        a[15] += r00 * sdm
        a[16] += r01 * sdm
        a[17] += r02 * sdm
        a[18] += r10 * sdm
        a[19] += r11 * sdm
        a[20] += r12 * sdm
        a[21] += r20 * sdm
        a[22] += r21 * sdm
        a[23] += r22 * sdm
        a[24] += r00 * k0 + r01 * k1 + r02 * k2
        a[25] += r10 * k0 + r11 * k1 + r12 * k2
        a[26] += r20 * k0 + r21 * k1 + r22 * k2
        a[27] += r00 * j0 + r01 * j1 + r02 * j2
        a[28] += r10 * j0 + r11 * j1 + r12 * j2
        a[29] += r20 * j0 + r21 * j1 + r22 * j2
        self._seg = [0.0] * _SEG_LEN
        self._seg_open = False

    def _set_scale_fraction(self, g: float) -> None:
        """Partial-update fraction ``g`` of the airspeed scale (0: consider state)."""
        self._gain_scale[S.tas_scale] = g
        part = [(int(i), 1.0 - float(self._gain_scale[i])) for i in np.flatnonzero(self._gain_scale != 1.0)]
        # The Joseph form with the gain K = D K_opt (D = diag(g)), P - K H P - P H' K' + K S K', is P - A o G with
        # A = P H' S^-1 H P and G_ij = g_i + g_j - g_i g_j = 1 - (1 - g_i)(1 - g_j): the optimal-gain update except
        # in the block of these states, where A_ij (1 - g_i)(1 - g_j) is given back.  The correction is D K_opt y.
        self._schmidt = [(i, j, ci * cj) for i, ci in part for j, cj in part]   # (i, j, (1 - g_i)(1 - g_j))

    def _flush(self) -> None:
        """Predict the state and covariance over everything consumed: the filter time becomes ``_t_in_us``."""
        if self._seg_open:
            self._fold()
        T_us = self._t_in_us - self._t_x_us
        if T_us > 0:
            a = self._acc
            self._kf.predict(u=ImuIncrement(T_us * S_PER_US, a[0:3], [a[6:9], a[9:12], a[12:15]], a[3:6],
                                            [a[15:18], a[18:21], a[21:24]], a[24:27], a[27:30]))
            self._acc = [0.0] * _ACC_LEN
            self._est = None
            self._t_x_us = self._t_in_us

    def _predict_to(self, t: int) -> None:
        """Bring the state to ``t`` (>= the inputs consumed) in one prediction: the consumed samples plus the last
        sample held (zero-order hold) from its stamp to ``t``; before the first IMU sample the velocity is held."""
        t_in = self._t_in_us
        dt_us = t - t_in
        if dt_us > 0:
            dt = dt_us * S_PER_US
            mid = (t + t_in - 2 * self._t_x_us) * (0.5 * S_PER_US)
            if self._f_held is not None:
                seg = self._seg
                for k, v in enumerate(self._f_held):          # f (0-2) and omega x f (3-5) of the held sample
                    o = k if k < 3 else k + 5                    # their sums' places in the segment
                    seg[o] += v * dt
                    seg[o + 3] += v * dt * mid
                seg[6] += dt
                seg[7] += dt * mid
                self._seg_open = True
            else:                          # no IMU yet: a specific force of exactly -g (velocity held)
                g_dt = -STANDARD_GRAVITY_M_S2 * dt
                self._acc[2] += g_dt
                self._acc[5] += g_dt * mid
            self._t_in_us = t
        self._flush()

    # ----------------------------------------------------------------------------------------------------------
    # updates (Joseph form as a symmetric rank-m update, see the module docstring)
    def _fuse1(self, row: _StatusRow, t_us: int, z_hat: float, h: Vec, z: float, r: float, gate_nis: float) -> bool:
        """Gated scalar update with Jacobian row ``h`` and variance ``r``; returns whether it was fused."""
        kf = self._kf
        x, P = kf.x, kf.P
        y = z - z_hat
        Ph = P.dot(h)
        hph = float(Ph.dot(h))
        s = hph + r
        if not (math.isfinite(y) and math.isfinite(s)):
            row.set(t_us, rejected=True, reason=REASON_NUMERIC)
            return False
        if hph < -COV_RESET_REL_TOL * r:
            self._cov_reset(row, t_us, np.flatnonzero(h), (y,), (s,))
            return False
        ratio = y * y / s / gate_nis
        if not ratio <= 1.0:
            row.set(t_us, rejected=True, reason=REASON_GATE, innovation=(y,), innovation_var=(s,), test_ratio=ratio)
            return False
        u = (Ph * (1.0 / math.sqrt(s))).reshape(-1, 1)    # u u' = P h' s^-1 h P
        A = u.dot(u.T)
        P_new = P - A
        dx = Ph * (y / s)                             # the optimal-gain correction K_opt y
        if self._schmidt:
            dx *= self._gain_scale
            for i, j, cc in self._schmidt:         # partial-update states: P_ij += (1-g_i)(1-g_j) A_ij
                P_new[i, j] += cc * A[i, j]
        return self._commit(row, t_us, x + dx, P_new, float(Ph.dot(Ph)), (y,), (s,), ratio)

    def _fuse2(self, row: _StatusRow, t_us: int, z_hat: Vec, H: Mat, z: tuple[float, float], r: float,
               gate_nis: float) -> bool:
        """Gated 2-D update with Jacobian ``H`` (2 x n) and covariance ``r I``: ``S = C C'`` factorised in closed
        form, ``L = P H' C^-T`` so that ``P H' S^-1 H P = L L'`` and ``K y = L C^-1 y``."""
        kf = self._kf
        x, P = kf.x, kf.P
        zh0, zh1 = z_hat.tolist()
        y0, y1 = z[0] - zh0, z[1] - zh1
        PHt = P.dot(H.T)
        (a, b), (c, d) = H.dot(PHt).tolist()
        s00, s11, s01 = a + r, d + r, 0.5 * (b + c)
        innov, var = (y0, y1), (s00, s11)
        if not math.isfinite(y0 + y1 + s00 + s11 + s01):
            row.set(t_us, rejected=True, reason=REASON_NUMERIC)
            return False
        if a < -COV_RESET_REL_TOL * r or d < -COV_RESET_REL_TOL * r:
            self._cov_reset(row, t_us, np.flatnonzero(np.any(H != 0.0, axis=0)), innov, var)
            return False
        if not (s00 > 0.0 and s00 * s11 - s01 * s01 > 0.0):
            row.set(t_us, rejected=True, reason=REASON_NUMERIC, innovation=innov, innovation_var=var)
            return False
        c00 = math.sqrt(s00)                          # Cholesky factor C = [[c00, 0], [c10, c11]]
        c10 = s01 / c00
        c11 = math.sqrt(s11 - c10 * c10)
        i00, i10, i11 = 1.0 / c00, -c10 / (c00 * c11), 1.0 / c11     # C^-1 = [[i00, 0], [i10, i11]]
        w0, w1 = i00 * y0, i10 * y0 + i11 * y1        # C^-1 y (whitened innovation)
        ratio = (w0 * w0 + w1 * w1) / gate_nis
        if not ratio <= 1.0:
            row.set(t_us, rejected=True, reason=REASON_GATE, innovation=innov, innovation_var=var, test_ratio=ratio)
            return False
        L = PHt.dot(np.array(((i00, i10), (0.0, i11))))   # P H' C^-T
        A = L.dot(L.T)
        P_new = P - A
        dx = L.dot(np.array((w0, w1)))                # K_opt y
        if self._schmidt:
            dx *= self._gain_scale
            for i, j, cc in self._schmidt:         # partial-update states: P_ij += (1-g_i)(1-g_j) A_ij
                P_new[i, j] += cc * A[i, j]
        return self._commit(row, t_us, x + dx, P_new, float(A.trace()), innov, var, ratio)

    def _fuse_sel(self, row: _StatusRow, t_us: int, idx: list[int], z: Vec, r: list[float], gate_nis: float) -> bool:
        """Gated update of a direct measurement of the states ``idx`` (``H`` = those rows of the identity, so
        ``P H'`` is a column selection) with diagonal covariance ``r``: ``S = C C'`` factorised in floats,
        ``L = P H' C^-T``, as :meth:`_fuse2`."""
        kf = self._kf
        x, P = kf.x, kf.P
        m = len(idx)
        y = (z - x[idx]).tolist()
        PHt = P[:, idx]
        hph = PHt[idx].tolist()
        Sm = [[0.5 * (hph[i][j] + hph[j][i]) + (r[i] if i == j else 0.0) for j in range(m)] for i in range(m)]
        innov, var = tuple(y), tuple(Sm[i][i] for i in range(m))
        if not math.isfinite(sum(y) + sum(map(sum, Sm))):
            row.set(t_us, rejected=True, reason=REASON_NUMERIC)
            return False
        if any(hph[i][i] < -COV_RESET_REL_TOL * r[i] for i in range(m)):
            self._cov_reset(row, t_us, np.array(idx), innov, var)
            return False
        Ci = _chol_inv(Sm)
        if Ci is None:
            row.set(t_us, rejected=True, reason=REASON_NUMERIC, innovation=innov, innovation_var=var)
            return False
        w = [sum(Ci[i][k] * y[k] for k in range(i + 1)) for i in range(m)]     # C^-1 y
        ratio = sum(v * v for v in w) / gate_nis
        if not ratio <= 1.0:
            row.set(t_us, rejected=True, reason=REASON_GATE, innovation=innov, innovation_var=var, test_ratio=ratio)
            return False
        L = PHt.dot(np.array(Ci).T)                  # P H' C^-T
        A = L.dot(L.T)
        P_new = P - A
        dx = L.dot(np.array(w))
        if self._schmidt:
            dx *= self._gain_scale
            for i, j, cc in self._schmidt:         # partial-update states: P_ij += (1-g_i)(1-g_j) A_ij
                P_new[i, j] += cc * A[i, j]
        return self._commit(row, t_us, x + dx, P_new, float(A.trace()), innov, var, ratio)

    def _commit(self, row: _StatusRow, t_us: int, x_new: Vec, P_new: Mat, check: float, innov: tuple[float, ...],
                var: tuple[float, ...], ratio: float) -> bool:
        """Store the corrected state unless ``check`` (a sum of squares or products of every element of the update's
        factors, e.g. ``u @ u``) is non-finite; then the prior is kept.  A NaN or inf in a factor makes that sum
        non-finite, and with finite factors the update is finite: ``P`` is finite, and the NIS gate bounds
        ``|K y|`` by ``sqrt(gate * P_ii)`` and the subtracted term by ``|P_ij|``-sized values."""
        if not math.isfinite(check):
            row.set(t_us, rejected=True, reason=REASON_NUMERIC, innovation=innov, innovation_var=var,
                    test_ratio=ratio)
            return False
        self._kf.x, self._kf.P = x_new, P_new
        self._est = None
        row.fused_now(t_us, innov, var, ratio)
        return True

    def _store(self, x: Vec, P: Mat) -> None:
        self._kf.x, self._kf.P = x, P
        self._est = None

    def _cov_reset(self, row: _StatusRow, t_us: int, cols: NDArray[np.intp], innov: tuple[float, ...],
                   var: tuple[float, ...]) -> None:
        self._reset_covariance(cols)
        log.warning("EKF %s at %d us: innovation variance below observation variance, covariance of states %s reset",
                    row.source, t_us, cols.tolist())
        row.set(t_us, rejected=True, reason=REASON_COV_RESET, innovation=innov, innovation_var=var)

    def _initial_variances(self) -> Vec:
        c = self.cfg
        var = np.zeros(S.dim)
        var[S.pos_ne] = c.init_pos_ne_sigma_m**2
        var[S.pos_d] = c.init_pos_d_sigma_m**2
        var[S.vel_ne] = c.init_vel_ne_sigma_m_s**2
        var[S.vel_d] = c.init_vel_d_sigma_m_s**2
        var[S.wind_ne] = c.init_wind_sigma_m_s**2
        var[S.wind_mean_ne] = c.init_wind_sigma_m_s**2
        var[S.wind_d] = (c.wind_d_sigma_ratio * c.wind_turb_sigma_m_s)**2     # the turbulence's stationary variance
        var[S.accel_bias_b] = c.init_accel_bias_sigma_m_s2**2
        var[S.yaw_bias] = c.init_yaw_bias_sigma_rad**2
        var[S.opt_rot] = c.init_opt_rot_sigma_rad**2
        var[S.baro_bias] = c.init_baro_bias_sigma_m**2
        var[S.terrain_h] = c.init_terrain_sigma_m**2
        var[S.tas_scale] = c.init_tas_scale_sigma**2
        var[S.att_delay] = c.init_att_delay_sigma_s**2
        var[S.side_force_ofs] = c.init_side_force_ofs_sigma_m_s2**2
        var[S.aoa_ofs] = math.radians(c.init_aoa_ofs_sigma_deg)**2
        var[S.base_pos_ne] = c.init_pos_ne_sigma_m**2
        var[S.base_pos_d] = c.init_pos_d_sigma_m**2
        return var

    def _reset_covariance(self, idx: NDArray[np.intp]) -> None:
        P = self._kf.P.copy()
        P[idx, :] = 0.0
        P[:, idx] = 0.0
        P[idx, idx] = self._init_var[idx]
        self._store(self._kf.x, P)
        if np.intersect1d(idx, np.concatenate([_I_POS, _I_CLONE])).size:
            self._clone_cycle = None

    def _reset_states(self, idx: NDArray[np.intp], z: Vec, R: Mat) -> None:
        x = self._kf.x.copy()
        P = self._kf.P.copy()
        x[idx] = z
        P[idx, :] = 0.0
        P[:, idx] = 0.0
        P[np.ix_(idx, idx)] = R
        self._store(x, P)
        if np.intersect1d(idx, _I_POS).size:   # the position jumped: the current cycle's clone no longer applies
            self._clone_cycle = None

    def _do_airspeed(self, t: int, tas: float) -> None:
        c = self.cfg
        if tas < c.tas_min_m_s:
            self._st["airspeed"].set(t, reason=REASON_LOW_AIRSPEED)
            self._st["sideslip"].set(t, reason=REASON_LOW_AIRSPEED)
            self._st["aoa"].set(t, reason=REASON_LOW_AIRSPEED)
            return
        if self._wind_reset_pending and self._att is not None:
            self._reset_wind(tas)
            self._st["airspeed"].set(t, reason=REASON_WIND_RESET)
            return
        kf = self._kf
        # the scale's fraction follows the turbulence level (full update in calm air; see EkfConfig)
        calm = t >= self._calm_known_us and kf.turb_var <= c.tas_scale_calm_turb_sigma_max_m_s**2
        g = c.tas_scale_calm_fraction if calm else c.tas_scale_update_fraction
        if g != self._gain_scale[_I_SCALE]:
            self._set_scale_fraction(g)
        z_hat, h = TrueAirspeed.row(kf.x)
        self._fuse1(self._st["airspeed"], t, z_hat, h, tas, TrueAirspeed.variance(c, kf.turb_var),
                    c.gate_airspeed_nis)
        if c.sideslip_fusion:
            if self._Rl is None:
                self._st["sideslip"].set(t, reason=REASON_NO_ATTITUDE)
            else:
                if self._R_nb is None:
                    self._R_nb = np.array(self._Rl).reshape(3, 3)
                # the side-force sideslip (measured value) from the lateral specific force and the corrected
                # airspeed; 0 with the model off (zero sideslip)
                k_beta, z_beta = 0.0, 0.0
                v_air = max(tas / (1.0 + float(kf.x[_I_SCALE])), c.tas_min_m_s)
                if self._beta_gain_m and not math.isnan(self._lat_f):
                    k_beta = self._beta_gain_m / (v_air * v_air)
                    z_beta = k_beta * self._lat_f
                z_hat, h = SyntheticSideslip(self._R_nb, k_beta).row(self._kf.x)
                self._fuse1(self._st["sideslip"], t, z_hat, h, z_beta,
                            SyntheticSideslip.variance(c, kf.turb_var, v_air), c.gate_sideslip_nis)
        if self._alpha_gain_m:
            if self._Rl is None or math.isnan(self._nrm_f):
                self._st["aoa"].set(t, reason=REASON_NO_ATTITUDE)
            else:
                if self._R_nb is None:
                    self._R_nb = np.array(self._Rl).reshape(3, 3)
                v_air = max(tas / (1.0 + float(kf.x[_I_SCALE])), c.tas_min_m_s)
                z_alpha = LiftAngleOfAttack.measured(c, self._nrm_f, v_air)
                if abs(z_alpha) > self._alpha_max_rad:       # stall, or a pull beyond the linear lift curve
                    self._st["aoa"].set(t, reason=REASON_AOA_RANGE)
                    return
                z_hat, h = LiftAngleOfAttack(self._R_nb, self._alpha_gain_m / (v_air * v_air)).row(kf.x)
                self._fuse1(self._st["aoa"], t, z_hat, h, z_alpha,
                            LiftAngleOfAttack.variance(c, kf.turb_var, v_air), c.gate_aoa_nis)

    def _reset_wind(self, tas: float) -> None:
        """Wind from the wind triangle (:meth:`TrueAirspeed.wind_from_airspeed`) with its covariance
        ``J P J' + sigma_tas^2 a a' + sigma_beta^2 b b'`` and cross covariance ``J P``."""
        assert self._att is not None
        x, P = self._kf.x, self._kf.P
        wind, J, d_tas, d_beta = TrueAirspeed.wind_from_airspeed(x, tas, self._att.yaw_rad)
        A = J @ P
        iw, im = _I_WIND, _I_WMEAN
        x_new = x.copy()
        x_new[iw] = wind
        x_new[im] = wind                           # the mean: the same wind, less the turbulence (unknown, zero mean)
        P_new = P.copy()
        P_new[iw, :] = A
        P_new[:, iw] = A.T
        P_new[im, :] = A
        P_new[:, im] = A.T
        Pww = (A @ J.T + self.cfg.tas_sigma_m_s**2 * np.outer(d_tas, d_tas)
               + self.cfg.sideslip_sigma_rad**2 * np.outer(d_beta, d_beta))
        P_new[np.ix_(iw, iw)] = Pww
        P_new[np.ix_(iw, im)] = Pww
        P_new[np.ix_(im, iw)] = Pww
        P_new[np.ix_(im, im)] = Pww + self._kf.turb_var * np.eye(2)
        self._store(x_new, 0.5 * (P_new + P_new.T))
        self._wind_reset_pending = False

    def _do_gnss(self, source: str, t: int, z: Vec, sigmas: tuple[float | None, float | None]) -> None:
        c = self.cfg
        if source == "gnss_pos":
            model: GnssPosition | GnssVelocity = GnssPosition(dim=z.shape[0])
            gate = c.gate_gnss_pos_nis
            r = model.variances(c, *sigmas)
            # correlated receiver error: fixes closer than the correlation time share their error
            if self._gnss_pos_last_us is not None and c.gnss_pos_corr_time_s > 0.0:
                dt = max(t - self._gnss_pos_last_us, 1) / US_PER_S
                k = max(1.0, 2.0 * c.gnss_pos_corr_time_s / dt)
                r = [v * k for v in r]
            self._gnss_pos_last_us = t
        else:
            model = GnssVelocity(dim=z.shape[0])
            gate = c.gate_gnss_vel_nis
            r = model.variances(c, *sigmas)
        row = self._st[source]
        idx = model.state_idx
        if self._fuse_sel(row, t, idx, z, r, gate):
            self._reject_since[source] = None
            return
        if row.reason != REASON_GATE:
            return
        since = self._reject_since[source]
        if since is None:
            self._reject_since[source] = t
        elif t - since >= c.gnss_reset_after_s * US_PER_S:
            self._reset_states(np.array(idx), z, np.diag(r))
            self._reject_since[source] = None
            log.warning("EKF: %s rejected for %.1f s, state reset to GNSS at %d us", source, (t - since) / US_PER_S, t)
            row.n_rejected -= 1                  # this sample was used after all
            row.set(t, fused=True, reason=REASON_RESET_TO_MEAS, innovation=row.innovation,
                    innovation_var=row.innovation_var, test_ratio=row.test_ratio)

    def _clone(self, cycle_id: int) -> None:
        x = self._kf.x.copy()
        P = self._kf.P.copy()
        x[_I_CLONE] = x[_I_POS]
        P[_I_CLONE, :] = P[_I_POS, :]
        P[:, _I_CLONE] = P[:, _I_POS]
        self._store(x, P)
        self._clone_cycle = cycle_id

    def _clone_from_step(self, model: OpticalDisplacement, step: GsoeStep, R: Mat) -> None:
        """Anchor a cycle whose base time is behind the horizon on its first step: the clone becomes the base position
        reconstructed from the step (:meth:`OpticalDisplacement.base_from_step`), with covariance ``J P J' + K R K'``
        and cross covariance ``J P``, so the step's error is carried, correlated, by the cycle's later steps."""
        x, P = self._kf.x, self._kf.P
        base, J, Kz = model.base_from_step(x, np.array([step.dx_px, step.dy_px]))
        A = J @ P
        x_new = x.copy()
        x_new[_I_CLONE] = base
        P_new = P.copy()
        P_new[_I_CLONE, :] = A
        P_new[:, _I_CLONE] = A.T
        P_new[np.ix_(_I_CLONE, _I_CLONE)] = A @ J.T + Kz @ R @ Kz.T
        self._store(x_new, 0.5 * (P_new + P_new.T))
        self._clone_cycle = int(step.cycle_id)

    def _do_optical(self, step: GsoeStep) -> None:
        c = self.cfg
        t = int(step.t_us)
        row = self._st["optical"]
        if step.t_us <= step.base_t_us:
            row.set(t, reason=REASON_BASE_FRAME)
            return
        if not (step.valid and step.quality.valid):
            row.set(t, rejected=True, reason=REASON_INVALID_MATCH)
            return
        model = OpticalDisplacement(focal_px=float(step.focal_px), base_yaw_rad=float(step.base_yaw_rad))
        x = self._kf.x
        if model.height_base_m(x) < c.optical_min_height_m:
            row.set(t, rejected=True, reason=REASON_LOW_HEIGHT)
            return
        r = OpticalDisplacement.noise_var_px2(step, c)
        if self._clone_cycle != step.cycle_id:
            if self._clone_cycle is not None and step.cycle_id < self._clone_cycle:
                row.set(t, rejected=True, reason=REASON_STALE_CYCLE)
                return
            self._clone_from_step(model, step, np.eye(2) * r)
            row.set(t, reason=REASON_ANCHORED)
            return
        z_hat, H = model.linearise(x)
        self._fuse2(row, t, z_hat, H, (float(step.dx_px), float(step.dy_px)), r, c.gate_optical_nis)

    # ----------------------------------------------------------------------------------------------------------
    # output
    def _estimate(self) -> NavEstimate:
        x, P = self._kf.x, self._kf.P
        xl = x.tolist()
        xr = _read_only(x.copy())                  # the output's vectors are read-only views of this copy
        sd = _read_only(np.sqrt(np.maximum(P.diagonal(), 0.0)))
        # the covariance entries the derived outputs need, in one gather (see _EST_FLAT)
        (pnn, pne, pee, pyy, pny, pey, qnn, qne, qee, pdd, ptt, pdt, pdd_t, pyd, pnd, ped) = P.take(_EST_FLAT).tolist()
        iv, iw = S.vel_ne.start, S.wind_ne.start
        vn, ve = xl[iv], xl[iv + 1]
        gs = math.hypot(vn, ve)
        # course = atan2(ve, vn); gradient w.r.t. (vn, ve) = (-ve, vn) / gs^2
        course = float(wrap_2pi(math.atan2(ve, vn)))
        if gs > 0.0:
            gn, ge = -ve / (gs * gs), vn / (gs * gs)
            var_c = gn * gn * pnn + 2.0 * gn * ge * pne + ge * ge * pee
            gs_var = (vn * vn * pnn + 2.0 * vn * ve * pne + ve * ve * pee) / (gs * gs)
            gs_sd = math.sqrt(max(gs_var, 0.0))
        else:
            gn = ge = 0.0
            var_c, gs_sd = math.inf, math.sqrt(max((pnn + pee) / 2.0, 0.0))
        course_sd = min(math.pi, math.sqrt(max(var_c, 0.0)))
        # heading = yaw_ahrs - yaw_bias + yaw_rate * att_delay (the AHRS heading lags the turn by the delay);
        # drift = course - heading
        yb, tau = xl[_I_YAW], xl[_I_DELAY]
        att = self._att if self._att is not None else self._att_out
        if att is not None:
            rate = _yaw_rate(att, self._rates_held)
            heading = float(wrap_2pi(att.yaw_rad - yb + rate * tau))
            drift = float(angle_diff(course, heading))
            var_h = pyy - 2.0 * rate * pyd + rate * rate * pdd_t
            # d drift / d (vel_n, vel_e, yaw_bias, att_delay) = (gn, ge, 1, -rate)
            var_d = var_c + var_h + 2.0 * (gn * pny + ge * pey) - 2.0 * rate * (gn * pnd + ge * ped)
            drift_sd = min(math.pi, math.sqrt(max(var_d, 0.0))) if gs > 0.0 else math.pi
            heading_sd = math.sqrt(max(var_h, 0.0))
        else:
            heading = drift = math.nan
            drift_sd = heading_sd = math.pi
        # wind speed and the direction it blows from: atan2(-we, -wn); gradient (-we, wn) / ws^2
        wn, we = xl[iw], xl[iw + 1]
        ws = math.hypot(wn, we)
        w_from = float(wrap_2pi(math.atan2(-we, -wn)))
        if ws > 0.0:
            dn, de = -we / (ws * ws), wn / (ws * ws)
            wd_sd = min(math.pi, math.sqrt(max(dn * dn * qnn + 2.0 * dn * de * qne + de * de * qee, 0.0)))
            ws_sd = math.sqrt(max((wn * wn * qnn + 2.0 * wn * we * qne + we * we * qee) / (ws * ws), 0.0))
        else:
            wd_sd, ws_sd = math.pi, math.sqrt(max((qnn + qee) / 2.0, 0.0))
        # height above ground: -pos_d - terrain_h
        ipd, ith = S.pos_d.start, S.terrain_h.start
        h_agl_sd = math.sqrt(max(pdd + ptt + 2.0 * pdt, 0.0))
        vel_sd_max = math.sqrt(max(pnn, pee, 0.0))
        valid, why = self._validity(vel_sd_max, gs, drift_sd)
        return NavEstimate(
            t_us=self._t_x_us,
            pos_ne_m=xr[S.pos_ne], pos_ne_sigma_m=sd[S.pos_ne],
            height_m=-xl[ipd], height_sigma_m=math.sqrt(max(pdd, 0.0)),
            height_agl_m=-xl[ipd] - xl[ith], height_agl_sigma_m=h_agl_sd,
            vel_ned_m_s=xr[S.vel_ned], vel_ned_sigma_m_s=sd[S.vel_ned],
            ground_speed_m_s=gs, ground_speed_sigma_m_s=gs_sd,
            course_rad=course, course_sigma_rad=course_sd,
            wind_ne_m_s=xr[S.wind_ne], wind_ne_sigma_m_s=sd[S.wind_ne],
            wind_speed_m_s=ws, wind_speed_sigma_m_s=ws_sd, wind_from_rad=w_from, wind_from_sigma_rad=wd_sd,
            wind_d_m_s=xl[_I_WD], wind_d_sigma_m_s=float(sd[_I_WD]),
            heading_rad=heading, heading_sigma_rad=heading_sd,
            drift_rad=drift, drift_sigma_rad=drift_sd,
            ata_rad=course, ata_sigma_rad=course_sd,
            accel_bias_b_m_s2=xr[S.accel_bias_b], yaw_bias_rad=yb, opt_rot_rad=xl[S.opt_rot.start],
            baro_bias_m=xl[S.baro_bias.start],
            terrain_h_m=xl[ith], tas_scale=xl[S.tas_scale.start], side_force_ofs_m_s2=xl[S.side_force_ofs.start],
            aoa_ofs_rad=xl[S.aoa_ofs.start], wind_turb_sigma_m_s=math.sqrt(self._kf.turb_var),
            cov_pvw=_read_only(P[_IX_PVW]),
            valid=valid, invalid_reason=why,
        )

    def _validity(self, vel_sd_max: float, gs: float, drift_sd: float) -> tuple[bool, str]:
        c = self.cfg
        if self._att is None:
            return False, REASON_NO_ATTITUDE
        if vel_sd_max > c.valid_vel_sigma_max_m_s:
            return False, "velocity sigma above valid_vel_sigma_max_m_s"
        if gs < c.valid_min_ground_speed_m_s:
            return False, "ground speed below valid_min_ground_speed_m_s"
        if drift_sd > c.valid_drift_sigma_max_rad:
            return False, "drift sigma above valid_drift_sigma_max_deg"
        timeout_us = c.valid_aid_timeout_s * US_PER_S
        last = max(self._st[s].t_last_fuse_us for s in ("optical", "gnss_pos", "gnss_vel"))
        if last < 0 or self._t_x_us - last > timeout_us:
            return False, "no optical or GNSS fused within valid_aid_timeout_s"
        return True, ""
