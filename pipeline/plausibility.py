"""Plausibility of IMU and AHRS attitude samples: in range, but could the airframe have done this?

The link (:class:`nav.link.TelemetryGuard`) refuses what is non-finite or beyond the sensors' ranges (35 rad/s,
16 g).  A bit-flipped or spoofed sample can still be inside those ranges: one SCALED_IMU of 15 g and 30 rad/s per
axis, integrated for 20 ms, is a velocity error of 3 m/s, and a few of them diverged the EKF (issue 23).  Before the
pipeline hands a sample to the optical estimator's attitude buffer and to the EKF, :class:`SamplePlausibility`
judges it against what the airframe can do, each test with a named threshold in ``[pipeline]``
(:class:`pipeline.navpipeline.PipelineConfig`; a threshold of 0 switches its test off):

``stamp not increasing``
    an IMU or attitude stamp at or before the last accepted one of its kind (the EKF requires increasing IMU
    stamps; a spoofed message's stamp is arbitrary).
``specific force jump`` / ``rate jump``
    an IMU sample whose specific force (``imu_max_accel_step_m_s2``, any axis) or body rate
    (``imu_max_gyro_step_rad_s``, any axis) differs from the last accepted sample by more than the airframe
    can change between two samples: far from its neighbours.
``gyro disagrees with the AHRS rate``
    an IMU sample whose body rates differ from the rates of the AHRS attitude (the last two accepted attitude
    samples, Euler rates turned into body rates) by more than ``gyro_ahrs_max_diff_rad_s`` on any axis.
``attitude rate disagrees with the gyro``
    an attitude sample whose change since the last accepted one, as body rates, differs by more than
    ``gyro_ahrs_max_diff_rad_s`` from the mean of the gyro samples accepted in between (a jump of the AHRS).
``attitude rate jump (no gyro to compare)``
    the same without a recent gyro sample (the IMU stream lost): the rate against the AHRS's own last rate.

The reference is the last accepted sample of the kind; the comparison is skipped only for the first sample and
after a gap of the stream (no sample of the kind, accepted or not, for ``plausibility_max_gap_s``: a link loss),
so a burst of rejected samples cannot age the reference away.  A genuine step must not lock a stream out: when
``plausibility_confirm_samples`` consecutive samples of one kind have been rejected and agree with each other
(IMU: each within the jump thresholds of the first of them and agreeing with the AHRS rate; attitude: a smooth
run, each rate between two of them close to the one before), the last of them is accepted and becomes the new
reference (counted as ``reanchored``).  A step larger than the thresholds so costs the samples before it was
confirmed (2 at the default: 8 ms at the simulator's 240 Hz, 40 ms at 50 Hz).

Every rejection is counted by kind and reason in :attr:`SamplePlausibility.status` and written to the
``samples_rejected`` stream (``t_us``, ``kind``, ``reason``, ``excess``: the largest difference found, in the
test's unit).

These tests stop isolated and scattered garbage.  A sender that replaces a stream with values consistent with each
other (and, for the IMU, with the AHRS rate) gets through once confirmed: only MAVLink signing stops that
(docs/security.md).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from common.angles import angle_diff
from common.samples import AttitudeSample, ImuSample

if TYPE_CHECKING:
    from pipeline.navpipeline import PipelineConfig

log = logging.getLogger(__name__)

US_PER_S = 1_000_000
LOG_EVERY = 100  # a rejection reason is logged at its first occurrence and then every this many

Vec3 = tuple[float, float, float]
JUMPS = ("specific force jump", "rate jump")   # the IMU reasons a confirmed run overrides


@dataclass
class PlausibilityStatus:
    """Counters of :class:`SamplePlausibility`: accepted samples per kind, rejections per ``kind: reason``,
    re-anchorings per kind, and the last rejection."""

    accepted: dict[str, int] = field(default_factory=lambda: {"imu": 0, "attitude": 0})
    rejected: dict[str, int] = field(default_factory=dict)
    reanchored: dict[str, int] = field(default_factory=dict)
    last_rejected_t_us: int = -1
    last_reason: str = ""

    @property
    def n_rejected(self) -> int:
        return sum(self.rejected.values())


def _vec(a: Any) -> Vec3:
    x, y, z = a.tolist() if hasattr(a, "tolist") else a
    return float(x), float(y), float(z)


def _max_abs_diff(a: Vec3, b: Vec3) -> float:
    return max(abs(a[0] - b[0]), abs(a[1] - b[1]), abs(a[2] - b[2]))


def euler_rates_to_body(roll_rad: float, pitch_rad: float, droll: float, dpitch: float, dyaw: float) -> Vec3:
    """Body rates (p, q, r, rad/s, FRD) from 3-2-1 Euler angle rates at the given roll and pitch."""
    sr, cr = math.sin(roll_rad), math.cos(roll_rad)
    sp, cp = math.sin(pitch_rad), math.cos(pitch_rad)
    return (droll - dyaw * sp,
            dpitch * cr + dyaw * sr * cp,
            -dpitch * sr + dyaw * cr * cp)


def ahrs_body_rate(a: AttitudeSample, b: AttitudeSample) -> Vec3 | None:
    """The mean body rate (rad/s) between two attitude samples (``b`` later), at their mid attitude; None when
    their stamps do not increase."""
    dt = (b.t_us - a.t_us) / US_PER_S
    if dt <= 0.0:
        return None
    droll = float(angle_diff(b.roll_rad, a.roll_rad)) / dt
    dpitch = (b.pitch_rad - a.pitch_rad) / dt
    dyaw = float(angle_diff(b.yaw_rad, a.yaw_rad)) / dt
    roll = a.roll_rad + 0.5 * float(angle_diff(b.roll_rad, a.roll_rad))
    pitch = 0.5 * (a.pitch_rad + b.pitch_rad)
    return euler_rates_to_body(roll, pitch, droll, dpitch, dyaw)


class SamplePlausibility:
    """The plausibility tests of the module docstring; ``imu(s)`` and ``attitude(s)`` return True when the sample
    may be used.  Push the samples of each kind in the order they arrive."""

    def __init__(self, cfg: PipelineConfig, sink: Callable[[str, dict[str, Any]], None] | None = None) -> None:
        self.status = PlausibilityStatus()
        self._sink = sink
        self._acc_step = cfg.imu_max_accel_step_m_s2
        self._gyro_step = cfg.imu_max_gyro_step_rad_s
        self._ahrs_diff = cfg.gyro_ahrs_max_diff_rad_s
        self._gap_us = round(cfg.plausibility_max_gap_s * US_PER_S)
        self._confirm = cfg.plausibility_confirm_samples
        # IMU: the last accepted sample, the rejected run waiting for confirmation
        self._imu_t_us: int | None = None
        self._imu_seen_us: int | None = None     # the previous IMU sample received, whatever its verdict
        self._gyro: Vec3 = (0.0, 0.0, 0.0)
        self._acc: Vec3 = (0.0, 0.0, 0.0)
        self._imu_run: list[tuple[int, Vec3, Vec3]] = []
        # gyro accepted since the last accepted attitude: sums and count (the attitude test's mean)
        self._gyro_sum = [0.0, 0.0, 0.0]
        self._gyro_n = 0
        # attitude: the last accepted sample, the AHRS rate between the last two, the rejected run's length
        self._att: AttitudeSample | None = None
        self._att_seen_us: int | None = None
        self._ahrs_rate: Vec3 | None = None
        self._ahrs_rate_t_us = -(2**62)
        self._att_run: list[AttitudeSample] = []

    # ------------------------------------------------------------------------------------------------ IMU
    def imu(self, s: ImuSample) -> bool:
        t = int(s.t_us)
        g, a = _vec(s.gyro_b_rad_s), _vec(s.accel_b_m_s2)
        seen, self._imu_seen_us = self._imu_seen_us, t
        reason, excess = self._imu_test(t, g, a, seen is not None and t - seen <= self._gap_us)
        if not reason:
            self._imu_run.clear()
            self._accept_imu(t, g, a)
            return True
        if reason in JUMPS and self._confirmed_imu(t, g, a):
            self._count_reanchor("imu", t)
            self._gyro_sum = [0.0, 0.0, 0.0]  # the gyro accepted before the change says nothing of the AHRS now
            self._gyro_n = 0
            self._accept_imu(t, g, a)
            return True
        self._reject("imu", t, reason, excess)
        return False

    def _imu_test(self, t: int, g: Vec3, a: Vec3, no_gap: bool) -> tuple[str, float]:
        last = self._imu_t_us
        if last is not None and t <= last:
            return "stamp not increasing", (last - t) / US_PER_S
        if last is not None and no_gap:
            if self._acc_step > 0.0:
                d = _max_abs_diff(a, self._acc)
                if d > self._acc_step:
                    return "specific force jump", d
            if self._gyro_step > 0.0:
                d = _max_abs_diff(g, self._gyro)
                if d > self._gyro_step:
                    return "rate jump", d
        d = self._ahrs_excess(t, g)
        if d > self._ahrs_diff:
            return "gyro disagrees with the AHRS rate", d
        return "", 0.0

    def _ahrs_excess(self, t: int, g: Vec3) -> float:
        """The largest difference (rad/s) between the gyro ``g`` and the recent AHRS rate; 0 without one (or with
        the test off)."""
        if self._ahrs_diff <= 0.0 or self._ahrs_rate is None or abs(t - self._ahrs_rate_t_us) > self._gap_us:
            return 0.0
        return _max_abs_diff(g, self._ahrs_rate)

    def _confirmed_imu(self, t: int, g: Vec3, a: Vec3) -> bool:
        """The rejected run so far plus this sample: confirmed when long enough, each of its samples within the
        jump thresholds of the run's first and agreeing with the AHRS rate (a lasting change the attitude shows
        too, not scattered garbage nor a repeated spoof)."""
        run = self._imu_run
        if self._ahrs_excess(t, g) > self._ahrs_diff:
            run.clear()
            return False
        if run and (t - run[-1][0] > self._gap_us or not self._close(run[0], g, a)):
            run.clear()
        run.append((t, g, a))
        if len(run) < self._confirm:
            return False
        run.clear()
        return True

    def _close(self, ref: tuple[int, Vec3, Vec3], g: Vec3, a: Vec3) -> bool:
        _, g0, a0 = ref
        acc_ok = self._acc_step <= 0.0 or _max_abs_diff(a, a0) <= self._acc_step
        gyro_ok = self._gyro_step <= 0.0 or _max_abs_diff(g, g0) <= self._gyro_step
        return acc_ok and gyro_ok

    def _accept_imu(self, t: int, g: Vec3, a: Vec3) -> None:
        self._imu_t_us, self._gyro, self._acc = t, g, a
        self._gyro_sum[0] += g[0]
        self._gyro_sum[1] += g[1]
        self._gyro_sum[2] += g[2]
        self._gyro_n += 1
        self.status.accepted["imu"] += 1

    # ------------------------------------------------------------------------------------------------ attitude
    def attitude(self, s: AttitudeSample) -> bool:
        t = int(s.t_us)
        prev = self._att
        seen, self._att_seen_us = self._att_seen_us, t
        if prev is not None and t <= prev.t_us:
            self._reject("attitude", t, "stamp not increasing", (prev.t_us - t) / US_PER_S)
            return False
        reason, excess, rate = "", 0.0, None
        if prev is not None and seen is not None and t - seen <= self._gap_us:
            reason, excess, rate = self._attitude_test(prev, s)
        if reason and self._confirmed_attitude(s):
            self._count_reanchor("attitude", t)
            reason, rate = "", None               # a new reference: no rate from the rejected run's start
        if reason:
            self._reject("attitude", t, reason, excess)
            return False
        self._att_run.clear()
        self._att = s
        self._ahrs_rate = rate
        self._ahrs_rate_t_us = t
        self._gyro_sum = [0.0, 0.0, 0.0]
        self._gyro_n = 0
        self.status.accepted["attitude"] += 1
        return True

    def _attitude_test(self, prev: AttitudeSample, s: AttitudeSample) -> tuple[str, float, Vec3 | None]:
        """(reason or "", excess, the AHRS rate from ``prev`` to ``s``): the rate against the gyro accepted since
        ``prev``; without a recent gyro sample (the IMU stream lost) against the AHRS's own last rate, which cannot
        jump either."""
        rate = ahrs_body_rate(prev, s)
        if rate is None or self._ahrs_diff <= 0.0:
            return "", 0.0, rate
        gyro = self._gyro_mean(s.t_us)
        if gyro is not None:
            d = _max_abs_diff(rate, gyro)
            return ("attitude rate disagrees with the gyro" if d > self._ahrs_diff else ""), d, rate
        own = self._ahrs_rate
        if own is not None and s.t_us - self._ahrs_rate_t_us <= self._gap_us:
            d = _max_abs_diff(rate, own)
            return ("attitude rate jump (no gyro to compare)" if d > self._ahrs_diff else ""), d, rate
        return "", 0.0, rate

    def _confirmed_attitude(self, s: AttitudeSample) -> bool:
        """The rejected run so far plus ``s``: confirmed when long enough and smooth, the rate between each two of
        its samples within ``gyro_ahrs_max_diff_rad_s`` of the rate between the two before (the AHRS moved on, not
        scattered garbage).  The gyro is not asked: it may be what made the run's start fail."""
        run = self._att_run
        if run and s.t_us - run[-1].t_us > self._gap_us:
            run.clear()
        if len(run) >= 2:
            r1, r2 = ahrs_body_rate(run[-2], run[-1]), ahrs_body_rate(run[-1], s)
            if r1 is None or r2 is None or (self._ahrs_diff > 0.0 and _max_abs_diff(r1, r2) > self._ahrs_diff):
                run.clear()
        run.append(s)
        if len(run) < self._confirm:
            return False
        run.clear()
        return True

    def _gyro_mean(self, t: int) -> Vec3 | None:
        """The mean of the gyro samples accepted since the last accepted attitude, else the last accepted gyro
        sample when recent; None without either."""
        n = self._gyro_n
        if n:
            return self._gyro_sum[0] / n, self._gyro_sum[1] / n, self._gyro_sum[2] / n
        if self._imu_t_us is not None and abs(t - self._imu_t_us) <= self._gap_us:
            return self._gyro
        return None

    # ------------------------------------------------------------------------------------------------ bookkeeping
    def _reject(self, kind: str, t_us: int, reason: str, excess: float) -> None:
        key = f"{kind}: {reason}"
        n = self.status.rejected.get(key, 0) + 1
        self.status.rejected[key] = n
        self.status.last_rejected_t_us = t_us
        self.status.last_reason = key
        if n == 1 or n % LOG_EVERY == 0:
            log.warning("implausible %s sample rejected at t=%d us: %s (%.3g); %d so far", kind, t_us, reason,
                        excess, n)
        if self._sink is not None:
            self._sink("samples_rejected", {"t_us": t_us, "kind": kind, "reason": reason, "excess": excess})

    def _count_reanchor(self, kind: str, t_us: int) -> None:
        n = self.status.reanchored.get(kind, 0) + 1
        self.status.reanchored[kind] = n
        log.warning("%s: %d consecutive samples rejected agree with each other: accepted as a new reference at "
                    "t=%d us (%d re-anchorings)", kind, self._confirm, t_us, n)
