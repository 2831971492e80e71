"""The standard atmosphere and the one policy for the air temperature that makes an equivalent airspeed true.

An autopilot reports equivalent airspeed (ArduPilot's ``VFR_HUD.airspeed``, a log's ``ARSP``); the filter needs true
airspeed, ``TAS = EAS sqrt(rho0 / rho)``.  The air density takes the static pressure and an air temperature.  Every
reader (the live link, the log reader) takes that temperature the way ArduPilot's ``AP_Baro::get_EAS2TAS`` does, so
that the companion's TAS is the autopilot's:

- the *ground* temperature is the baro's own temperature at the lowest altitude seen, at most
  ``baro_temp_clamp_c`` (a board's baro reads its own warm board, often 30 K above the air);
- above the ground the ISA lapse rate, over the pressure altitude between the two pressures.

ArduPilot's clamp is :data:`ARDUPILOT_BARO_TEMP_CLAMP_C` from 4.0 on and :data:`ARDUPILOT_3_BARO_TEMP_CLAMP_C` before.
SI inside: Pa, K, m.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

P0_PA = 101325.0  #: ISA sea-level pressure
T0_K = 288.15  #: ISA sea-level temperature
LAPSE_K_M = 0.0065  #: ISA temperature lapse rate in the troposphere
R_AIR_J_KG_K = 287.053  #: specific gas constant of dry air
G0_M_S2 = 9.80665  #: standard gravity
RHO0_KG_M3 = P0_PA / (R_AIR_J_KG_K * T0_K)  #: ISA sea-level density (1.225)
KELVIN_AT_0_C = 273.15
_EXPONENT = G0_M_S2 / (R_AIR_J_KG_K * LAPSE_K_M)  # 5.2559: p/p0 = (T/T0)^_EXPONENT

#: ArduPilot 4.x: a baro's own temperature is taken as the air's up to this (AP_Baro INTERNAL_TEMPERATURE_CLAMP).
ARDUPILOT_BARO_TEMP_CLAMP_C = 35.0
#: ArduPilot 3.x (the ALFA logs of 2018): the same clamp was 25 degC.
ARDUPILOT_3_BARO_TEMP_CLAMP_C = 25.0


#: An ArduPilot firmware string as its logs and STATUSTEXT name it ("ArduPlane V3.8.2-dev (8178ab40)").
_ARDUPILOT_VERSION = re.compile(r"(?:\bArdu\w+|\bAPM:\w+) V(\d+)\.(\d+)")


def ardupilot_baro_temp_clamp_c(firmware: str) -> float | None:
    """The baro temperature clamp of the ArduPilot firmware named by ``firmware`` ("ArduPlane V4.5.1"): 35 degC from
    4.0 on, 25 degC before; ``None`` when the string names no ArduPilot version."""
    m = _ARDUPILOT_VERSION.search(firmware)
    if m is None:
        return None
    return ardupilot_major_baro_temp_clamp_c(int(m.group(1)))


def ardupilot_major_baro_temp_clamp_c(major: int) -> float:
    """The baro temperature clamp of ArduPilot major version ``major``: 35 degC from 4 on, 25 degC before."""
    return ARDUPILOT_BARO_TEMP_CLAMP_C if major >= 4 else ARDUPILOT_3_BARO_TEMP_CLAMP_C


def pressure_altitude_m(pressure_pa: ArrayLike) -> NDArray[np.float64]:
    """ISA pressure altitude (m) of a static pressure (troposphere)."""
    return T0_K / LAPSE_K_M * (1.0 - (np.asarray(pressure_pa, dtype=float) / P0_PA) ** (1.0 / _EXPONENT))


def isa_pressure_pa(alt_amsl_m: float) -> float:
    """ISA static pressure at an altitude (troposphere): the inverse of :func:`pressure_altitude_m`."""
    return P0_PA * (1.0 - LAPSE_K_M * alt_amsl_m / T0_K) ** _EXPONENT


def eas_to_tas_ratio(pressure_pa: ArrayLike, ground: tuple[float, float] | None = None) -> NDArray[np.float64]:
    """``sqrt(rho0 / rho)`` at a static pressure: with ``ground = (pressure_pa, temperature_k)`` that temperature at
    that pressure less the ISA lapse rate above it; with ``None`` the ISA atmosphere's temperature."""
    p = np.asarray(pressure_pa, dtype=float)
    if ground is None:
        temp_k = T0_K - LAPSE_K_M * pressure_altitude_m(p)
    else:
        temp_k = ground[1] - LAPSE_K_M * (pressure_altitude_m(p) - pressure_altitude_m(ground[0]))
    return np.sqrt(RHO0_KG_M3 / (p / (R_AIR_J_KG_K * temp_k)))


def baro_air_temperature_k(baro_temp_c: float, clamp_c: float) -> float:
    """The air temperature a baro's own temperature stands for: at most ``clamp_c`` (the board warms the baro)."""
    return min(baro_temp_c, clamp_c) + KELVIN_AT_0_C


@dataclass
class GroundAir:
    """The ground reference of a live stream: the (pressure, clamped baro temperature) at the lowest altitude seen.

    ``update`` takes each baro report; ``ratio`` gives ``sqrt(rho0 / rho)`` at a pressure (nan before a report);
    ``set_clamp`` changes the clamp once the autopilot's firmware is known, the reference taken again.
    """

    baro_temp_clamp_c: float = ARDUPILOT_BARO_TEMP_CLAMP_C
    pressure_pa: float = math.nan
    temperature_k: float = math.nan
    baro_temp_c: float = math.nan      #: the reference's own baro temperature, before the clamp

    def update(self, pressure_pa: float, baro_temp_c: float) -> None:
        if not (math.isfinite(pressure_pa) and pressure_pa > 0.0 and math.isfinite(baro_temp_c)):
            return
        if not math.isfinite(self.pressure_pa) or pressure_pa >= self.pressure_pa:
            self.pressure_pa = pressure_pa
            self.baro_temp_c = baro_temp_c
            self.temperature_k = baro_air_temperature_k(baro_temp_c, self.baro_temp_clamp_c)

    def set_clamp(self, clamp_c: float) -> None:
        self.baro_temp_clamp_c = clamp_c
        if math.isfinite(self.baro_temp_c):
            self.temperature_k = baro_air_temperature_k(self.baro_temp_c, clamp_c)

    def ratio(self, pressure_pa: float) -> float:
        if not math.isfinite(self.pressure_pa):
            return math.nan
        return float(eas_to_tas_ratio(pressure_pa, (self.pressure_pa, self.temperature_k)))
