"""Optical displacement with stochastic cloning: the model and the aid source.

A new cycle (``cycle_id``) schedules a *clone event* at its ``base_t_us``, where ``base_pos_ne``/``base_pos_d`` become
copies of the position with its covariance rows (exact joint covariance of "position then" and "state now").  Each
later step measures ``pos - base_pos`` in the base-heading frame over the base image's ground sample distance, fused
at its exposure time; the base step carries no displacement.  If the horizon had passed ``base_t_us`` already when
the cycle's first step arrived (fusion delay shorter than the camera latency, or base steps not pushed), the first
valid step *anchors* the cycle (:meth:`OpticalAid.reset`): the base position is reconstructed from it, its pixel
noise in the clone's covariance.  Cycle ids must increase.  Gating replaces the paper's data and integrity filters:
a bad match is rejected by its NIS (or its quality verdict) and the next steps are measured against the same base.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

import numpy as np
from numpy.typing import NDArray

from common.samples import GsoeStep
from fusion.aid.base import AidSource, ModelBase, Vec
from fusion.config import EkfConfig
from fusion.core import Linearised
from fusion.state import S
from fusion.status import REASON_BAD_SHAPE, REASON_BAD_TIME, REASON_NON_FINITE
from fusion.timeline import is_int

REASON_BASE_FRAME = "base frame (no displacement yet)"
REASON_INVALID_MATCH = "invalid match"
REASON_ANCHORED = "anchored the cycle: base position reconstructed from this step (base time already processed)"
REASON_STALE_CYCLE = "stale cycle"
REASON_LOW_HEIGHT = "height above ground below optical_min_height_m"
REASON_BAD_FOCAL = "focal_px not positive"

_N, _E, _PD = S.pos_ne.start, S.pos_ne.start + 1, S.pos_d.start
_BN, _BE, _BD = S.base_pos_ne.start, S.base_pos_ne.start + 1, S.base_pos_d.start
_YB, _OR, _TH = S.yaw_bias.start, S.opt_rot.start, S.terrain_h.start
# the same indices in the second row of a flattened 2 x n Jacobian
_N2, _E2, _BN2, _BE2, _BD2, _TH2, _YB2, _OR2 = (S.dim + i for i in (_N, _E, _BN, _BE, _BD, _TH, _YB, _OR))
_I_POS, _I_CLONE, _I_POS_CLONE = S.idx("pos_ned"), S.idx("base_pos_ned"), S.idx("pos_ned", "base_pos_ned")


@dataclass(slots=True)
class OpticalDisplacement(ModelBase):
    """The template's accumulated migration ``[dx_px, dy_px]`` since the cycle's base snapshot.

    The position change since the base snapshot, ``pos_ne - base_pos_ne`` (the clone), rotated into the cycle's
    stabilised frame (cross track to the right, along track forward of ``psi = base_yaw_rad - yaw_bias + opt_rot``)
    and divided by the base image's ground sample distance ``h_base / focal_px`` with
    ``h_base = -base_pos_d - terrain_h``: ``dx_px = f (-sin(psi) dN + cos(psi) dE) / h_base``, ``dy_px = f (cos(psi)
    dN + sin(psi) dE) / h_base``.  ``focal_px`` (``f``): the virtual nadir camera's focal length (px); ``base_yaw_rad``:
    the AHRS heading the cycle's frame was built with (rad), so an AHRS heading error shows only in the label
    (``- yaw_bias``); ``opt_rot``: what the optical estimator's own attitude adds.  ``var_px2``: the noise variance of
    each axis (uncorrelated, :meth:`for_step`; NaN when the model is built for its geometry only).
    """

    focal_px: float
    base_yaw_rad: float
    var_px2: float = math.nan

    @classmethod
    def for_step(cls, step: GsoeStep, terms: NoiseTerms) -> OpticalDisplacement:
        """The model of one step, with the configuration's :func:`noise_terms` (read once by the source): each axis's
        noise variance is the sum of the squares of :meth:`noise_sigma_px` (matcher and attitude, uncorrelated)."""
        m, a = _sigmas_px(step, terms)
        return cls(float(step.focal_px), float(step.base_yaw_rad), m * m + a * a)

    def _parts(self, x: Vec) -> tuple[float, float, float, float, float, float]:
        xl = x.tolist()
        psi = self.base_yaw_rad - xl[_YB] + xl[_OR]
        c, s = math.cos(psi), math.sin(psi)
        dn, de = xl[_N] - xl[_BN], xl[_E] - xl[_BE]
        h = -xl[_BD] - xl[_TH]
        return c, s, c * dn + s * de, -s * dn + c * de, h, self.focal_px / h

    def height_base_m(self, x: Vec) -> float:
        """Height above ground at the base snapshot according to ``x`` (m)."""
        return -x.item(_BD) - x.item(_TH)

    def linearise(self, x: Vec) -> Linearised:
        c, s, along, cross, h, k = self._parts(x)
        zx_h, zy_h = k * cross / h, k * along / h        # d z / d h_base = -z / h, and d h_base / d(.) = -1
        ks, kc = k * s, k * c
        H = np.zeros(2 * S.dim)                           # row-major 2 x n, filled element by element (cheapest)
        H[_N], H[_E], H[_BN], H[_BE] = -ks, kc, ks, -kc                       # row 0 (dx_px)
        H[_BD] = H[_TH] = zx_h
        H[_YB], H[_OR] = k * along, -k * along                                # d psi / d yaw_bias = -1, opt_rot = +1
        H[_N2], H[_E2], H[_BN2], H[_BE2] = kc, ks, -kc, -ks                   # row 1 (dy_px)
        H[_BD2] = H[_TH2] = zy_h
        H[_YB2], H[_OR2] = -k * cross, k * cross
        return Linearised((k * cross, k * along), H.reshape(2, S.dim), None, (self.var_px2, self.var_px2))

    def base_from_step(self, x: Vec, z_px: Vec) -> tuple[Vec, NDArray[np.float64], NDArray[np.float64]]:
        """The inverse model, for a cycle whose base time was missed: the base position ``[N, E, D]`` implied by the
        current state and a step ``z_px = [dx_px, dy_px]``, ``pos_ne - (h / f) R(psi) [dy, dx]`` with the height now
        standing for the height then (``base_pos_d = pos_d``), and its Jacobians w.r.t. the state (3 x n) and
        w.r.t. ``z_px`` (3 x 2)."""
        psi = self.base_yaw_rad - x[_YB] + x[_OR]
        c, s = math.cos(psi), math.sin(psi)
        dx, dy = float(z_px[0]), float(z_px[1])
        uN, uE = c * dy - s * dx, s * dy + c * dx          # the pixel displacement rotated to north/east
        f = self.focal_px
        k = (-x[_PD] - x[_TH]) / f
        base = np.array([x[_N] - k * uN, x[_E] - k * uE, x[_PD]])
        J = np.zeros((3, S.dim))
        J[0, _N] = J[1, _E] = J[2, _PD] = 1.0
        J[0, _PD] = J[0, _TH] = uN / f                       # d(-k)/d(pos_d) = d(-k)/d(terrain_h) = 1/f
        J[1, _PD] = J[1, _TH] = uE / f
        J[0, _YB], J[1, _YB] = -k * uE, k * uN               # d psi / d yaw_bias = -1
        J[0, _OR], J[1, _OR] = k * uE, -k * uN               # d psi / d opt_rot = +1
        Kz = np.array([[k * s, -k * c], [-k * c, -k * s], [0.0, 0.0]])
        return base, J, Kz

    @staticmethod
    def noise_sigma_px(step: GsoeStep, cfg: EkfConfig) -> tuple[float, float]:
        """(matcher sigma, attitude-induced sigma) in px for one step.

        Matcher: ``optical.match_sigma_px / q`` with the quality ``q = clip(psr / optical.psr_ref,
        optical.quality_floor, 1)`` (a non-finite PSR counts as the floor), or ``optical.ssd_sigma_factor`` times the
        match's own SSD precision ``quality.match_sigma_px`` where that is larger.  Attitude: ``focal_px`` times the
        relative attitude error between base and current frame, ``optical.att_rel_sigma_rad +
        optical.att_rel_sigma_per_rad * rel_rot_rad + optical.att_rel_sigma_rad_per_s * (t - base_t)``
        (independent of altitude: an angle error moves the image by ``f * angle`` pixels at any height)."""
        return _sigmas_px(step, noise_terms(cfg))


class NoiseTerms(NamedTuple):
    """The ``optical`` configuration numbers of :meth:`OpticalDisplacement.noise_sigma_px` (its units)."""

    psr_ref: float
    quality_floor: float
    rel_rot_fallback_rad: float
    att_rel_sigma_rad: float
    att_rel_sigma_per_rad: float
    att_rel_sigma_rad_per_s: float
    match_sigma_px: float
    ssd_sigma_factor: float


def noise_terms(cfg: EkfConfig) -> NoiseTerms:
    """The numbers of the optical noise model in ``cfg``, read once."""
    o = cfg.optical
    return NoiseTerms(o.psr_ref, o.quality_floor, o.rel_rot_fallback_rad, o.att_rel_sigma_rad, o.att_rel_sigma_per_rad,
                      o.att_rel_sigma_rad_per_s, o.match_sigma_px, o.ssd_sigma_factor)


def _sigmas_px(step: GsoeStep, o: NoiseTerms) -> tuple[float, float]:
    """:meth:`OpticalDisplacement.noise_sigma_px` from the configuration's numbers."""
    psr = step.quality.psr
    q = psr / o.psr_ref if not math.isnan(psr) else 0.0
    q = min(1.0, max(o.quality_floor, q))
    rel = step.rel_rot_rad if math.isfinite(step.rel_rot_rad) else o.rel_rot_fallback_rad
    elapsed_s = max(0, step.t_us - step.base_t_us) * 1e-6
    att_rad = o.att_rel_sigma_rad + o.att_rel_sigma_per_rad * abs(rel) + o.att_rel_sigma_rad_per_s * elapsed_s
    match = o.match_sigma_px / q
    ssd = o.ssd_sigma_factor * step.quality.match_sigma_px
    if ssd > match:                                   # False for nan (no SSD precision: the PSR model alone)
        match = ssd
    return match, step.focal_px * att_rad


