"""The navigation EKF: IMU-driven prediction, optical displacement, airspeed, sideslip, baro and GNSS updates.

Usage (every method documents its units; frames as in :mod:`gsoe`)::

    ekf = NavEkf(cfg, t_us=t0, pos_ned_m=p0, vel_ned_m_s=v0)      # fully configured when built
    ekf.predict(imu, att)                 # every IMU sample, with the AHRS attitude valid at (about) imu.t_us
    ekf.fuse_airspeed(t_us, tas_m_s)      # whenever a sample arrives, in any order within the fusion delay
    ekf.fuse_baro(t_us, alt_m)
    ekf.fuse_gnss(t_us, pos_ned_m, vel_ned_m_s)
    ekf.fuse_optical(step)                # every gsoe.types.GsoeStep, including the new-cycle (base) steps
    est = ekf.estimate()                  # NavEstimate with one-sigma uncertainties and a validity flag
    st = ekf.status()                     # per aid source: innovation, variance, test ratio, fused/rejected

Numerical core
    filterpy's :class:`~filterpy.kalman.ExtendedKalmanFilter` holds ``x`` and ``P`` and does the covariance
    prediction ``P = F P F' + Q``; its documented extension point ``predict_x`` runs our (nonlinear) mean
    propagation and sets ``F``.  The update is ours, because filterpy's inverts ``S`` and has no gating: the
    innovation covariance is factorised with ``solve``, the NIS is gated against a named threshold, the covariance
    is updated in Joseph form and symmetrised, and nothing is committed unless the result is finite (the state is
    copied before the correction, as navlie does).  When an innovation variance falls below its observation
    variance (``H P H' < 0``: ``P`` has lost positive definiteness) the states the measurement touches get their
    initial covariance back and the measurement is skipped (PX4 EKF2).

Prediction
    ``v' = R_z(-yaw_bias) R_nb_ahrs (f_b - accel_bias_b) + g_n`` and ``p' = v``; IMU samples are accumulated (sums of
    ``R_nb f dt`` and ``R_nb dt``) into one prediction of at least ``predict_period_s`` (the mean is exact for a
    piecewise constant specific force; the bias and heading Jacobians use the sums).  Process noise from
    :class:`~fusion.config.EkfConfig` (white acceleration on each NED axis, random walks on the slow states).

Time (STYLE section 6)
    Every input carries its ``t_us``.  Inputs go into one time-ordered buffer and the filter runs on a *delayed
    fusion horizon* ``fusion_delay_s`` behind the newest IMU sample (PX4 EKF2's ``pop_first_older_than``): a
    measurement is fused at its own stamp, the state being predicted from the last IMU sample to it.  An input older
    than what the filter has already processed is rejected with reason ``late`` in its status.  The estimate refers
    to the horizon's time ``NavEstimate.t_us`` (at most ``fusion_delay_s + predict_period_s`` behind the newest IMU
    sample); give ``fusion_delay_s = 0`` when samples are fed in time order.  Samples with the same stamp are
    processed in a fixed order (IMU, GNSS, baro, airspeed + sideslip, optical, clone) whatever their arrival order,
    so a replay with other latencies gives the same filter.  The synthetic sideslip uses the AHRS attitude of the
    last IMU sample at or before its stamp.

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
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import ExtendedKalmanFilter
from numpy.typing import ArrayLike, NDArray
from scipy.constants import g as STANDARD_GRAVITY_M_S2

from fusion.config import EkfConfig
from fusion.measurements import (
    BaroAltitude,
    GnssPosition,
    GnssVelocity,
    MeasurementModel,
    OpticalDisplacement,
    SyntheticSideslip,
    TrueAirspeed,
)
from fusion.state import S
from gsoe.angles import angle_diff, wrap_2pi
from gsoe.types import AttitudeSample, GsoeStep, ImuSample

log = logging.getLogger(__name__)

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]

US_PER_S = 1_000_000
#: Relative tolerance of the covariance-health check: ``H P H'`` counts as negative (the PX4 condition "innovation
#: variance below observation variance") when a diagonal element is below ``-COV_RESET_REL_TOL * R``; smaller
#: negatives are rounding of an exactly zero variance (e.g. a clone taken this instant).
COV_RESET_REL_TOL = 1e-9

#: Aid sources with a status record, in logging order.
AID_SOURCES: tuple[str, ...] = ("imu", "optical", "airspeed", "sideslip", "baro", "gnss_pos", "gnss_vel")

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

# Processing order of buffered events with the same stamp (independent of arrival order, so a replay with other
# latencies gives the same filter): the IMU sample first (the state is predicted to the stamp), then GNSS, baro,
# airspeed, optical, and last the clone of a cycle starting at this stamp (after the previous cycle's last step).
_PRIO = {"imu": 0, "gnss_pos": 1, "gnss_vel": 2, "baro": 3, "airspeed": 4, "optical": 5, "clone": 6}


def _is_int(t: Any) -> bool:
    return isinstance(t, int | np.integer) and not isinstance(t, bool)


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


def R_nb_321(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Mat:
    """Body-to-NED rotation from 3-2-1 Euler angles; the same as :func:`gsoe.rotation.R_nb_from_euler` (a test
    checks it) written out, because building a scipy ``Rotation`` per IMU sample costs more than the EKF step."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


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
    """Mutable twin of :class:`AidStatus` updated at sample rate (frozen records are built only in ``status()``)."""

    __slots__ = ("source", "t_us", "innovation", "innovation_var", "test_ratio", "fused", "rejected", "reason",
                 "t_last_fuse_us", "n_fused", "n_rejected")

    def __init__(self, source: str) -> None:
        self.source = source
        self.t_us = -1
        self.innovation: Vec | None = None
        self.innovation_var: Vec | None = None
        self.test_ratio = math.nan
        self.fused = self.rejected = False
        self.reason = ""
        self.t_last_fuse_us = -1
        self.n_fused = self.n_rejected = 0

    def set(self, t_us: int, *, fused: bool = False, rejected: bool = False, reason: str = "",
            innovation: Vec | None = None, innovation_var: Vec | None = None, test_ratio: float = math.nan) -> None:
        self.t_us = t_us
        self.fused, self.rejected, self.reason = fused, rejected, reason
        self.innovation, self.innovation_var, self.test_ratio = innovation, innovation_var, test_ratio
        if fused:
            self.t_last_fuse_us = t_us
            self.n_fused += 1
        if rejected:
            self.n_rejected += 1

    def snapshot(self) -> AidStatus:
        return AidStatus(
            self.source, t_us=self.t_us,
            innovation=tuple(float(v) for v in self.innovation) if self.innovation is not None else (),
            innovation_var=tuple(float(v) for v in self.innovation_var) if self.innovation_var is not None else (),
            test_ratio=float(self.test_ratio), fused=self.fused, rejected=self.rejected, reason=self.reason,
            t_last_fuse_us=self.t_last_fuse_us, n_fused=self.n_fused, n_rejected=self.n_rejected)


