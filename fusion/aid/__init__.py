"""The aid sources, one module each (measurement model + source, PX4 EKF2's life cycle: :mod:`fusion.aid.base`).

A new sensor is one new module here (its model and its :class:`~fusion.aid.base.AidSource`) and one entry in
:data:`SOURCES`; it is pushed with ``NavEkf.push(name, t_us, sample)``.
"""

from __future__ import annotations

from fusion.aid.airspeed import AirspeedAid
from fusion.aid.aoa import AoaAid
from fusion.aid.baro import BaroAid
from fusion.aid.base import AidContext, AidSource
from fusion.aid.gnss import GnssPositionAid, GnssVelocityAid
from fusion.aid.optical import OpticalAid
from fusion.aid.sideslip import SideslipAid

#: The registered sources, in status (logging) order; sources riding on one event run in this order too.
SOURCES: tuple[type[AidSource], ...] = (OpticalAid, AirspeedAid, SideslipAid, AoaAid, BaroAid, GnssPositionAid,
                                        GnssVelocityAid)

__all__ = ["SOURCES", "AidContext", "AidSource"]