class OpticalAid(AidSource):
    """Fuses the optical steps of each cycle against its clone (module docstring; gate ``gates.optical_nis``)."""

    name = "optical"
    events: ClassVar[dict[str, int]] = {"optical": 5, "clone": 6}     # the clone after the previous cycle's last step

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self._clone_cycle: int | None = None
        self._last_cycle_pushed: int | None = None
        self._min_height_m, self._gate = self.cfg.optical.min_height_m, self.cfg.gates.optical_nis
        self._noise = noise_terms(self.cfg)

    def accept(self, t_us: Any, sample: GsoeStep) -> tuple[Any, Any] | None:
        step, row = sample, self.row
        try:
            ints_ok = is_int(step.t_us) and is_int(step.base_t_us) and is_int(step.cycle_id)
            # a sum is finite only if every term is (NaN and inf propagate); non-numbers raise
            vals_ok = math.isfinite(step.dx_px + step.dy_px + step.base_yaw_rad + step.focal_px)
            # used by the noise model: must be numbers (NaN allowed: they fall back to conservative values)
            float(step.quality.psr), float(step.rel_rot_rad), bool(step.quality.valid), bool(step.valid)
        except (AttributeError, TypeError, ValueError):
            row.set(-1, rejected=True, reason=REASON_BAD_SHAPE)
            return None
        if not ints_ok or step.base_t_us > step.t_us:
            row.set(int(step.t_us) if is_int(getattr(step, "t_us", None)) else -1, rejected=True,
                    reason=REASON_BAD_TIME)
            return None
        if not vals_ok:
            row.set(int(step.t_us), rejected=True, reason=REASON_NON_FINITE)
            return None
        if step.focal_px <= 0.0:
            row.set(int(step.t_us), rejected=True, reason=REASON_BAD_FOCAL)
            return None
        return step, 0.0

    def push(self, t_us: int, payload: GsoeStep) -> None:
        """Queue the step; the first step of a new cycle schedules the clone at the cycle's base time."""
        step, timeline = payload, self.ctx.timeline
        if step.cycle_id != self._last_cycle_pushed:
            self._last_cycle_pushed = int(step.cycle_id)
            if step.base_t_us >= self.ctx.imu.t_in_us:
                timeline.schedule(int(step.base_t_us), "clone", int(step.cycle_id))
        timeline.push(step.t_us, "optical", step)

    def handler(self, kind: str) -> Callable[[int, Any], bool]:
        return self.clone if kind == "clone" else self.control

    def control(self, t_us: int, step: GsoeStep) -> bool:
        t, row = int(step.t_us), self.row
        if step.t_us <= step.base_t_us:
            row.set(t, reason=REASON_BASE_FRAME)
            return True
        if not (step.valid and step.quality.valid):
            row.set(t, rejected=True, reason=REASON_INVALID_MATCH)
            return True
        model = OpticalDisplacement.for_step(step, self._noise)
        if model.height_base_m(self.core.x) < self._min_height_m:
            row.set(t, rejected=True, reason=REASON_LOW_HEIGHT)
            return True
        if self._clone_cycle != step.cycle_id:
            if self._clone_cycle is not None and step.cycle_id < self._clone_cycle:
                row.set(t, rejected=True, reason=REASON_STALE_CYCLE)
                return True
            self.reset(t, (model, step))
            return True
        self.fuse(t, (float(step.dx_px), float(step.dy_px)), model, self._gate)
        return True

    def clone(self, t_us: int, cycle_id: int) -> bool:
        """The clone: ``base_pos`` becomes a copy of the position, with the position's covariance rows."""
        core = self.core
        x = core.x.copy()
        P = core.P.copy()
        x[_I_CLONE] = x[_I_POS]
        P[_I_CLONE, :] = P[_I_POS, :]
        P[:, _I_CLONE] = P[:, _I_POS]
        core.store(x, P)
        self._clone_cycle = cycle_id
        return True

    def reset(self, t_us: int, sample: tuple[OpticalDisplacement, GsoeStep]) -> None:
        """Anchor a cycle whose base time is behind the horizon on its first step: the clone becomes the base position
        reconstructed from the step (:meth:`OpticalDisplacement.base_from_step`), with covariance ``J P J' + K R K'``
        and cross covariance ``J P``, so the step's error is carried, correlated, by the cycle's later steps."""
        model, step = sample
        core = self.core
        x, P = core.x, core.P
        base, J, Kz = model.base_from_step(x, np.array([step.dx_px, step.dy_px]))
        A = J @ P
        x_new = x.copy()
        x_new[_I_CLONE] = base
        P_new = P.copy()
        P_new[_I_CLONE, :] = A
        P_new[:, _I_CLONE] = A.T
        P_new[np.ix_(_I_CLONE, _I_CLONE)] = A @ J.T + Kz @ (np.eye(2) * model.var_px2) @ Kz.T
        core.store(x_new, 0.5 * (P_new + P_new.T))
        self._clone_cycle = int(step.cycle_id)
        self.row.set(t_us, reason=REASON_ANCHORED)

    def stop(self) -> None:
        """Forget the clone: the next step anchors its cycle anew."""
        self._clone_cycle = None

    def states_reset(self, idx: NDArray[np.intp]) -> None:
        if np.intersect1d(idx, _I_POS_CLONE).size:     # the position or the clone jumped: the clone no longer applies
            self.stop()
