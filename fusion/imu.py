"""The IMU integrator: sums the IMU samples between covariance predictions and runs them through the process model.

An IMU sample is the IMU's output over the interval its stamp ends (the mean of an averaging link, the output of
the IMU's filter), paired with the attitude at its stamp, the interval's end: its specific force is turned back to
the interval's middle with its own body rates, ``f - (dt / 2) omega x f`` (first order).  Otherwise a sample rotated
by its end's attitude leads the body by half an interval, 10 ms at a link's 50 Hz, and in a turn the velocity's
direction leads by that much.  The last sample held past its stamp (:meth:`ImuIntegrator.predict_to`) is turned on,
``+``, to the middle of that extension.

The per-IMU-sample work is a few floating-point additions: samples with the same AHRS attitude are summed as
``sum f_b dt``, ``sum (omega_b x f_b) dt`` and their first moments ``... dt t_mid`` (``t_mid``: the sample interval's
midpoint from the start of the prediction); when the attitude changes, or when the covariance is predicted, these
sums are rotated once by ``R_nb`` into ``sum R_nb f dt``, ``sum R_nb dt``, ``sum R_nb (omega x f) dt`` and their
moments (:class:`~fusion.process.ImuIncrement`).  The covariance rate is then a free choice: it is predicted at most
every ``predict_period_s`` while only IMU samples arrive, and once at the stamp of a measurement (all measurements
with one stamp share it).  The integrator also keeps what the air-data models read from the IMU: the AHRS attitude
of the last processed sample and the low-passed lateral and normal specific forces.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import NDArray
from scipy.constants import g as STANDARD_GRAVITY_M_S2

from common.samples import AttitudeSample
from fusion.config import EkfConfig
from fusion.core import FilterCore
from fusion.process import S_PER_US, US_PER_S, ProcessModel, rot_rows
from fusion.status import REASON_IMU_GAP, StatusRow

Mat = NDArray[np.float64]
#: One queued IMU sample: stamp (µs), specific force (3, m/s^2), body rates (3, rad/s), FRD, and its attitude.
ImuEntry = tuple[int, float, float, float, float, float, float, AttitudeSample]

_ACC_LEN = 30           # floats of the accumulated increment (see ImuIntegrator.__init__)
_SEG_LEN = 14           # floats of an open segment (see ImuIntegrator.__init__)
#: (segment index, increment index) of the 3-vectors a fold rotates: sum f dt, sum f dt t_mid, sum (w x f) dt and
#: sum (w x f) dt t_mid
_FOLD_VECTORS = ((0, 0), (3, 3), (8, 24), (11, 27))


class ImuIntegrator:
    """Consumes IMU samples up to a time and predicts the filter to it (module docstring).

    ``t_x_us`` is the time of the filter state (the fusion horizon), ``t_in_us`` how far the inputs have been
    consumed (``>= t_x_us``; the rest is accumulated, to be predicted at the next measurement or period)."""

    def __init__(self, cfg: EkfConfig, core: FilterCore, process: ProcessModel, row: StatusRow, t_us: int) -> None:
        self._core, self._process, self._row = core, process, row
        self.t_x_us = self.t_in_us = t_us
        # The covariance prediction being accumulated over [t_x_us, t_in_us] (ImuIncrement), as floats: sum R f dt
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
        self.rates_held = (0.0, 0.0, 0.0)                #: body rates of the last IMU sample (rad/s, FRD)
        #: lateral specific force (body y, m/s^2), low-passed over sideslip_accel_tau_s (NaN before any sample)
        self.lat_f = math.nan
        self.nrm_f = math.nan                            #: normal specific force (body z, m/s^2), low-passed alike
        self._lat_rate_per_s = 1.0 / cfg.airframe.accel_tau_s if cfg.airframe.accel_tau_s > 0.0 else math.inf
        self.att: AttitudeSample | None = None           #: AHRS attitude of the last processed IMU sample
        self._att_out: AttitudeSample | None = None      # newest pushed attitude (output before any is processed)
        self._Rl: tuple[float, ...] | None = None        # its rotation (body to AHRS-NED), row by row
        self._R_nb: Mat | None = None                    # the same as a matrix (built when a model needs it)
        self._period_us = round(cfg.timing.predict_period_s * US_PER_S)
        self._gap_us = round(cfg.timing.imu_max_gap_s * US_PER_S)
        #: bumped whenever what the output reads from the IMU (attitude, rates) changes
        self.version = 0

    def output_attitude(self) -> AttitudeSample | None:
        """The attitude the output heading uses: the last processed one, or the newest pushed before that."""
        return self.att if self.att is not None else self._att_out

    def pushed(self, att: AttitudeSample) -> None:
        """A sample with attitude ``att`` entered the queue."""
        if self.att is None:
            self._att_out = att             # heading for the output until the horizon reaches an IMU sample
            self.version += 1

    def R_nb_rows(self) -> tuple[float, ...] | None:
        """:meth:`R_nb` as its nine entries, row by row (what the per-sample models read)."""
        return self._Rl

    def R_nb(self) -> Mat | None:
        """Body-to-AHRS-NED rotation of the last processed IMU sample (``None`` before one)."""
        if self._R_nb is None and self._Rl is not None:
            self._R_nb = np.array(self._Rl).reshape(3, 3)
        return self._R_nb

    # ----------------------------------------------------------------------------------------------------------
    def run(self, q: deque[ImuEntry], t_end: int) -> None:
        """Process the queued IMU samples stamped at or before ``t_end``, in order.  Each sample covers the interval
        since the previous one with its own specific force, body rates and attitude: it is added to the open segment
        (a new attitude closes the segment first, :meth:`_fold`), and the covariance is predicted once
        ``predict_period_s`` has accumulated.  One loop over local floats: this is the per-sample path."""
        s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, s10, s11, s12, s13 = self._seg
        opened, t_in, t_x, a0 = self._seg_open, self.t_in_us, self.t_x_us, self.att
        n_fused = self._row.n_fused
        gap = False
        fx = fy = fz = gx = gy = gz = 0.0
        lat, lat_rate, nrm = self.lat_f, self._lat_rate_per_s, self.nrm_f
        gap_us, period_us = self._gap_us, self._period_us
        if math.isnan(lat) and q:
            lat, nrm = q[0][2], q[0][3]                   # the low-passes start at the first sample's f_y, f_z
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
                    self._Rl = rot_rows(att.roll_rad, att.pitch_rad, att.yaw_rad)
                    self._R_nb = None
                    self.version += 1      # the output heading follows the AHRS
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
                h = 0.5 * dt                  # the attitude is the interval's end's: rotate back to its middle
                ax, ay, az = (fx - h * wx) * dt, (fy - h * wy) * dt, (fz - h * wz) * dt
                s0, s1, s2, s3, s4, s5 = s0 + ax, s1 + ay, s2 + az, s3 + ax * mid, s4 + ay * mid, s5 + az * mid
                s6, s7 = s6 + dt, s7 + dt * mid
                ax, ay, az = wx * dt, wy * dt, wz * dt
                s8, s9, s10 = s8 + ax, s9 + ay, s10 + az
                s11, s12, s13 = s11 + ax * mid, s12 + ay * mid, s13 + az * mid
                opened = True
                t_in = t
                if t_in - t_x >= period_us:
                    self._seg = [s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, s10, s11, s12, s13]
                    self._seg_open, self.t_in_us = opened, t_in
                    self._flush()
                    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = s9 = s10 = s11 = s12 = s13 = 0.0
                    opened = False
                    t_x = self.t_x_us
        self._seg = [s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, s10, s11, s12, s13]
        self._seg_open, self.t_in_us, self.att, self.lat_f, self.nrm_f = opened, t_in, a0, lat, nrm
        if n_fused != self._row.n_fused:
            self._ran(t, n_fused, gap, (fx, fy, fz), (gx, gy, gz))

    def _ran(self, t: int, n_fused: int, gap: bool, f: tuple[float, float, float],
             rates: tuple[float, float, float]) -> None:
        """Samples up to ``t`` were processed: hold the last one's specific force and rates; the ``imu`` status."""
        fx, fy, fz = f
        gx, gy, gz = self.rates_held = rates
        self._f_held = (fx, fy, fz, gy * fz - gz * fy, gz * fx - gx * fz, gx * fy - gy * fx)
        self.version += 1                     # the output heading uses the newest body rates
        self._row.fused_again(t, n_fused)
        if gap:
            self._row.reason = REASON_IMU_GAP

    def _fold(self) -> None:
        """Rotate the open segment's sums by its attitude into the prediction's increment."""
        seg, a = self._seg, self._acc
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = self._Rl   # type: ignore[misc]
        for i, o in _FOLD_VECTORS:                       # R (sum f dt), R (sum f dt t_mid), R (sum w x f dt), ...
            v0, v1, v2 = seg[i], seg[i + 1], seg[i + 2]
            a[o] += r00 * v0 + r01 * v1 + r02 * v2
            a[o + 1] += r10 * v0 + r11 * v1 + r12 * v2
            a[o + 2] += r20 * v0 + r21 * v1 + r22 * v2
        sdt, sdm = seg[6], seg[7]
        for i, r in enumerate((r00, r01, r02, r10, r11, r12, r20, r21, r22)):
            a[6 + i] += r * sdt                           # sum R dt, row by row
            a[15 + i] += r * sdm                          # sum R dt t_mid
        self._seg = [0.0] * _SEG_LEN
        self._seg_open = False

    def _flush(self) -> None:
        """Predict the state and covariance over everything consumed: the filter time becomes ``t_in_us``."""
        if self._seg_open:
            self._fold()
        T_us = self.t_in_us - self.t_x_us
        if T_us > 0:
            core = self._core
            # the sums go to the process model as they are (the increment carries only the interval)
            x_new, Q, add_var = self._process.step_sums(core.x, core.P, T_us * S_PER_US, self._acc)
            core.predict(x_new, self._process.F, Q, add_var)
            self._acc = [0.0] * _ACC_LEN
            self.t_x_us = self.t_in_us

    def predict_to(self, t: int) -> None:
        """Bring the state to ``t`` (>= the inputs consumed) in one prediction: the consumed samples plus the last
        sample held (zero-order hold) from its stamp to ``t``; before the first IMU sample the velocity is held."""
        t_in = self.t_in_us
        dt_us = t - t_in
        if dt_us > 0:
            dt = dt_us * S_PER_US
            mid = (t + t_in - 2 * self.t_x_us) * (0.5 * S_PER_US)
            if self._f_held is not None:
                seg = self._seg
                f_held = self._f_held                            # f (0-2) and omega x f (3-5) of the held sample
                h = 0.5 * dt                 # the attitude is the interval's start's: rotate on to its middle
                for k, v in enumerate(f_held):
                    if k < 3:
                        v += h * f_held[k + 3]
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
            self.t_in_us = t
        self._flush()
