"""The filter's timeline: IMU FIFO, measurement heap, the delayed fusion horizon and the admission checks.

Every input carries its ``t_us`` (STYLE section 6).  IMU samples (in stamp order) wait in a FIFO, measurements in a
time-ordered heap, and the filter runs on a *delayed fusion horizon* ``fusion_delay_s`` behind the newest IMU sample
(PX4 EKF2's ``pop_first_older_than``): a measurement is fused at its own stamp, the state being predicted from the
last IMU sample to it (zero-order hold).  An input older than what the filter has already processed is rejected
with reason ``late``.  Events with the same stamp are processed in a fixed order (the IMU sample first, then the
aid sources' ``stamp_order``) whatever their arrival order, so a replay with other latencies gives the same filter.
IMU samples wait until something needs them (a due measurement, a reader, a prediction period behind the horizon)
and are then processed in one loop; the result does not depend on when that happens.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from common.samples import AttitudeSample, ImuSample
from fusion.config import EkfConfig
from fusion.imu import ImuEntry, ImuIntegrator
from fusion.process import US_PER_S
from fusion.status import (
    REASON_ATT_STALE,
    REASON_BAD_SHAPE,
    REASON_BAD_TIME,
    REASON_BUFFER_FULL,
    REASON_LATE,
    REASON_NON_FINITE,
    REASON_NOT_INCREASING,
    StatusRow,
)

log = logging.getLogger(__name__)

#: Same-stamp rank of the IMU sample: before every measurement (the state is predicted to the stamp first).
IMU_STAMP_ORDER = 0


def is_int(t: Any) -> bool:
    """An integer timestamp (Python or NumPy; not a bool)."""
    return type(t) is int or (isinstance(t, int | np.integer) and not isinstance(t, bool))


def finite(*values: Any) -> bool:
    """All values (numbers or arrays of numbers) finite; anything that is not numeric counts as not finite."""
    for v in values:
        if type(v) is float or (isinstance(v, float | int) and not isinstance(v, bool)):
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


class Timeline:
    """Orders the inputs in time and hands each due one on: IMU samples to the :class:`~fusion.imu.ImuIntegrator`,
    measurements (and scheduled events such as an optical clone) to ``dispatch(t_us, kind, payload)``.

    ``stamp_order`` maps every event kind to its same-stamp rank (after :data:`IMU_STAMP_ORDER`)."""

    def __init__(self, cfg: EkfConfig, imu: ImuIntegrator, imu_row: StatusRow,
                 dispatch: Callable[[int, str, Any], None], stamp_order: Mapping[str, int]) -> None:
        self._imu, self._imu_row, self._dispatch = imu, imu_row, dispatch
        self._order = dict(stamp_order)
        self.newest_imu_us: int | None = None
        self._imu_q: deque[ImuEntry] = deque()
        self._heap: list[tuple[int, int, int, str, Any]] = []
        self._seq = itertools.count()
        self._n_meas_buffered = 0
        self._buffer_max = cfg.timing.buffer_max_events
        self._buffer_full_warned = False
        self._delay_us = round(cfg.timing.fusion_delay_s * US_PER_S)
        self._period_us = round(cfg.timing.predict_period_s * US_PER_S)
        self._att_age_us = round(cfg.timing.att_max_age_s * US_PER_S)

    @property
    def imu_waiting(self) -> bool:
        """IMU samples wait in the FIFO."""
        return bool(self._imu_q)

    # ----------------------------------------------------------------------------------------------------------
    def push_imu(self, imu: ImuSample, att: AttitudeSample) -> None:
        """Admit one IMU sample with its attitude (or record why not in the ``imu`` status) and queue it."""
        entry, reason = self._check_imu(imu, att)
        if entry is None:
            t = getattr(imu, "t_us", -1)
            self._imu_row.set(int(t) if is_int(t) else -1, rejected=True, reason=reason)
            return
        t = entry[0]
        self.newest_imu_us = t
        if self._imu.att is None:                 # the output's heading until the horizon reaches a sample
            self._imu.pushed(att)
        q = self._imu_q
        q.append(entry)
        # Due samples are processed in batches (the result is the same as one by one): now if a measurement is
        # due, or the oldest waiting sample is a prediction period behind the horizon; otherwise when anything
        # reads the filter (estimate, status, the properties) or a measurement arrives.
        horizon = t - self._delay_us
        heap = self._heap
        if (heap and heap[0][0] <= horizon) or q[0][0] <= horizon - self._period_us:
            self.process_due()

    def _check_imu(self, imu: ImuSample, att: AttitudeSample) -> tuple[ImuEntry | None, str]:
        """The queue entry of a valid sample, or ``None`` and the reason.  Written out (not per-field helpers):
        this is the per-sample path."""
        try:
            t, ta = imu.t_us, att.t_us
            if not ((type(t) is int or is_int(t)) and (type(ta) is int or is_int(ta))):
                return None, REASON_BAD_TIME
            a, g = imu.accel_b_m_s2, imu.gyro_b_rad_s
            if not (type(a) is np.ndarray and type(g) is np.ndarray):
                a, g = np.asarray(a, dtype=float), np.asarray(g, dtype=float)
            # unpacking checks the shape: anything but 3 numbers raises (or gives lists, which do not add up)
            fx, fy, fz = a.tolist()
            gx, gy, gz = g.tolist()
            # the sum of finite numbers is finite (an overflow at absurd magnitudes is rejected as well)
            if not math.isfinite(fx + fy + fz + gx + gy + gz + att.roll_rad + att.pitch_rad + att.yaw_rad):
                return None, REASON_NON_FINITE
        except (AttributeError, TypeError, ValueError, IndexError):
            return None, REASON_BAD_SHAPE
        t = int(t)
        newest = self.newest_imu_us
        if newest is not None and t <= newest:
            return None, REASON_NOT_INCREASING
        if t < self._imu.t_in_us:
            return None, REASON_LATE
        if abs(int(ta) - t) > self._att_age_us:
            return None, REASON_ATT_STALE
        return (t, fx, fy, fz, gx, gy, gz, att), ""

    def admit(self, row: StatusRow, t_us: Any, value: Any) -> bool:
        """Whether a measurement stamped ``t_us`` (its ``value`` checked for finiteness) may enter the buffer;
        if not, ``row`` says why.  What is due is processed first, so "late" means the same whenever it is asked."""
        if self._imu_q:
            self.process_due()
        if not (type(t_us) is int or is_int(t_us)):
            row.set(-1, rejected=True, reason=REASON_BAD_TIME)
            return False
        if not finite(value):
            row.set(int(t_us), rejected=True, reason=REASON_NON_FINITE)
            return False
        if t_us < self._imu.t_in_us:
            row.set(int(t_us), rejected=True, reason=REASON_LATE)
            return False
        if self._n_meas_buffered >= self._buffer_max:
            row.set(int(t_us), rejected=True, reason=REASON_BUFFER_FULL)
            if not self._buffer_full_warned:
                log.warning("EKF buffer full (%d measurements waiting: IMU stopped, or samples stamped ahead of "
                            "the IMU clock?): dropping %s samples", self._n_meas_buffered, row.source)
                self._buffer_full_warned = True
            return False
        self._buffer_full_warned = False
        return True

    def push(self, t_us: int, kind: str, payload: Any) -> None:
        """Queue an admitted measurement and process what is due."""
        t = int(t_us)
        newest = self.newest_imu_us
        if not self._heap and not self._imu_q and newest is not None and t <= newest - self._delay_us:
            self._dispatch(t, kind, payload)    # nothing waits before it: due now (the usual case without delay)
            return
        self.schedule(t, kind, payload)
        self.process_due()

    def schedule(self, t_us: int, kind: str, payload: Any) -> None:
        """Queue an event without processing (e.g. the clone at an optical cycle's base time)."""
        heapq.heappush(self._heap, (int(t_us), self._order[kind], next(self._seq), kind, payload))
        self._n_meas_buffered += 1

    def process_due(self) -> None:
        """Process, in time order, every buffered input at or before the horizon (the IMU samples up to a
        measurement's stamp before it)."""
        if self.newest_imu_us is None:
            return
        horizon = self.newest_imu_us - self._delay_us
        q, heap = self._imu_q, self._heap
        while True:
            if q and q[0][0] <= horizon:
                limit = min(horizon, heap[0][0]) if heap else horizon
                if q[0][0] <= limit:
                    self._imu.run(q, limit)
                    continue
            if not heap or heap[0][0] > horizon:
                return
            t, _, _, kind, payload = heapq.heappop(heap)
            self._n_meas_buffered -= 1
            self._dispatch(t, kind, payload)
