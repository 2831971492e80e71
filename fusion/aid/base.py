"""What every aid source and every measurement model has (STYLE sections 4 and 5).

A measurement model is built per measurement with its context (the camera's focal length, the AHRS attitude, the
noise of this sample) and is then a pure function of the state: ``evaluate(x)`` (``z_hat``, shape ``(m,)``),
``jacobian(x)`` (``H``, ``(m, n)``, analytic; tests check it against finite differences), ``covariance(x)``
(``R``, ``(m, m)``) and ``linearise(x)`` (all three at once, in the form the filter core's one update is cheapest
with: :class:`~fusion.core.Linearised`).  ``x`` is laid out by :data:`fusion.state.S`.  The models built per sample
(airspeed, sideslip, angle of attack, optical) are slotted dataclasses that are never changed once built, but not
frozen: a frozen dataclass's constructor costs three times as much, and they are built about 120 times a second.

An aid source has PX4 EKF2's life cycle: the filter hands it each due sample (:meth:`AidSource.control`), which
either skips it with a reason in its status record or builds the model and fuses it through the core's one update
(:meth:`AidSource.fuse`); :meth:`AidSource.reset` resets the states it observes to its measurement and
:meth:`AidSource.stop` drops what it remembers between samples.  Before a sample enters the timeline
:meth:`AidSource.accept` checks it and :meth:`AidSource.push` queues it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np
from numpy.typing import NDArray

from fusion.config import EkfConfig
from fusion.core import FilterCore, Linearised
from fusion.imu import ImuIntegrator
from fusion.process import ProcessModel
from fusion.state import S
from fusion.status import StatusRow

if TYPE_CHECKING:
    from fusion.timeline import Timeline

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]


class MeasurementModel(Protocol):
    """What the filter needs from a measurement model (all of one signature: the state)."""

    def evaluate(self, x: Vec) -> Vec: ...

    def jacobian(self, x: Vec) -> Mat: ...

    def covariance(self, x: Vec) -> Mat: ...

    def linearise(self, x: Vec) -> Linearised: ...


class ModelBase:
    """``evaluate``, ``jacobian`` and ``covariance`` from :meth:`linearise` (models override what they do faster)."""

    __slots__ = ()

    def linearise(self, x: Vec) -> Linearised:
        raise NotImplementedError

    def evaluate(self, x: Vec) -> Vec:
        return np.array(self.linearise(x).z_hat)

    def predict(self, x: Vec) -> Vec:
        """:meth:`evaluate` under its former name (kept for callers outside :mod:`fusion`)."""
        return self.evaluate(x)

    def jacobian(self, x: Vec) -> Mat:
        lin = self.linearise(x)
        if lin.H is None:
            H = np.zeros((len(lin.r), S.dim))
            H[np.arange(len(lin.r)), list(lin.idx or ())] = 1.0
            return H
        return np.atleast_2d(lin.H).copy()

    def covariance(self, x: Vec) -> Mat:
        return np.diag(np.asarray(self.linearise(x).r, dtype=float))


@dataclass(frozen=True)
class AidContext:
    """What the sources share: the config, the core, the process model (turbulence level), the IMU integrator
    (attitude, low-passed specific forces), the timeline, the start time and whether the wind was given."""

    cfg: EkfConfig
    core: FilterCore
    process: ProcessModel
    imu: ImuIntegrator
    timeline: Timeline
    t0_us: int
    wind_given: bool


class AidSource:
    """One aid source (module docstring).  ``name``: its status record; ``events``: the timeline event kinds it
    owns with their same-stamp rank (after the IMU's 0); ``listens``: the event kinds it processes (its own by
    default; the sideslip and the angle of attack ride on the airspeed's)."""

    name: ClassVar[str]
    events: ClassVar[Mapping[str, int]] = {}
    listens: ClassVar[tuple[str, ...]] = ()

    def __init__(self, ctx: AidContext, row: StatusRow) -> None:
        self.ctx, self.cfg, self.core, self.row = ctx, ctx.cfg, ctx.core, row

    @classmethod
    def event_kinds(cls) -> tuple[str, ...]:
        return cls.listens or tuple(cls.events)

    # input side --------------------------------------------------------------------------------------------
    def accept(self, t_us: Any, sample: Any) -> tuple[Any, Any] | None:
        """Check a sample before it enters the timeline: ``(payload, value whose finiteness the timeline checks)``,
        or ``None`` with the reason in the status record."""
        return sample, sample

    def push(self, t_us: int, payload: Any) -> None:
        """Queue an admitted sample."""
        self.ctx.timeline.push(t_us, self.name, payload)

    # life cycle --------------------------------------------------------------------------------------------
    def handler(self, kind: str) -> Callable[[int, Any], bool]:
        """What processes a due event of one of :meth:`event_kinds` (``(t_us, payload)``; returns whether the next
        sources of the event may use it): :meth:`control` unless the source has other events."""
        return self.control

    def control(self, t_us: int, sample: Any) -> bool:
        """Skip the sample with a reason, or fuse it; returns whether later sources of the same event go on."""
        raise NotImplementedError

    def fuse(self, t_us: int, z: Sequence[float] | Vec, model: MeasurementModel, gate_nis: float) -> bool:
        """The core's one update with this source's status record."""
        return self.core.update(self.row, t_us, z, model.linearise(self.core.x), gate_nis)

    def reset(self, t_us: int, sample: Any) -> None:
        """Reset the states this source observes to its measurement (sources without such a reset do nothing)."""

    def stop(self) -> None:
        """Forget what the source keeps between samples (sources that keep nothing do nothing)."""

    def states_reset(self, idx: NDArray[np.intp]) -> None:
        """The core reset the states ``idx`` (covariance or values); sources holding derived state react."""
