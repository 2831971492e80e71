"""The simulator's true state at one instant (frames and units as in :mod:`gsoe`)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray


class TruthState(NamedTuple):
    """Truth at ``t_s`` (simulation time, seconds from start).

    ``pos_ned_m`` is relative to the mission's reference point on the ground (so ``-pos_ned_m[2]`` is the height
    above the reference ground, equal to ``height_agl_m`` over flat terrain).  ``accel_b_m_s2`` is the specific
    force an ideal accelerometer at the CG measures (FRD).  ``wind_ned_m_s`` is the total wind (steady + shear +
    turbulence + gusts) the aircraft flies in, ``wind_steady_ned_m_s`` the steady part at its height; both are
    the velocity of the air (the direction the wind blows *to*).

    An immutable named tuple (build it by keyword; ``_replace`` gives a changed copy) rather than a frozen
    dataclass: the dynamics builds one every step (240 per simulated second), and a frozen dataclass sets each of
    its 14 fields through ``object.__setattr__``, which cost about 3 us per step (7 us with the caches cold in a
    full ``gsoe sim`` run) against 0.4 us for :meth:`_make`.  The arrays are not to be written to.
    """

    t_s: float
    pos_ned_m: NDArray[np.float64]
    vel_ned_m_s: NDArray[np.float64]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rates_b_rad_s: NDArray[np.float64]
    accel_b_m_s2: NDArray[np.float64]
    tas_m_s: float
    alpha_rad: float
    beta_rad: float
    wind_ned_m_s: NDArray[np.float64]
    wind_steady_ned_m_s: NDArray[np.float64]
    height_agl_m: float

    @property
    def t_us(self) -> int:
        return int(round(self.t_s * 1e6))
