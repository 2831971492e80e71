"""GNSS position and velocity: direct measurements of states, and their aid sources.

GNSS rejected continuously for ``gnss.reset_after_s`` (e.g. back after a long outage) resets the position
(velocity) to it, as PX4 does; a position reset re-anchors the current optical cycle.  Position fixes closer than
``gnss.pos_corr_time_s`` share their receiver error, so their variance is inflated by ``2 tau / dt`` (the
information rate of a Gauss-Markov error).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, ClassVar, Self

import numpy as np

from fusion.aid.base import AidSource, ModelBase, Vec
from fusion.config import EkfConfig
from fusion.core import Linearised
from fusion.process import US_PER_S
from fusion.state import S
from fusion.status import REASON_BAD_SHAPE, REASON_GATE, REASON_NON_FINITE
from fusion.timeline import finite, is_int

log = logging.getLogger(__name__)

REASON_BAD_SIGMA = "sigma not a positive finite number"
REASON_RESET_TO_MEAS = "state reset to the measurement after continuous rejection"


@dataclass(frozen=True, slots=True)
class GnssFix(ModelBase):
    """A direct GNSS measurement of the ``dim`` states from :attr:`START` (2: north/east, 3: with down) with the noise
    variances ``var`` (one per axis, in the square of the measurement's unit); ``H`` is the rows :attr:`state_idx` of
    the identity.  The config's sigmas are the fields :attr:`SIGMA_FIELDS` (horizontal, vertical) of ``gnss``."""

    START: ClassVar[int]
    SIGMA_FIELDS: ClassVar[tuple[str, str]]
    dim: int
    var: tuple[float, ...]

    @classmethod
    def from_config(cls, cfg: EkfConfig, dim: int, sigma_ne: float | None = None,
                    sigma_d: float | None = None) -> Self:
        """The receiver's own accuracies replace the config's when given."""
        ne = getattr(cfg.gnss, cls.SIGMA_FIELDS[0]) if sigma_ne is None else float(sigma_ne)
        d = getattr(cfg.gnss, cls.SIGMA_FIELDS[1]) if sigma_d is None else float(sigma_d)
        return cls(dim, (ne * ne, ne * ne, d * d)[:dim])

    @property
    def state_idx(self) -> list[int]:
        """Indices of the measured states, in measurement order."""
        return list(range(self.START, self.START + self.dim))

    def linearise(self, x: Vec) -> Linearised:
        return Linearised(tuple(x[self.state_idx].tolist()), None, self.state_idx, self.var[: self.dim])


@dataclass(frozen=True, slots=True)
class GnssPosition(GnssFix):
    """GNSS position in the local NED frame (m): ``pos_ne`` (``dim=2``) or ``pos_ne, pos_d`` (``dim=3``); ``var`` in
    m^2."""

    START: ClassVar[int] = S.pos_ned.start
    SIGMA_FIELDS: ClassVar[tuple[str, str]] = ("pos_ne_sigma_m", "pos_d_sigma_m")


@dataclass(frozen=True, slots=True)
class GnssVelocity(GnssFix):
    """GNSS ground velocity (m/s): ``vel_ne`` (``dim=2``, e.g. from ground speed and course) or ``vel_ned``; ``var`` in
    (m/s)^2."""

    START: ClassVar[int] = S.vel_ned.start
    SIGMA_FIELDS: ClassVar[tuple[str, str]] = ("vel_ne_sigma_m_s", "vel_d_sigma_m_s")


class _GnssAid(AidSource):
    """Shared life cycle of the position and the velocity: fuse, and reset to the fix after continuous rejection."""

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self._reject_since: int | None = None

    def accept(self, t_us: Any, sample: Any) -> tuple[Any, Any] | None:
        """``sample`` = (2 or 3 values or ``None``, (sigma_ne, sigma_d), each ``None`` or a positive number)."""
        val, sigmas = sample
        if val is None:
            return None
        tt = int(t_us) if is_int(t_us) else -1
        a = np.asarray(val, dtype=float).reshape(-1) if finite(val) else None
        if a is not None and a.shape not in ((2,), (3,)):
            self.row.set(tt, rejected=True, reason=REASON_BAD_SHAPE)
            return None
        if a is None:
            self.row.set(tt, rejected=True, reason=REASON_NON_FINITE)
            return None
        if not all(s is None or (finite(s) and float(s) > 0.0) for s in sigmas):
            self.row.set(tt, rejected=True, reason=REASON_BAD_SIGMA)
            return None
        return (a, sigmas), 0.0

    def model(self, t_us: int, dim: int, sigmas: tuple[float | None, float | None]) -> GnssFix:
        raise NotImplementedError

    def gate_nis(self) -> float:
        raise NotImplementedError

    def control(self, t_us: int, sample: tuple[Vec, tuple[float | None, float | None]]) -> bool:
        z, sigmas = sample
        model = self.model(t_us, z.shape[0], sigmas)
        if self.fuse(t_us, z, model, self.gate_nis()):
            self._reject_since = None
            return True
        if self.row.reason != REASON_GATE:
            return True
        since = self._reject_since
        if since is None:
            self._reject_since = t_us
        elif t_us - since >= self.cfg.gnss.reset_after_s * US_PER_S:
            self.reset(t_us, (z, model))
            log.warning("EKF: %s rejected for %.1f s, state reset to GNSS at %d us", self.name,
                        (t_us - since) / US_PER_S, t_us)
        return True

    def reset(self, t_us: int, sample: tuple[Vec, GnssFix]) -> None:
        """The measured states become the fix with its noise (the rejected sample is counted as used after all)."""
        z, model = sample
        lin = model.linearise(self.core.x)
        self.core.reset_states(np.array(model.state_idx), z, np.diag(lin.r))
        self._reject_since = None
        row = self.row
        row.n_rejected -= 1
        row.set(t_us, fused=True, reason=REASON_RESET_TO_MEAS, innovation=row.innovation,
                innovation_var=row.innovation_var, test_ratio=row.test_ratio)

    def stop(self) -> None:
        self._reject_since = None


class GnssPositionAid(_GnssAid):
    """GNSS position (gate ``gates.gnss_pos_nis``; correlated receiver error, module docstring)."""

    name = "gnss_pos"
    events: ClassVar[dict[str, int]] = {"gnss_pos": 1}

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self._last_us: int | None = None

    def gate_nis(self) -> float:
        return self.cfg.gates.gnss_pos_nis

    def model(self, t_us: int, dim: int, sigmas: tuple[float | None, float | None]) -> GnssPosition:
        m = GnssPosition.from_config(self.cfg, dim, *sigmas)
        tau = self.cfg.gnss.pos_corr_time_s
        # correlated receiver error: fixes closer than the correlation time share their error
        if self._last_us is not None and tau > 0.0:
            dt = max(t_us - self._last_us, 1) / US_PER_S
            k = max(1.0, 2.0 * tau / dt)
            m = GnssPosition(dim, tuple(v * k for v in m.var))
        self._last_us = t_us
        return m


class GnssVelocityAid(_GnssAid):
    """GNSS velocity (gate ``gates.gnss_vel_nis``)."""

    name = "gnss_vel"
    events: ClassVar[dict[str, int]] = {"gnss_vel": 2}

    def gate_nis(self) -> float:
        return self.cfg.gates.gnss_vel_nis

    def model(self, t_us: int, dim: int, sigmas: tuple[float | None, float | None]) -> GnssVelocity:
        return GnssVelocity.from_config(self.cfg, dim, *sigmas)
