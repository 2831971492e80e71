"""The measurement models of the navigation EKF, one small class each (STYLE section 4), gathered from their aid
source modules (:mod:`fusion.aid`).

Every model is built per measurement with its context (the camera's focal length, the AHRS attitude, this sample's
noise) and has ``evaluate(x)`` (``z_hat``, shape ``(m,)``), ``jacobian(x)`` (analytic ``H``, ``(m, n)``),
``covariance(x)`` (``R``, ``(m, m)``) and ``linearise(x)`` (all three in the form the filter core's update takes,
:class:`~fusion.core.Linearised`): :class:`~fusion.aid.base.MeasurementModel`.  ``x`` is laid out by
:data:`fusion.state.S`; frames and units as in :mod:`gsoe` (NED, FRD, SI, radians).  The tests check every
``jacobian`` against finite differences of ``evaluate``.

Heading: the state's ``yaw_bias`` is ``yaw_ahrs - yaw_true``, so a heading reported by the AHRS (or a
:class:`GsoeStep`'s ``base_yaw_rad``, which comes from it) is corrected as ``yaw_true = yaw - yaw_bias``.
"""

from __future__ import annotations

from fusion.aid.air import MIN_AIR_SPEED_M_S
from fusion.aid.airspeed import TrueAirspeed
from fusion.aid.aoa import LiftAngleOfAttack
from fusion.aid.baro import BaroAltitude
from fusion.aid.base import MeasurementModel
from fusion.aid.gnss import GnssPosition, GnssVelocity
from fusion.aid.optical import OpticalDisplacement
from fusion.aid.sideslip import SyntheticSideslip
from fusion.core import Linearised

__all__ = [
    "MIN_AIR_SPEED_M_S", "BaroAltitude", "GnssPosition", "GnssVelocity", "LiftAngleOfAttack", "Linearised",
    "MeasurementModel", "OpticalDisplacement", "SyntheticSideslip", "TrueAirspeed",
]
