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

:class:`NavEkf` puts together (one module each, design notes there):

- :mod:`fusion.core`: state, covariance, ``P = F P F' + Q`` and the one gated, Joseph-form, partial-update update;
- :mod:`fusion.process`: the IMU-driven mean propagation, ``F``, ``Q`` and the wind model;
- :mod:`fusion.imu`: the IMU samples summed between covariance predictions;
- :mod:`fusion.timeline`: the IMU FIFO, the measurement heap, the delayed fusion horizon, same-stamp order and the
  admission checks;
- :mod:`fusion.aid`: one module per aid source (measurement model + PX4-style life cycle and status record);
- :mod:`fusion.estimate`: the output :class:`NavEstimate`.

Bad input never reaches the state: a non-finite value, a wrong shape, a stamp out of order or a stale attitude is
rejected and the source's status says why; the filter carries on from the model.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from common.samples import AttitudeSample, GsoeStep, ImuSample
from fusion.aid import SOURCES, AidContext, AidSource
from fusion.aid.airspeed import REASON_LOW_AIRSPEED, REASON_WIND_RESET
from fusion.aid.aoa import REASON_AOA_RANGE
from fusion.aid.gnss import REASON_BAD_SIGMA, REASON_RESET_TO_MEAS
from fusion.aid.optical import (
    REASON_ANCHORED,
    REASON_BAD_FOCAL,
    REASON_BASE_FRAME,
    REASON_INVALID_MATCH,
    REASON_LOW_HEIGHT,
    REASON_STALE_CYCLE,
)
from fusion.config import EkfConfig
from fusion.core import COV_RESET_REL_TOL, FilterCore
from fusion.estimate import NavEstimate, make_estimate
from fusion.imu import ImuIntegrator
from fusion.process import (
    ImuIncrement,
    ProcessModel,
    R_nb_321,
    initial_covariance,
    initial_variances,
    propagate,
)
from fusion.state import S
from fusion.status import (
    REASON_ATT_STALE,
    REASON_BAD_SHAPE,
    REASON_BAD_TIME,
    REASON_BUFFER_FULL,
    REASON_COV_RESET,
    REASON_GATE,
    REASON_IMU_GAP,
    REASON_LATE,
    REASON_NO_ATTITUDE,
    REASON_NON_FINITE,
    REASON_NOT_INCREASING,
    REASON_NUMERIC,
    AidStatus,
    StatusRow,
)
from fusion.timeline import Timeline, is_int

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]

#: Aid sources with a status record, in logging order.
AID_SOURCES: tuple[str, ...] = ("imu", *(src.name for src in SOURCES))
#: The sources whose fusion keeps the output valid (``validity.aid_timeout_s``).
POSITION_AIDS = ("optical", "gnss_pos", "gnss_vel")

__all__ = [
    "AID_SOURCES", "COV_RESET_REL_TOL", "AidStatus", "ImuIncrement", "NavEkf", "NavEstimate", "R_nb_321", "propagate",
    "REASON_ANCHORED", "REASON_AOA_RANGE", "REASON_ATT_STALE", "REASON_BAD_FOCAL", "REASON_BAD_SHAPE",
    "REASON_BAD_SIGMA", "REASON_BAD_TIME", "REASON_BASE_FRAME", "REASON_BUFFER_FULL", "REASON_COV_RESET",
    "REASON_GATE", "REASON_IMU_GAP", "REASON_INVALID_MATCH", "REASON_LATE", "REASON_LOW_AIRSPEED",
    "REASON_LOW_HEIGHT", "REASON_NO_ATTITUDE", "REASON_NON_FINITE", "REASON_NOT_INCREASING", "REASON_NUMERIC",
    "REASON_RESET_TO_MEAS", "REASON_STALE_CYCLE", "REASON_WIND_RESET",
]


