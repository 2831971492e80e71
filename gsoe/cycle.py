"""The template-matching cycle (paper 2.4-2.6): base snapshot, template migration, new cycle conditions.

:class:`GsoeEstimator` takes timestamped attitude and gyro samples (:meth:`push_attitude`, :meth:`push_imu`) and
camera frames stamped at their exposure time (:meth:`process_frame`), and returns :class:`common.samples.GsoeStep`
records: the template's accumulated migration since the base snapshot, in the cycle's stabilised frame.

The attitude of a frame is the AHRS attitude with its latency removed (:meth:`AttitudeBuffer.compensated_at`:
the latency is estimated against the gyro unless given); a cycle's base attitude also has the AHRS noise averaged
out, since its heading labels the whole cycle's migration (an error there is an error of the optical course).

A cycle ends (and the next one starts from the same frame, so no frame is lost) when

* the template's predicted next position would leave the base image (the critical position, paper 2.4),
* the cycle has lasted ``cycle.max_cycle_s``,
* the match is invalid (quality gates of :mod:`gsoe.matching`) or the data filter of eq. 6 fires,
* the attitude leaves the stabilisable range or the stabilised patch leaves the raw frame.

``template_start = "trailing"`` puts the base snapshot's nadir near the trailing (bottom) edge of the base image,
so the template can travel almost the whole base image: the baseline, and so the angle resolution, grows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from common.angles import circular_mean, wrap_pi
from common.samples import AttitudeSample, GsoeStep, ImuSample, MatchQuality
from gsoe import quat
from gsoe.attitude import US_PER_S, AttitudeBuffer
from gsoe.camera import CameraModel
from gsoe.config import GsoeConfig
from gsoe.integrity import data_filter_fires
from gsoe.matching import match_template, texture_std
from gsoe.quat import Quat
from gsoe.stabilise import Frame, VirtualNadirCamera

_NO_QUALITY = MatchQuality(psr=0.0, texture_std=0.0, ssd_per_px=math.nan, valid=False)


def base_reference_px(cfg: GsoeConfig) -> tuple[float, float]:
    """Pixel (u0, v0) of the base snapshot's nadir (= the template's start) in the base image."""
    s = cfg.stab
    u0 = (s.base_cross_px - 1) / 2.0
    if s.template_start == "centre":
        v0 = (s.base_along_px - 1) / 2.0
    else:
        v0 = s.base_along_px - 1 - (s.template_px - 1) / 2.0 - cfg.cycle.edge_margin_px
    return u0, v0


def chord_drift_rad(step: GsoeStep) -> float:
    """Drift from a step's accumulated migration (eq. 9 generalised to turns).

    The chord from the base nadir to the current nadir points along the course at the middle of the interval
    (exact for a steady turn); the heading there is the circular mean of the base and current headings.
    """
    course = step.base_yaw_rad + math.atan2(step.dx_px, step.dy_px)
    heading_mid = circular_mean(np.array([step.base_yaw_rad, step.yaw_rad]))
    return float(wrap_pi(course - heading_mid))


@dataclass
class _Cycle:
    cycle_id: int
    base_t_us: int
    base_yaw_rad: float
    q_nb0: Quat
    base_image: NDArray[np.float32]
    height_agl_m: float
    gsd_m_px: float
    step: int
    last_xy: tuple[float, float]
    last_step_xy: tuple[float, float] | None
    n_valid: int
    carried_step_xy: tuple[float, float] | None = None


class GsoeEstimator:
    """The optical estimator.  Built fully configured; feed samples in time order."""

    def __init__(self, cfg: GsoeConfig, camera: CameraModel, ahrs_latency_s: float | None = None) -> None:
        """``ahrs_latency_s``: the AHRS latency (s) if known, else None: estimated from the AHRS and the gyro
        (:class:`gsoe.attitude.AttitudeBuffer`)."""
        self.cfg = cfg
        self.camera = camera
        s = cfg.stab
        self.ref_uv = base_reference_px(cfg)
        self.vcam = VirtualNadirCamera(camera, (s.base_cross_px, s.base_along_px), self.ref_uv, s.template_px,
                                       s.focal_px, s.map_grid_px)
        self.buffer = AttitudeBuffer(gyro_bias_tau_s=s.gyro_bias_tau_s, latency_s=ahrs_latency_s)
        half = (s.template_px - 1) / 2.0 + cfg.cycle.edge_margin_px
        self._u_lim = (half, s.base_cross_px - 1 - half)
        self._v_lim = (half, s.base_along_px - 1 - half)
        self._roll_lim = math.radians(s.roll_limit_deg)
        self._pitch_lim = math.radians(s.pitch_limit_deg)
        self._max_cycle_us = int(cfg.cycle.max_cycle_s * US_PER_S)
        self._featureless_retry_us = int(round(cfg.cycle.featureless_retry_s * US_PER_S))
        self._cycle: _Cycle | None = None
        self._next_id = 0
        # featureless ground: no new base before this time (see CycleConfig)
        self._retry_after_us: int | None = None
        self.featureless = False
        """Whether the last base tried was featureless (no cycle runs until the ground shows texture)."""
        self.n_featureless_bases = 0

    @property
    def focal_px(self) -> float:
        return self.vcam.focal_px

    @property
    def cycle_base(self) -> NDArray[np.float32] | None:
        """The current cycle's base image (for figures)."""
        return None if self._cycle is None else self._cycle.base_image

    def raw_roi(self, R_nb: NDArray[np.float64], margin_px: int) -> tuple[int, int, int, int] | None:
        """Bounding box (x0, y0, x1, y1; end exclusive) of the raw pixels a base image taken at attitude ``R_nb``
        reads, grown by ``margin_px`` (a template of the same cycle lies inside it).  For renderers that draw
        only what the estimator reads; None when the base image would leave the raw frame."""
        yaw = math.atan2(R_nb[1, 0], R_nb[0, 0])
        mx, my, ok = self.vcam.base.sample_map(self.vcam.R_cn(R_nb), yaw, 1.0 / self.focal_px)
        if not ok:
            return None
        w, h = self.camera.size_px
        x0 = max(0, int(np.floor(mx.min())) - margin_px)
        y0 = max(0, int(np.floor(my.min())) - margin_px)
        x1 = min(w, int(np.ceil(mx.max())) + 1 + margin_px)
        y1 = min(h, int(np.ceil(my.max())) + 1 + margin_px)
        return x0, y0, x1, y1

    def push_attitude(self, s: AttitudeSample) -> bool:
        return self.buffer.push_attitude(s)

    def push_imu(self, s: ImuSample) -> bool:
        return self.buffer.push_imu(s)

    def fusion_attitude(self, t_us: int) -> AttitudeSample | None:
        """The attitude at ``t_us`` for the EKF's prediction and heading: the AHRS with its latency removed and its
        noise averaged (:meth:`AttitudeBuffer.compensated_at`), so that the EKF and the optical frames share one
        attitude; None when the AHRS does not cover ``t_us``."""
        q = self.buffer.compensated_at(t_us, smooth=True)
        if q is None:
            return None
        roll, pitch, yaw = quat.to_euler321(q)
        return AttitudeSample(t_us, roll, pitch, yaw)

    # ------------------------------------------------------------------------------------------------------
    def process_frame(self, t_us: int, image: Frame, height_agl_m: float = math.nan) -> list[GsoeStep]:
        """Process one raw frame exposed at ``t_us``; returns 0-2 steps (a cycle's last step, a new base).

        ``image`` is the raw frame (grey or BGR, the camera's size) or a callable giving it region by region
        (:data:`gsoe.stabilise.Frame`).  A frame of the wrong size or type ends the cycle and returns nothing.
        """
        w, h = self.camera.size_px
        if not callable(image) and (image is None or not isinstance(image, np.ndarray) or image.ndim not in (2, 3)
                                    or image.shape[0] != h or image.shape[1] != w or image.size == 0):
            self._cycle = None
            return []
        # the attitude at the exposure, AHRS latency removed (gsoe.attitude); a new base averages the AHRS noise too
        att = self.buffer.compensated_at(t_us, smooth=False)
        if att is None or not self._attitude_ok(att):
            self._cycle = None
            return []
        c = self._cycle
        if c is None:
            if self._retry_after_us is not None and t_us < self._retry_after_us:
                return []
            return self._start(t_us, image, att, height_agl_m)
        rel = self.buffer.relative_rotation(c.base_t_us, t_us, self.cfg.stab.use_gyro)
        q_nb = quat.mul(c.q_nb0, rel) if rel is not None else att
        R_nb = quat.to_matrix(q_nb)
        ratio = c.height_agl_m / height_agl_m if (math.isfinite(height_agl_m) and height_agl_m > 0
                                                  and math.isfinite(c.height_agl_m)) else 1.0
        if not self.cfg.stab.scale_template_to_base:
            ratio = 1.0
        yaw_now = math.atan2(R_nb[1, 0], R_nb[0, 0])
        tpl = self.vcam.sample_template(image, R_nb, c.base_yaw_rad, ratio)
        c.step += 1
        if not tpl.valid:
            return [self._step(t_us, c, c.last_xy, _NO_QUALITY, False, yaw_now, rel)] + self._restart(
                t_us, image, att, height_agl_m, c)
        pred = c.last_xy if c.last_step_xy is None else (c.last_xy[0] + c.last_step_xy[0],
                                                          c.last_xy[1] + c.last_step_xy[1])
        res = match_template(c.base_image, tpl.image, self.cfg.match, pred)
        xy = (res.x_px, res.y_px)
        step_xy = (xy[0] - c.last_xy[0], xy[1] - c.last_xy[1])
        prev = c.last_step_xy if c.last_step_xy is not None else c.carried_step_xy
        cc = self.cfg.cycle
        filtered = prev is not None and (
            (cc.data_filter and data_filter_fires(prev, step_xy, cc.data_filter_zeta_px))
            or (cc.step_gate_px > 0 and math.hypot(step_xy[0] - prev[0], step_xy[1] - prev[1]) > cc.step_gate_px))
        valid = res.quality.valid and not filtered
        out = [self._step(t_us, c, xy, res.quality, valid, yaw_now, rel)]
        if not valid:
            return out + self._restart(t_us, image, att, height_agl_m, c)
        c.n_valid += 1
        c.last_step_xy = step_xy
        c.last_xy = xy
        nxt = (xy[0] + step_xy[0], xy[1] + step_xy[1])
        at_edge = not (self._u_lim[0] <= nxt[0] <= self._u_lim[1] and self._v_lim[0] <= nxt[1] <= self._v_lim[1])
        if at_edge or t_us - c.base_t_us >= self._max_cycle_us:
            return out + self._restart(t_us, image, att, height_agl_m, c)
        return out

    # ------------------------------------------------------------------------------------------------------
    def _attitude_ok(self, att: Quat) -> bool:
        roll, pitch, _ = quat.to_euler321(att)
        return abs(roll) <= self._roll_lim and abs(pitch) <= self._pitch_lim

    def _restart(self, t_us: int, image: Frame, att: Quat, height_agl_m: float, old: _Cycle) -> list[GsoeStep]:
        if old.n_valid > 0:
            self.buffer.update_bias(old.base_t_us, t_us)
        self._cycle = None
        out = self._start(t_us, image, att, height_agl_m)
        new = self._cycle
        # only a step the old cycle measured itself is carried: a carried step is used once, so a stale one
        # (the ground speed changed during a stretch without matches) cannot lock the gate
        step = old.last_step_xy
        if new is not None and step is not None:
            # image x = right, y = -forward; rotate the ground step into the new base heading
            d = new.base_yaw_rad - old.base_yaw_rad
            fwd, right = -step[1], step[0]
            fwd2 = fwd * math.cos(d) + right * math.sin(d)
            right2 = -fwd * math.sin(d) + right * math.cos(d)
            new.carried_step_xy = (right2, -fwd2)
        return out

    def _start(self, t_us: int, image: Frame, att: Quat, height_agl_m: float) -> list[GsoeStep]:
        # the base attitude labels the whole cycle (its heading error is the optical course's): average the AHRS
        att = self.buffer.compensated_at(t_us, smooth=True) or att
        yaw0 = quat.to_euler321(att)[2]
        patch = self.vcam.sample_base(image, quat.to_matrix(att), yaw0)
        if not patch.valid:
            return []
        # the base's texture, once: it decides whether a cycle can run (the matcher's own criterion; every template
        # of the cycle shows ground inside the base) and labels the base step
        base_std = texture_std(patch.image)
        if base_std < self.cfg.match.texture_std_min:
            self.featureless = True
            self.n_featureless_bases += 1
            self._retry_after_us = t_us + self._featureless_retry_us
            return []
        self.featureless = False
        self._retry_after_us = None
        h_ok = math.isfinite(height_agl_m) and height_agl_m > 0
        c = _Cycle(cycle_id=self._next_id, base_t_us=t_us, base_yaw_rad=yaw0, q_nb0=att, base_image=patch.image,
                   height_agl_m=height_agl_m if h_ok else math.nan,
                   gsd_m_px=height_agl_m / self.focal_px if h_ok else math.nan,
                   step=0, last_xy=self.ref_uv, last_step_xy=None, n_valid=0)
        self._next_id += 1
        self._cycle = c
        q = MatchQuality(psr=math.inf, texture_std=base_std, ssd_per_px=0.0, valid=True)
        return [self._step(t_us, c, self.ref_uv, q, True, yaw0, quat.IDENTITY, new_cycle=True)]

    def _step(self, t_us: int, c: _Cycle, xy: tuple[float, float], q: MatchQuality, valid: bool, yaw_rad: float,
              rel: Quat | None, new_cycle: bool = False) -> GsoeStep:
        u0, v0 = self.ref_uv
        return GsoeStep(
            t_us=t_us, base_t_us=c.base_t_us, cycle_id=c.cycle_id, step=c.step,
            dx_px=float(xy[0] - u0), dy_px=float(v0 - xy[1]),
            base_yaw_rad=c.base_yaw_rad, yaw_rad=yaw_rad, gsd_m_px=c.gsd_m_px, height_agl_m=c.height_agl_m,
            focal_px=self.focal_px, rel_rot_rad=quat.angle(rel) if rel is not None else math.nan,
            quality=q, valid=valid, new_cycle=new_cycle,
        )
