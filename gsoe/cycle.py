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

``stab.roi_centre = "view"`` (an oblique or narrow camera that does not see the nadir, a low frame rate with large
motion per frame): the base image lies around the ground point of the raw image's centre, ``O_b`` stabilised
pixels (forward, right) from the base nadir, and each frame's template is cut ``O_k = O_b + A - D_pred`` from the
current nadir, where ``D_pred`` is the predicted migration and ``A`` the base's *anchor*: the most textured
template-sized spot within ``VIEW_ANCHOR_FRACTION`` of the search range of the base's centre (water or a bare field
at the centre would fail every match of the cycle).  The template then shows the ground at the anchor and lands
there, give or take the prediction's error.  A match at base pixel ``(x, y)`` then means a migration
``(x - u0 + O_b.right - O_k.right, v0 - y + O_b.fwd - O_k.fwd)``; the cycle keeps positions in those nadir
terms, so its steps mean what they mean in ``"nadir"`` mode.  The critical position becomes: the next
predicted template would leave the raw frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
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
#: "view" mode: the anchor lies within this fraction of the search range ((base side - template side) / 2) of the base
#: image's centre; the rest of the range is left for the prediction's error.
VIEW_ANCHOR_FRACTION = 1.0 / 3.0


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
    # "view" mode: the base image's ground centre from the base nadir, and the anchor from the base image's centre,
    # stabilised px (forward, right)
    offset_b: tuple[float, float] = (0.0, 0.0)
    anchor: tuple[float, float] = (0.0, 0.0)
    # step_prediction "per_second": the time of the last valid position and the intervals the steps spanned
    last_t_us: int = 0
    last_step_dt_us: int = 0
    carried_step_dt_us: int = 0


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
        self._view = s.roi_centre == "view"
        self._per_second = cfg.cycle.step_prediction == "per_second"
        # "window" matching: the positions the step gate can accept around the predicted one (the matcher adds
        # its margin); without the gate the whole base image is searched
        self._window_radius = (math.ceil(cfg.cycle.step_gate_px)
                               if cfg.match.method == "window" and cfg.cycle.step_gate_px > 0 else None)
        # "view" mode: the last valid step as a rate, rotated to north/east (px/s), for predicting the template's
        # position across cycles that measured nothing (the gates never use it)
        self._last_rate_ne: tuple[float, float] | None = None
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
        offset = (0.0, 0.0)
        if self._view:
            view = self.vcam.view_offset_px(R_nb, yaw)
            if view is None:
                return None
            offset = view
        mx, my, ok = self.vcam.base.sample_map(self.vcam.R_cn(R_nb), yaw, 1.0 / self.focal_px, offset)
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
        ratio = c.height_agl_m / height_agl_m if (math.isfinite(height_agl_m) and height_agl_m > 0
                                                  and math.isfinite(c.height_agl_m)) else 1.0
        if not self.cfg.stab.scale_template_to_base:
            ratio = 1.0
        yaw_now = quat.yaw(q_nb)
        if self._per_second:
            exp_last = self._expected_step(c.last_step_xy, c.last_step_dt_us, t_us - c.last_t_us)
            exp_carried = self._expected_step(c.carried_step_xy, c.carried_step_dt_us, t_us - c.last_t_us)
        else:                                   # "per_frame": the steps themselves
            exp_last, exp_carried = c.last_step_xy, c.carried_step_xy
        # the template's expected position (nadir terms); "view" mode also trusts a step carried from the last cycle,
        # else the last rate measured
        exp_pred = exp_last if exp_last is not None or not self._view else (
            exp_carried if exp_carried is not None else self._rate_step(c, t_us))
        pred = c.last_xy if exp_pred is None else (c.last_xy[0] + exp_pred[0], c.last_xy[1] + exp_pred[1])
        if self._view:
            off_k = self._template_offset(c, pred)
            tpl = self.vcam.sample_template(image, q_nb, c.base_yaw_rad, ratio, off_k)
        else:
            tpl = self.vcam.sample_template(image, q_nb, c.base_yaw_rad, ratio)
        c.step += 1
        if not tpl.valid:
            return [self._step(t_us, c, c.last_xy, _NO_QUALITY, False, yaw_now, rel)] + self._restart(
                t_us, image, att, height_agl_m, c)
        # the step the gates compare with; "window" matching searches where they can accept a match
        prev = exp_last if exp_last is not None else exp_carried
        radius = self._window_radius if prev is not None else None
        if self._view:
            # the template was cut where the prediction puts the base's anchor: it lands there, give or take
            start = (self.ref_uv[0] + c.anchor[1], self.ref_uv[1] - c.anchor[0])
            res = match_template(c.base_image, tpl.image, self.cfg.match, start, radius)
            xy = (res.x_px + c.offset_b[1] - off_k[1], res.y_px - c.offset_b[0] + off_k[0])
        else:
            if radius is not None and prev is not None:
                pred = (c.last_xy[0] + prev[0], c.last_xy[1] + prev[1])
            res = match_template(c.base_image, tpl.image, self.cfg.match, pred, radius)
            xy = (res.x_px, res.y_px)
        step_xy = (xy[0] - c.last_xy[0], xy[1] - c.last_xy[1])
        cc = self.cfg.cycle
        filtered = prev is not None and (
            (cc.data_filter and data_filter_fires(prev, step_xy, cc.data_filter_zeta_px))
            or (cc.step_gate_px > 0 and math.hypot(step_xy[0] - prev[0], step_xy[1] - prev[1]) > cc.step_gate_px))
        valid = res.quality.valid and not filtered
        out = [self._step(t_us, c, xy, res.quality, valid, yaw_now, rel)]
        if not valid:
            return out + self._restart(t_us, image, att, height_agl_m, c)
        c.n_valid += 1
        if self._view and t_us > c.last_t_us:
            cy, sy = math.cos(c.base_yaw_rad), math.sin(c.base_yaw_rad)
            fwd, right = -step_xy[1], step_xy[0]
            k = US_PER_S / (t_us - c.last_t_us)
            self._last_rate_ne = ((fwd * cy - right * sy) * k, (fwd * sy + right * cy) * k)
        c.last_step_xy = step_xy
        c.last_step_dt_us = t_us - c.last_t_us
        c.last_t_us = t_us
        c.last_xy = xy
        nxt = (xy[0] + step_xy[0], xy[1] + step_xy[1])
        if self._view:
            at_edge = not self.vcam.template_fits(q_nb, c.base_yaw_rad, ratio, self._template_offset(c, nxt))
        else:
            at_edge = not (self._u_lim[0] <= nxt[0] <= self._u_lim[1]
                           and self._v_lim[0] <= nxt[1] <= self._v_lim[1])
        if at_edge or t_us - c.base_t_us >= self._max_cycle_us:
            return out + self._restart(t_us, image, att, height_agl_m, c)
        return out

    # ------------------------------------------------------------------------------------------------------
    def _expected_step(self, step: tuple[float, float] | None, step_dt_us: int,
                       dt_us: int) -> tuple[float, float] | None:
        """The step expected over the next ``dt_us`` from a step that spanned ``step_dt_us`` (``step_prediction``)."""
        if step is None or not self._per_second or step_dt_us <= 0:
            return step
        k = dt_us / step_dt_us
        return step[0] * k, step[1] * k

    def _rate_step(self, c: _Cycle, t_us: int) -> tuple[float, float] | None:
        """The step (image x, y of cycle ``c``) the last measured rate predicts since ``c``'s last position."""
        if self._last_rate_ne is None:
            return None
        n, e = self._last_rate_ne
        cy, sy = math.cos(c.base_yaw_rad), math.sin(c.base_yaw_rad)
        dt_s = (t_us - c.last_t_us) / US_PER_S
        fwd, right = (n * cy + e * sy) * dt_s, (-n * sy + e * cy) * dt_s
        return right, -fwd

    def _template_offset(self, c: _Cycle, xy: tuple[float, float]) -> tuple[float, float]:
        """"view" mode: the template's offset from the current nadir (forward, right; base px) that shows the
        base's centre when the nadir has migrated to ``xy`` (nadir terms)."""
        u0, v0 = self.ref_uv
        return c.offset_b[0] + c.anchor[0] - (v0 - xy[1]), c.offset_b[1] + c.anchor[1] - (xy[0] - u0)

    def _anchor(self, base: NDArray[np.float32]) -> tuple[float, float]:
        """"view" mode: the most textured template-sized spot near the base image's centre (forward, right of it;
        the module docstring)."""
        s = self.cfg.stab
        t = s.template_px
        u0, v0 = (int(round(v)) for v in self.ref_uv)
        ru = int((s.base_cross_px - t) / 2 * VIEW_ANCHOR_FRACTION)
        rv = int((s.base_along_px - t) / 2 * VIEW_ANCHOR_FRACTION)
        half = (t - 1) // 2
        region = base[v0 - rv - half:v0 + rv + half + 1, u0 - ru - half:u0 + ru + half + 1].astype(np.float64)
        mean = cv2.boxFilter(region, -1, (t, t), normalize=True, borderType=cv2.BORDER_ISOLATED)
        sq = cv2.boxFilter(region * region, -1, (t, t), normalize=True, borderType=cv2.BORDER_ISOLATED)
        var = (sq - mean * mean)[half:half + 2 * rv + 1, half:half + 2 * ru + 1]
        iv, iu = np.unravel_index(int(np.argmax(var)), var.shape)
        return float(rv - iv), float(iu - ru)

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
            new.carried_step_dt_us = old.last_step_dt_us
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
        offset_b = anchor = (0.0, 0.0)
        if self._view:
            view = self.vcam.view_offset_px(quat.to_matrix(att), yaw0)
            if view is None:
                return []
            offset_b = view
            patch = self.vcam.sample_base(image, quat.to_matrix(att), yaw0, offset_b)
            anchor = self._anchor(patch.image) if patch.valid else anchor
        else:
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
                   step=0, last_xy=self.ref_uv, last_step_xy=None, n_valid=0, offset_b=offset_b, anchor=anchor,
                   last_t_us=t_us)
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
