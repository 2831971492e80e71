"""Barometric altitude: the model ``-pos_d + baro_bias`` and its aid source."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from fusion.aid.base import AidSource, Mat, ModelBase, Vec
from fusion.config import EkfConfig
from fusion.core import Linearised
from fusion.state import S

_PD, _BB = S.pos_d.start, S.baro_bias.start
_H_BARO = np.zeros(S.dim)
_H_BARO[_PD], _H_BARO[_BB] = -1.0, 1.0
_H_BARO.flags.writeable = False


@dataclass(frozen=True, slots=True)
class BaroAltitude(ModelBase):
    """Barometric altitude above the reference ground (m): ``-pos_d + baro_bias``; ``var_m2`` its noise variance."""

    var_m2: float

    @classmethod
    def from_config(cls, cfg: EkfConfig) -> BaroAltitude:
        return cls(cfg.baro.sigma_m**2)

    def linearise(self, x: Vec) -> Linearised:
        return Linearised((x.item(_BB) - x.item(_PD),), _H_BARO, None, (self.var_m2,))

    def jacobian(self, x: Vec) -> Mat:
        return _H_BARO[None, :].copy()


class BaroAid(AidSource):
    """Fuses every baro sample (gate ``gates.baro_nis``)."""

    name = "baro"
    events: ClassVar[dict[str, int]] = {"baro": 3}

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self._model = BaroAltitude.from_config(self.cfg)

    def push(self, t_us: int, payload: Any) -> None:
        self.ctx.timeline.push(t_us, self.name, float(payload))

    def control(self, t_us: int, sample: float) -> bool:
        self.fuse(t_us, (sample,), self._model, self.cfg.gates.baro_nis)
        return True
