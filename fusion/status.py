"""Per-source status records (PX4 EKF2's ``estimator_aid_source``) and the reasons common to every source.

Each aid source (:mod:`fusion.aid`) and the IMU fill one :class:`StatusRow` per processed sample; ``status()``
hands out frozen :class:`AidStatus` snapshots of them.  Reasons that only one source gives live in its module.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

# Status reasons (the ``reason`` field of :class:`AidStatus`) shared by the input checks and the filter core.
REASON_NON_FINITE = "non-finite input"
REASON_BAD_SHAPE = "wrong shape"
REASON_BAD_TIME = "bad timestamp"
REASON_NOT_INCREASING = "timestamp not increasing"
REASON_LATE = "late (older than the fusion horizon)"
REASON_BUFFER_FULL = "buffer full"
REASON_ATT_STALE = "attitude too far from the IMU stamp"
REASON_IMU_GAP = "gap before this IMU sample"
REASON_GATE = "innovation gate"
REASON_COV_RESET = "covariance reset (innovation variance below observation variance)"
REASON_NUMERIC = "non-finite update result"
REASON_NO_ATTITUDE = "no attitude yet"


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


class StatusRow:
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

    def fused_again(self, t_us: int, n_fused: int) -> None:
        """Several samples fused at once (the IMU's batches): the stamp of the last and the new count."""
        if self.fused and not self.reason:      # the record already says "fused": only the stamp and count move
            self.t_us = self.t_last_fuse_us = t_us
            self._snap = None
        else:
            self.fused_now(t_us, (), (), math.nan)
        self.n_fused = n_fused

    def snapshot(self) -> AidStatus:
        if self._snap is None:
            self._snap = AidStatus(
                self.source, t_us=self.t_us, innovation=self.innovation, innovation_var=self.innovation_var,
                test_ratio=float(self.test_ratio), fused=self.fused, rejected=self.rejected, reason=self.reason,
                t_last_fuse_us=self.t_last_fuse_us, n_fused=self.n_fused, n_rejected=self.n_rejected)
        return self._snap