@dataclass(frozen=True, slots=True)
class NavEstimate:
    """The filter's output at ``t_us`` (the fusion horizon), with one-sigma uncertainties.

    Positions in the local NED frame (m); ``height_m`` above the reference ground, ``height_agl_m`` above the ground
    under the aircraft.  Velocities are ground velocities (m/s).  Angles in radians, clockwise from north:
    ``course_rad`` (of the ground velocity, [0, 2 pi)), ``heading_rad`` (AHRS yaw corrected by the estimated
    heading error), ``drift_rad`` = course - heading in [-pi, pi) (positive: track to the right of the heading),
    ``ata_rad`` = the paper's eq. 12 actual tracking angle ``beta + psi + drift``, i.e. the EKF's course over
    ground.  ``wind_ne_m_s`` is the velocity of the air (blowing *to*); ``wind_from_rad`` the direction it blows
    *from* (MAVLink WIND).  Angle sigmas are capped at pi where the angle is undefined (speed near zero).
    ``yaw_bias_rad``, ``opt_rot_rad``, ``baro_bias_m``, ``terrain_h_m``, ``tas_scale``, ``accel_bias_b_m_s2``: the
    calibration states (:mod:`fusion.state`).  ``cov_pvw`` is the 6x6 covariance of ``[pos_ne, vel_ne, wind_ne]``
    (for NEES).  ``valid`` is false with
    ``invalid_reason`` when the output should not be used (see :class:`~fusion.config.EkfConfig`).
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
            heading_rad=self.heading_rad, heading_sigma_rad=self.heading_sigma_rad,
            drift_rad=self.drift_rad, drift_sigma_rad=self.drift_sigma_rad,
            ata_rad=self.ata_rad, ata_sigma_rad=self.ata_sigma_rad,
            accel_bias_x_m_s2=float(self.accel_bias_b_m_s2[0]), accel_bias_y_m_s2=float(self.accel_bias_b_m_s2[1]),
            accel_bias_z_m_s2=float(self.accel_bias_b_m_s2[2]), yaw_bias_rad=self.yaw_bias_rad,
            opt_rot_rad=self.opt_rot_rad,
            baro_bias_m=self.baro_bias_m, terrain_h_m=self.terrain_h_m, tas_scale=self.tas_scale,
            valid=self.valid, invalid_reason=self.invalid_reason,
        )
        return r


# --------------------------------------------------------------------------------------------------------------
@dataclass(slots=True)
class ImuIncrement:
    """IMU input of one prediction over ``dt_s``: ``dv_ahrs_n = sum(R_nb f_b dt)`` (m/s, AHRS-NED, no gravity, no
    bias correction) and ``int_R_nb = sum(R_nb dt)`` (s) for the bias Jacobian."""

    dt_s: float = 0.0
    dv_ahrs_n: Vec = field(default_factory=lambda: np.zeros(3))
    int_R_nb: Mat = field(default_factory=lambda: np.zeros((3, 3)))


_I_POS = S.idx("pos_ned")
_I_VEL = S.idx("vel_ned")
_I_CLONE = S.idx("base_pos_ned")
_I_YAW = S.yaw_bias.start
_I_PVW = S.idx("pos_ne", "vel_ne", "wind_ne")
_POS, _VEL, _BA = S.pos_ned, S.vel_ned, S.accel_bias_b
_EYE = np.eye(S.dim)
_EYE.flags.writeable = False
_F_POS_VEL = np.ravel_multi_index((_I_POS, _I_VEL), (S.dim, S.dim))     # flat indices of dpos/dvel in F


def propagate(x: Vec, inc: ImuIncrement) -> tuple[Vec, Mat]:
    """Mean propagation over one increment and its Jacobian ``F = d x_new / d x`` (n x n)."""
    T = inc.dt_s
    m = inc.dv_ahrs_n - inc.int_R_nb @ x[_BA]
    c, s = math.cos(x[_I_YAW]), math.sin(x[_I_YAW])      # R_z(-yaw_bias) = [[c, s], [-s, c]]
    mp = np.array([c * m[0] + s * m[1], -s * m[0] + c * m[1], m[2]])
    dv = mp.copy()
    dv[2] += STANDARD_GRAVITY_M_S2 * T
    xn = x.copy()
    v = x[_VEL]
    xn[_POS] = x[_POS] + v * T + 0.5 * T * dv
    xn[_VEL] = v + dv
    F = _EYE.copy()
    F.flat[_F_POS_VEL] = T
    Rz = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    A = -(Rz @ inc.int_R_nb)
    F[_VEL, _BA] = A
    F[_POS, _BA] = 0.5 * T * A
    F[_VEL, _I_YAW] = (mp[1], -mp[0], 0.0)
    F[_POS, _I_YAW] = (0.5 * T * mp[1], -0.5 * T * mp[0], 0.0)
    return xn, F


class _FilterCore(ExtendedKalmanFilter):
    """filterpy's EKF with our mean propagation: ``predict(u=ImuIncrement)`` runs :func:`propagate` (which also sets
    ``F`` at the prior state) and the process noise for the increment's length, then filterpy's ``P = F P F' + Q``."""

    def __init__(self, x0: Vec, P0: Mat, cfg: EkfConfig) -> None:
        super().__init__(dim_x=S.dim, dim_z=1)
        self.x = x0
        self.P = P0
        self._cfg = cfg
        self._q_cache: dict[int, Mat] = {}

    def process_noise(self, dt_s: float) -> Mat:
        key = round(dt_s * US_PER_S)
        Q = self._q_cache.get(key)
        if Q is None:
            c = self._cfg
            Q = np.zeros((S.dim, S.dim))
            qpv = Q_continuous_white_noise(dim=2, dt=dt_s, spectral_density=c.accel_noise_m_s2_per_rt_hz**2)
            for ip, iv in zip(_I_POS, _I_VEL, strict=True):
                Q[np.ix_([ip, iv], [ip, iv])] = qpv
            rw = {
                "wind_ne": c.wind_rw_m_s_per_rt_s,
                "accel_bias_b": c.accel_bias_rw_m_s2_per_rt_s,
                "yaw_bias": c.yaw_bias_rw_rad_per_rt_s,
                "opt_rot": c.opt_rot_rw_rad_per_rt_s,
                "baro_bias": c.baro_bias_rw_m_per_rt_s,
                "terrain_h": c.terrain_rw_m_per_rt_s,
                "tas_scale": c.tas_scale_rw_per_rt_s,
            }
            for name, q in rw.items():
                i = S.idx(name)
                Q[i, i] = q * q * dt_s
            if len(self._q_cache) > 64:
                self._q_cache.clear()
            self._q_cache[key] = Q
        return Q

    def predict_x(self, u: ImuIncrement = None) -> None:  # type: ignore[assignment]
        self.x, self.F = propagate(self.x, u)
        self.Q = self.process_noise(u.dt_s)

    def predict(self, u: ImuIncrement = None) -> None:  # type: ignore[assignment]
        """filterpy's prediction, then ``P`` symmetrised (``F P F'`` is symmetric only up to rounding)."""
        super().predict(u)
        self.P = 0.5 * (self.P + self.P.T)


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
        x0[S.terrain_h] = arr["terrain_h_m"]
        x0[S.base_pos_ned] = arr["pos_ned_m"]
        self._init_var = self._initial_variances()
        # partial-update (Schmidt) states: their rows of every gain are scaled down (see the module docstring)
        self._gain_scale = np.ones(S.dim)
        self._gain_scale[S.tas_scale] = cfg.tas_scale_update_fraction
        P0 = np.diag(self._init_var)
        P0[np.ix_(_I_CLONE, _I_POS)] = P0[np.ix_(_I_POS, _I_POS)]
        P0[np.ix_(_I_POS, _I_CLONE)] = P0[np.ix_(_I_POS, _I_POS)]
        self._kf = _FilterCore(x0, P0, cfg)
        self._t_x_us = int(t_us)           # time of the filter state (the fusion horizon)
        self._t_in_us = int(t_us)          # inputs consumed up to here (>= _t_x_us; the rest is in _acc)
        self._acc = ImuIncrement()
        self._held: tuple[Vec, Mat] | None = None   # last IMU sample: (R_nb f_b, R_nb)
        self._att: AttitudeSample | None = None          # AHRS attitude of the last processed IMU sample
        self._att_out: AttitudeSample | None = None      # first pushed attitude (output before any is processed)
        self._R_nb: Mat | None = None
        self._newest_imu_us: int | None = None
        self._heap: list[tuple[int, int, int, str, Any]] = []
        self._seq = itertools.count()
        self._n_meas_buffered = 0
        self._delay_us = round(cfg.fusion_delay_s * US_PER_S)
        self._period_us = round(cfg.predict_period_s * US_PER_S)
        self._gap_us = round(cfg.imu_max_gap_s * US_PER_S)
        self._att_age_us = round(cfg.att_max_age_s * US_PER_S)
        self._clone_cycle: int | None = None
        self._last_cycle_pushed: int | None = None
        self._reject_since: dict[str, int | None] = {"gnss_pos": None, "gnss_vel": None}
        self._st: dict[str, _StatusRow] = {s: _StatusRow(s) for s in AID_SOURCES}
        self._buffer_full_warned = False
        self._gnss_pos_last_us: int | None = None

    # ----------------------------------------------------------------------------------------------------------
    # public API
    @property
    def t_us(self) -> int:
        """Time of the filter state (the fusion horizon), µs."""
        return self._t_x_us

    @property
    def x(self) -> Vec:
        """Copy of the state vector (layout :data:`fusion.state.S`)."""
        return self._kf.x.copy()

    @property
    def P(self) -> Mat:
        """Copy of the state covariance."""
        return self._kf.P.copy()

    def covariance(self, *names: str) -> Mat:
        """Covariance block of the named state fields (in that order)."""
        i = S.idx(*names)
        return self._kf.P[np.ix_(i, i)].copy()

    def status(self) -> dict[str, AidStatus]:
        """Per aid source (:data:`AID_SOURCES`) the status after its last processed sample."""
        return {name: row.snapshot() for name, row in self._st.items()}

    def predict(self, imu: ImuSample, att: AttitudeSample) -> None:
        """Push one IMU sample (specific force m/s^2, FRD, at ``imu.t_us``; the body rates are checked but not used:
        attitude comes from the AHRS) with the AHRS attitude (3-2-1 Euler, rad) valid within ``att_max_age_s`` of
        it.  IMU stamps must increase.  The sample drives the prediction of the interval that ends at its stamp."""
        reason = self._check_imu(imu, att)
        if reason:
            t = getattr(imu, "t_us", -1)
            self._st["imu"].set(int(t) if _is_int(t) else -1, rejected=True, reason=reason)
            return
        t = int(imu.t_us)
        self._newest_imu_us = t
        if self._att_out is None or self._att is None:
            self._att_out = att             # heading for the output until the horizon reaches an IMU sample
        heapq.heappush(self._heap, (t, _PRIO["imu"], next(self._seq), "imu", (imu, att)))
        self._process_due()

    def fuse_airspeed(self, t_us: int, tas_m_s: float) -> None:
        """Push a true airspeed sample (m/s) measured at ``t_us``; the synthetic zero sideslip is fused with it
        (``cfg.sideslip_fusion``)."""
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
        """Push one optical step (:class:`gsoe.types.GsoeStep`, fused at its exposure time ``step.t_us``); push every
        step in order, including each cycle's base step (``new_cycle``) so the clone is taken at the base time."""
        row = self._st["optical"]
        try:
            ints_ok = all(_is_int(v) for v in (step.t_us, step.base_t_us, step.cycle_id))
            vals_ok = _finite(step.dx_px, step.dy_px, step.base_yaw_rad, step.focal_px)
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
        """The current estimate (at :attr:`t_us`), with one-sigma uncertainties and the validity flag."""
        return self._estimate()

    # ----------------------------------------------------------------------------------------------------------
    # input checks and the buffer
    def _check_imu(self, imu: ImuSample, att: AttitudeSample) -> str:
        try:
            if not (_is_int(imu.t_us) and _is_int(att.t_us)):
                return REASON_BAD_TIME
            a, g = imu.accel_b_m_s2, imu.gyro_b_rad_s
            if not (isinstance(a, np.ndarray) and a.shape == (3,) and isinstance(g, np.ndarray) and g.shape == (3,)):
                a, g = np.asarray(a, dtype=float), np.asarray(g, dtype=float)
                if a.shape != (3,) or g.shape != (3,):
                    return REASON_BAD_SHAPE
            # the sum of finite numbers is finite (an overflow at absurd magnitudes is rejected as well)
            total = float(a[0] + a[1] + a[2] + g[0] + g[1] + g[2]) + att.roll_rad + att.pitch_rad + att.yaw_rad
        except (AttributeError, TypeError, ValueError, IndexError):
            return REASON_BAD_SHAPE
        if not math.isfinite(total):
            return REASON_NON_FINITE
        if self._newest_imu_us is not None and imu.t_us <= self._newest_imu_us:
            return REASON_NOT_INCREASING
        if imu.t_us < self._t_in_us:
            return REASON_LATE
        if abs(int(att.t_us) - int(imu.t_us)) > self._att_age_us:
            return REASON_ATT_STALE
        return ""

    def _admit(self, source: str, t_us: Any, value: Any) -> bool:
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
        heapq.heappush(self._heap, (int(t_us), _PRIO[kind], next(self._seq), kind, payload))
        self._n_meas_buffered += 1
        self._process_due()

    def _process_due(self) -> None:
        if self._newest_imu_us is None:
            return
        horizon = self._newest_imu_us - self._delay_us
        heap = self._heap
        while heap and heap[0][0] <= horizon:
            t, _, _, kind, payload = heapq.heappop(heap)
            if kind == "imu":
                self._do_imu(t, *payload)
                continue
            self._n_meas_buffered -= 1
            self._predict_to(t)
            if kind == "optical":
                self._do_optical(payload)
            elif kind == "airspeed":
                self._do_airspeed(t, payload)
            elif kind == "baro":
                self._fuse("baro", t, BaroAltitude(), np.array([payload]), BaroAltitude.noise(self.cfg),
                           self.cfg.gate_baro_nis)
            elif kind in ("gnss_pos", "gnss_vel"):
                self._do_gnss(kind, t, *payload)
            elif kind == "clone":
                self._clone(payload)

    # ----------------------------------------------------------------------------------------------------------
    # prediction
    def _do_imu(self, t: int, imu: ImuSample, att: AttitudeSample) -> None:
        if att is self._att and self._R_nb is not None:
            R = self._R_nb                 # the AHRS is usually slower than the IMU: reuse its rotation
        else:
            R = R_nb_321(att.roll_rad, att.pitch_rad, att.yaw_rad)
        Rf = R @ imu.accel_b_m_s2
        dt_us = t - self._t_in_us
        if dt_us > 0:
            dt = dt_us / US_PER_S
            acc = self._acc
            acc.dt_s += dt
            acc.dv_ahrs_n += Rf * dt
            acc.int_R_nb += R * dt
            self._t_in_us = t
        self._held = (Rf, R)
        self._att = att
        self._R_nb = R
        row = self._st["imu"]
        row.set(t, fused=True, reason=REASON_IMU_GAP if (dt_us > self._gap_us and row.n_fused > 0) else "")
        if self._t_in_us - self._t_x_us >= self._period_us:
            self._flush()

    def _flush(self) -> None:
        if self._acc.dt_s > 0.0:
            self._kf.predict(u=self._acc)
            self._acc = ImuIncrement()
        self._t_x_us = self._t_in_us

    def _predict_to(self, t: int) -> None:
        """Bring the state to ``t`` (>= the inputs consumed): flush the accumulated IMU samples, then predict with
        the last sample held (zero-order hold) up to ``t``; before the first IMU sample the velocity is held."""
        self._flush()
        if t <= self._t_x_us:
            return
        dt = (t - self._t_x_us) / US_PER_S
        if self._held is not None:
            Rf, R = self._held
            inc = ImuIncrement(dt, Rf * dt, R * dt)
        else:
            inc = ImuIncrement(dt, np.array([0.0, 0.0, -STANDARD_GRAVITY_M_S2 * dt]), np.zeros((3, 3)))
        self._kf.predict(u=inc)
        self._t_x_us = self._t_in_us = t

    # ----------------------------------------------------------------------------------------------------------
    # updates
    def _fuse(self, source: str, t_us: int, model: MeasurementModel, z: Vec, R: Mat, gate_nis: float) -> bool:
        """One gated EKF update (Joseph form, solve, symmetric P); returns whether it was fused."""
        kf = self._kf
        row = self._st[source]
        x, P = kf.x, kf.P
        z_hat, H = model.linearise(x)
        y = z - z_hat
        if y.shape[0] == 1:
            return self._fuse_scalar(row, t_us, x, P, H[0], y, R, gate_nis)
        PHt = P @ H.T
        HPHt = H @ PHt
        Sm = HPHt + R
        s_diag = Sm.diagonal().copy()
        if not (np.isfinite(y).all() and np.isfinite(Sm).all()):
            row.set(t_us, rejected=True, reason=REASON_NUMERIC)
            return False
        if (HPHt.diagonal() < -COV_RESET_REL_TOL * R.diagonal()).any():
            self._cov_reset(row, t_us, H, y, s_diag)
            return False
        X = np.linalg.solve(Sm, np.column_stack([y, PHt.T]))      # one solve for the NIS and the gain: S^-1 [y, H P]
        nis = float(y @ X[:, 0])
        K = X[:, 1:].T
        K *= self._gain_scale[:, None]
        ratio = nis / gate_nis
        if not ratio <= 1.0:
            row.set(t_us, rejected=True, reason=REASON_GATE, innovation=y, innovation_var=s_diag, test_ratio=ratio)
            return False
        I_KH = _EYE - K @ H
        return self._commit(row, t_us, x + K @ y, I_KH @ P @ I_KH.T + K @ R @ K.T, y, s_diag, ratio)

    def _fuse_scalar(self, row: _StatusRow, t_us: int, x: Vec, P: Mat, h: Vec, y: Vec, R: Mat,
                     gate_nis: float) -> bool:
        """Scalar update: the same Joseph form ``(I - K h) P (I - K h)' + K r K'`` evaluated with rank-one products
        (``(I - K h) P = P - K (P h)'`` since P is symmetric) instead of two n x n matrix products."""
        r = float(R[0, 0])
        Ph = P @ h
        hph = float(h @ Ph)
        s = hph + r
        y0 = float(y[0])
        var = np.array([s])
        if not (math.isfinite(y0) and math.isfinite(s)):
            row.set(t_us, rejected=True, reason=REASON_NUMERIC)
            return False
        if hph < -COV_RESET_REL_TOL * r:
            self._cov_reset(row, t_us, h[None, :], y, var)
            return False
        ratio = y0 * y0 / s / gate_nis
        if not ratio <= 1.0:
            row.set(t_us, rejected=True, reason=REASON_GATE, innovation=y, innovation_var=var, test_ratio=ratio)
            return False
        K = Ph / s * self._gain_scale
        A = P - K[:, None] * Ph[None, :]                   # (I - K h) P
        P_new = A - (A @ h)[:, None] * K[None, :] + r * (K[:, None] * K[None, :])
        return self._commit(row, t_us, x + K * y0, P_new, y, var, ratio)

    def _commit(self, row: _StatusRow, t_us: int, x_new: Vec, P_new: Mat, y: Vec, var: Vec, ratio: float) -> bool:
        """Symmetrise and store the corrected state, unless anything is non-finite (then the prior is kept)."""
        P_new = 0.5 * (P_new + P_new.T)
        if not (np.isfinite(x_new).all() and np.isfinite(P_new).all()):
            row.set(t_us, rejected=True, reason=REASON_NUMERIC, innovation=y, innovation_var=var, test_ratio=ratio)
            return False
        self._kf.x, self._kf.P = x_new, P_new
        self._kf.y = y
        row.set(t_us, fused=True, innovation=y, innovation_var=var, test_ratio=ratio)
        return True

    def _cov_reset(self, row: _StatusRow, t_us: int, H: Mat, y: Vec, var: Vec) -> None:
        cols = np.flatnonzero(np.any(H != 0.0, axis=0))
        self._reset_covariance(cols)
        log.warning("EKF %s at %d us: innovation variance below observation variance, covariance of states %s reset",
                    row.source, t_us, cols.tolist())
        row.set(t_us, rejected=True, reason=REASON_COV_RESET, innovation=y, innovation_var=var)

    def _initial_variances(self) -> Vec:
        c = self.cfg
        var = np.zeros(S.dim)
        var[S.pos_ne] = c.init_pos_ne_sigma_m**2
        var[S.pos_d] = c.init_pos_d_sigma_m**2
        var[S.vel_ne] = c.init_vel_ne_sigma_m_s**2
        var[S.vel_d] = c.init_vel_d_sigma_m_s**2
        var[S.wind_ne] = c.init_wind_sigma_m_s**2
        var[S.accel_bias_b] = c.init_accel_bias_sigma_m_s2**2
        var[S.yaw_bias] = c.init_yaw_bias_sigma_rad**2
        var[S.opt_rot] = c.init_opt_rot_sigma_rad**2
        var[S.baro_bias] = c.init_baro_bias_sigma_m**2
        var[S.terrain_h] = c.init_terrain_sigma_m**2
        var[S.tas_scale] = c.init_tas_scale_sigma**2
        var[S.base_pos_ne] = c.init_pos_ne_sigma_m**2
        var[S.base_pos_d] = c.init_pos_d_sigma_m**2
        return var

    def _reset_covariance(self, idx: NDArray[np.intp]) -> None:
        P = self._kf.P.copy()
        P[idx, :] = 0.0
        P[:, idx] = 0.0
        P[idx, idx] = self._init_var[idx]
        self._kf.P = P
        if np.intersect1d(idx, np.concatenate([_I_POS, _I_CLONE])).size:
            self._clone_cycle = None

    def _reset_states(self, idx: NDArray[np.intp], z: Vec, R: Mat) -> None:
        x = self._kf.x.copy()
        P = self._kf.P.copy()
        x[idx] = z
        P[idx, :] = 0.0
        P[:, idx] = 0.0
        P[np.ix_(idx, idx)] = R
        self._kf.x, self._kf.P = x, P
        if np.intersect1d(idx, _I_POS).size:   # the position jumped: the current cycle's clone no longer applies
            self._clone_cycle = None

    def _do_airspeed(self, t: int, tas: float) -> None:
        c = self.cfg
        if tas < c.tas_min_m_s:
            self._st["airspeed"].set(t, reason=REASON_LOW_AIRSPEED)
            self._st["sideslip"].set(t, reason=REASON_LOW_AIRSPEED)
            return
        if self._wind_reset_pending and self._att is not None:
            self._reset_wind(tas)
            self._st["airspeed"].set(t, reason=REASON_WIND_RESET)
            return
        self._fuse("airspeed", t, TrueAirspeed(), np.array([tas]), TrueAirspeed.noise(c), c.gate_airspeed_nis)
        if c.sideslip_fusion:
            if self._R_nb is None:
                self._st["sideslip"].set(t, reason=REASON_NO_ATTITUDE)
            else:
                self._fuse("sideslip", t, SyntheticSideslip(self._R_nb), np.zeros(1), SyntheticSideslip.noise(c),
                           c.gate_sideslip_nis)

    def _reset_wind(self, tas: float) -> None:
        """Wind from the wind triangle (:meth:`TrueAirspeed.wind_from_airspeed`) with its covariance
        ``J P J' + sigma_tas^2 a a' + sigma_beta^2 b b'`` and cross covariance ``J P``."""
        assert self._att is not None
        x, P = self._kf.x, self._kf.P
        wind, J, d_tas, d_beta = TrueAirspeed.wind_from_airspeed(x, tas, self._att.yaw_rad)
        A = J @ P
        iw = S.idx("wind_ne")
        x_new = x.copy()
        x_new[iw] = wind
        P_new = P.copy()
        P_new[iw, :] = A
        P_new[:, iw] = A.T
        P_new[np.ix_(iw, iw)] = (A @ J.T + self.cfg.tas_sigma_m_s**2 * np.outer(d_tas, d_tas)
                                 + self.cfg.sideslip_sigma_rad**2 * np.outer(d_beta, d_beta))
        self._kf.x, self._kf.P = x_new, 0.5 * (P_new + P_new.T)
        self._wind_reset_pending = False

    def _do_gnss(self, source: str, t: int, z: Vec, sigmas: tuple[float | None, float | None]) -> None:
        c = self.cfg
        if source == "gnss_pos":
            model: GnssPosition | GnssVelocity = GnssPosition(dim=z.shape[0])
            gate, idx = c.gate_gnss_pos_nis, _I_POS[: z.shape[0]]
            R = model.noise(c, *sigmas)
            # correlated receiver error: fixes closer than the correlation time share their error
            if self._gnss_pos_last_us is not None and c.gnss_pos_corr_time_s > 0.0:
                dt = max(t - self._gnss_pos_last_us, 1) / US_PER_S
                R = R * max(1.0, 2.0 * c.gnss_pos_corr_time_s / dt)
            self._gnss_pos_last_us = t
        else:
            model = GnssVelocity(dim=z.shape[0])
            gate, idx = c.gate_gnss_vel_nis, _I_VEL[: z.shape[0]]
            R = model.noise(c, *sigmas)
        if self._fuse(source, t, model, z, R, gate):
            self._reject_since[source] = None
            return
        row = self._st[source]
        if row.reason != REASON_GATE:
            return
        since = self._reject_since[source]
        if since is None:
            self._reject_since[source] = t
        elif t - since >= c.gnss_reset_after_s * US_PER_S:
            self._reset_states(idx, z, R)
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
        self._kf.x, self._kf.P = x, P
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
        self._kf.x, self._kf.P = x_new, 0.5 * (P_new + P_new.T)
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
        if model.height_base_m(self._kf.x) < c.optical_min_height_m:
            row.set(t, rejected=True, reason=REASON_LOW_HEIGHT)
            return
        R = OpticalDisplacement.noise(step, c)
        if self._clone_cycle != step.cycle_id:
            if self._clone_cycle is not None and step.cycle_id < self._clone_cycle:
                row.set(t, rejected=True, reason=REASON_STALE_CYCLE)
                return
            self._clone_from_step(model, step, R)
            row.set(t, reason=REASON_ANCHORED)
            return
        self._fuse("optical", t, model, np.array([step.dx_px, step.dy_px]), R, c.gate_optical_nis)

    # ----------------------------------------------------------------------------------------------------------
    # output
    def _estimate(self) -> NavEstimate:
        x, P = self._kf.x, self._kf.P
        sd = np.sqrt(np.maximum(P.diagonal(), 0.0))
        v = x[S.vel_ned].copy()
        vn, ve = float(v[0]), float(v[1])
        gs = math.hypot(vn, ve)
        iv, iw, yb_i = S.vel_ne.start, S.wind_ne.start, _I_YAW
        pnn, pne, pee = P[iv, iv], P[iv, iv + 1], P[iv + 1, iv + 1]
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
        # heading = yaw_ahrs - yaw_bias; drift = course - heading = course - yaw_ahrs + yaw_bias
        yb = float(x[yb_i])
        att = self._att if self._att is not None else self._att_out
        if att is not None:
            heading = float(wrap_2pi(att.yaw_rad - yb))
            drift = float(angle_diff(course, heading))
            var_d = var_c + P[yb_i, yb_i] + 2.0 * (gn * P[iv, yb_i] + ge * P[iv + 1, yb_i])
            drift_sd = min(math.pi, math.sqrt(max(var_d, 0.0))) if gs > 0.0 else math.pi
        else:
            heading = drift = math.nan
            drift_sd = math.pi
        # wind speed and the direction it blows from: atan2(-we, -wn); gradient (-we, wn) / ws^2
        wn, we = float(x[iw]), float(x[iw + 1])
        qnn, qne, qee = P[iw, iw], P[iw, iw + 1], P[iw + 1, iw + 1]
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
        h_agl_sd = math.sqrt(max(P[ipd, ipd] + P[ith, ith] + 2.0 * P[ipd, ith], 0.0))
        valid, why = self._validity(sd, gs, drift_sd)
        return NavEstimate(
            t_us=self._t_x_us,
            pos_ne_m=x[S.pos_ne].copy(), pos_ne_sigma_m=sd[S.pos_ne],
            height_m=float(-x[ipd]), height_sigma_m=float(sd[ipd]),
            height_agl_m=float(-x[ipd] - x[ith]), height_agl_sigma_m=h_agl_sd,
            vel_ned_m_s=v, vel_ned_sigma_m_s=sd[S.vel_ned],
            ground_speed_m_s=gs, ground_speed_sigma_m_s=gs_sd,
            course_rad=course, course_sigma_rad=course_sd,
            wind_ne_m_s=x[S.wind_ne].copy(), wind_ne_sigma_m_s=sd[S.wind_ne],
            wind_speed_m_s=ws, wind_speed_sigma_m_s=ws_sd, wind_from_rad=w_from, wind_from_sigma_rad=wd_sd,
            heading_rad=heading, heading_sigma_rad=float(sd[yb_i]),
            drift_rad=drift, drift_sigma_rad=drift_sd,
            ata_rad=course, ata_sigma_rad=course_sd,
            accel_bias_b_m_s2=x[S.accel_bias_b].copy(), yaw_bias_rad=yb, opt_rot_rad=float(x[S.opt_rot.start]),
            baro_bias_m=float(x[S.baro_bias.start]),
            terrain_h_m=float(x[ith]), tas_scale=float(x[S.tas_scale.start]),
            cov_pvw=P[np.ix_(_I_PVW, _I_PVW)],
            valid=valid, invalid_reason=why,
        )

    def _validity(self, sd: Vec, gs: float, drift_sd: float) -> tuple[bool, str]:
        c = self.cfg
        if self._att is None:
            return False, REASON_NO_ATTITUDE
        if float(np.max(sd[S.vel_ne])) > c.valid_vel_sigma_max_m_s:
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