def _initial_values(t_us: Any, pos_ned_m: ArrayLike, vel_ned_m_s: ArrayLike, wind_ne_m_s: ArrayLike | None,
                    terrain_h_m: float) -> dict[str, Vec]:
    """The initial values as float arrays; ``ValueError`` naming the argument if one is not finite or misshapen."""
    if not is_int(t_us):
        raise ValueError(f"t_us: must be an integer (µs), got {t_us!r}")
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
    return arr


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
        at the first usable airspeed sample (:mod:`fusion.aid.airspeed`).
    terrain_h_m
        Height of the ground under the aircraft above the reference ground (m, up).
    aid_sources
        The aid sources (default :data:`fusion.aid.SOURCES`); another sensor is one more
        :class:`~fusion.aid.base.AidSource` here, pushed with :meth:`push`.

    The initial sigmas come from ``cfg.init_*``.  Raises ``ValueError`` naming the argument on non-finite or
    misshapen initial values.
    """

    def __init__(self, cfg: EkfConfig, *, t_us: int, pos_ned_m: ArrayLike, vel_ned_m_s: ArrayLike,
                 wind_ne_m_s: ArrayLike | None = None, terrain_h_m: float = 0.0,
                 aid_sources: Sequence[type[AidSource]] = SOURCES) -> None:
        arr = _initial_values(t_us, pos_ned_m, vel_ned_m_s, wind_ne_m_s, terrain_h_m)
        self.cfg = cfg
        x0 = np.zeros(S.dim)
        x0[S.pos_ned] = arr["pos_ned_m"]
        x0[S.vel_ned] = arr["vel_ned_m_s"]
        x0[S.wind_ne] = x0[S.wind_mean_ne] = arr["wind_ne_m_s"]
        x0[S.terrain_h] = arr["terrain_h_m"]
        x0[S.base_pos_ned] = arr["pos_ned_m"]
        init_var = initial_variances(cfg)
        self._core = FilterCore(x0, initial_covariance(cfg, init_var), init_var)
        self._process = ProcessModel(cfg)
        self._rows = {name: StatusRow(name) for name in ("imu", *(src.name for src in aid_sources))}
        self._imu = ImuIntegrator(cfg, self._core, self._process, self._rows["imu"], int(t_us))
        stamp_order = {kind: rank for src in aid_sources for kind, rank in src.events.items()}
        self._timeline = Timeline(cfg, self._imu, self._rows["imu"], self._dispatch, stamp_order)
        ctx = AidContext(cfg, self._core, self._process, self._imu, self._timeline, int(t_us), wind_ne_m_s is not None)
        self._sources: dict[str, AidSource] = {src.name: src(ctx, self._rows[src.name]) for src in aid_sources}
        self._handlers: dict[str, list[Callable[[int, Any], bool]]] = {}
        for source in self._sources.values():
            for kind in source.event_kinds():
                self._handlers.setdefault(kind, []).append(source.handler(kind))
            self._core.on_reset.append(source.states_reset)
        self._est: tuple[tuple[int, int], NavEstimate] | None = None   # estimate() per (core, IMU) version

    # ----------------------------------------------------------------------------------------------------------
    # public API
    @property
    def t_us(self) -> int:
        """Time of the filter state (the fusion horizon), µs."""
        self._timeline.process_due()
        return self._imu.t_x_us

    @property
    def x(self) -> Vec:
        """Copy of the state vector (layout :data:`fusion.state.S`)."""
        self._timeline.process_due()
        return self._core.x.copy()

    @property
    def P(self) -> Mat:
        """Copy of the state covariance."""
        self._timeline.process_due()
        return self._core.P.copy()

    @property
    def wind_turb_sigma_m_s(self) -> float:
        """The turbulence standard deviation the wind model uses now (m/s per axis; adapted in flight)."""
        self._timeline.process_due()
        return math.sqrt(self._process.turb_var)

    @property
    def covariance_predictions(self) -> int:
        """Number of covariance predictions so far (for the cost figures)."""
        self._timeline.process_due()
        return self._core.n_predictions

    def covariance(self, *names: str) -> Mat:
        """Covariance block of the named state fields (in that order)."""
        self._timeline.process_due()
        i = S.idx(*names)
        return self._core.P[np.ix_(i, i)].copy()

    def status(self) -> dict[str, AidStatus]:
        """Per aid source (:data:`AID_SOURCES` with the default sources) the status after its last processed sample."""
        self._timeline.process_due()
        return {name: row.snapshot() for name, row in self._rows.items()}

    def take_states(self, names: Sequence[str], x: ArrayLike, P: ArrayLike) -> None:
        """Set the named state fields (:data:`fusion.state.S`) to their values in another state ``x`` with
        covariance ``P`` of the same layout (e.g. an earlier :attr:`x` and :attr:`P`), uncorrelated with the rest:
        what a restart carries over from the last healthy filter (:mod:`pipeline.guard`).  ``ValueError`` when
        ``x`` or ``P`` is misshapen or not finite."""
        xa, Pa = np.asarray(x, dtype=float), np.asarray(P, dtype=float)
        if xa.shape != (S.dim,) or Pa.shape != (S.dim, S.dim) or not (np.all(np.isfinite(xa))
                                                                      and np.all(np.isfinite(Pa))):
            raise ValueError(f"x, P: must be finite of shapes ({S.dim},) and ({S.dim}, {S.dim})")
        self._timeline.process_due()
        idx = S.idx(*names)
        self._core.reset_states(idx, xa[idx], Pa[np.ix_(idx, idx)])

    def predict(self, imu: ImuSample, att: AttitudeSample) -> None:
        """Push one IMU sample (specific force m/s^2 and body rates rad/s, FRD, at ``imu.t_us``) with the AHRS
        attitude (3-2-1 Euler, rad) valid within ``att_max_age_s`` of it.  IMU stamps must increase.  The sample
        drives the prediction of the interval that ends at its stamp (its rates only through the AHRS delay)."""
        self._timeline.push_imu(imu, att)

    def fuse_airspeed(self, t_us: int, tas_m_s: float) -> None:
        """Push a true airspeed sample (m/s) measured at ``t_us``; the sideslip pseudo-measurement (side-force
        sideslip, or zero) is fused with it (``cfg.sideslip.enabled``), and so is the lift-model angle of attack
        (``cfg.aoa.enabled``)."""
        self.push("airspeed", t_us, tas_m_s)

    def fuse_baro(self, t_us: int, alt_m: float) -> None:
        """Push a barometric altitude (m above the reference ground, up) measured at ``t_us``."""
        self.push("baro", t_us, alt_m)

    def fuse_gnss(self, t_us: int, pos_ned_m: ArrayLike | None, vel_ned_m_s: ArrayLike | None, *,
                  pos_sigma_ne_m: float | None = None, pos_sigma_d_m: float | None = None,
                  vel_sigma_ne_m_s: float | None = None, vel_sigma_d_m_s: float | None = None) -> None:
        """Push a GNSS fix at ``t_us``: position in the local NED frame (m; 3 values, or 2 for north/east only) and/or
        ground velocity (m/s; 3 values NED, or 2 for north/east), either may be ``None``.  The optional one-sigma
        accuracies (the receiver's hacc/vacc/sacc) replace the configured ones."""
        self.push("gnss_pos", t_us, (pos_ned_m, (pos_sigma_ne_m, pos_sigma_d_m)))
        self.push("gnss_vel", t_us, (vel_ned_m_s, (vel_sigma_ne_m_s, vel_sigma_d_m_s)))

    def fuse_optical(self, step: GsoeStep) -> None:
        """Push one optical step (a :class:`GsoeStep` fused at its exposure time ``step.t_us``); push every
        step in order, including each cycle's base step (``new_cycle``) so the clone is taken at the base time."""
        self.push("optical", getattr(step, "t_us", None), step)

    def push(self, source: str, t_us: Any, sample: Any) -> None:
        """Push a sample of the registered aid source ``source`` (:data:`fusion.aid.SOURCES`) stamped ``t_us``: it is
        checked (the source's status says why it was refused) and fused when the horizon reaches its stamp."""
        src = self._sources[source]
        accepted = src.accept(t_us, sample)
        if accepted is None:
            return
        payload, value = accepted
        if self._timeline.admit(src.row, t_us, value):
            src.push(t_us, payload)

    def estimate(self) -> NavEstimate:
        """The current estimate (at :attr:`t_us`), with one-sigma uncertainties and the validity flag.  Computed once
        per filter state: until the state changes, calls return the same object (its arrays are read-only)."""
        if self._timeline.imu_waiting:
            self._timeline.process_due()
        key = (self._core.version, self._imu.version)
        if self._est is None or self._est[0] != key:
            core, imu = self._core, self._imu
            last = max((self._rows[s].t_last_fuse_us for s in POSITION_AIDS if s in self._rows), default=-1)
            est = make_estimate(self.cfg, core.x, core.P, imu.t_x_us, imu.output_attitude(), imu.rates_held,
                                self._process.turb_var, has_att=imu.att is not None, last_aid_fuse_us=last)
            self._est = (key, est)
        return self._est[1]

    # ----------------------------------------------------------------------------------------------------------
    def _dispatch(self, t_us: int, kind: str, payload: Any) -> None:
        """Predict to the stamp ``t_us`` of a due event and hand it to the sources that process it, in order (a
        source may end the event for the rest, e.g. the airspeed's wind reset)."""
        self._imu.predict_to(t_us)
        for handle in self._handlers[kind]:
            if not handle(t_us, payload):
                return
