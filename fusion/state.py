"""The EKF's state vector: declared once from ``(name, size)`` pairs, indices derived by name (STYLE section 3).

Fusion code never writes ``x[6:8]``; it writes ``x[S.wind_ne]`` and ``P[S.vel_ne, S.vel_ne]``.  Contiguous runs of
fields can be named as groups (``S.pos_ned`` = ``pos_ne`` followed by ``pos_d``).

The state (frames and units as in :mod:`gsoe`: NED ``n``, FRD ``b``, SI, radians)
---------------------------------------------------------------------------------
=================  ====  =====  ============================================================================
name               size  unit   meaning
=================  ====  =====  ============================================================================
``pos_ne``         2     m      horizontal position, north/east of the local NED origin (the mission's
                                reference point, or wherever the caller anchors NED, e.g. the last GNSS fix)
``pos_d``          1     m      down position relative to the reference ground (``-pos_d`` = height above it)
``vel_ne``         2     m/s    ground velocity, north/east
``vel_d``          1     m/s    ground velocity, down
``wind_ne``        2     m/s    horizontal wind: the velocity of the air (the direction it blows *to*), the
                                total wind the aircraft flies in (mean + turbulence)
``wind_mean_ne``   2     m/s    the slowly varying mean of that wind, to which ``wind_ne`` relaxes
``wind_d``         1     m/s    vertical wind (down positive): turbulence without a mean, seen by the sideslip
                                in banked flight (and by the 3-D airspeed)
``accel_bias_b``   3     m/s^2  accelerometer bias, body FRD (absorbs AHRS roll/pitch errors too: a constant
                                tilt error makes a body-fixed specific-force error)
``yaw_bias``       1     rad    AHRS heading error: ``yaw_ahrs - yaw_true``
``opt_rot``        1     rad    heading error of the optical frame: the stabilised image of a cycle points along
                                ``base_yaw_rad - yaw_bias + opt_rot`` (clockwise positive)
``baro_bias``      1     m      barometric altitude minus true height above the reference ground
``terrain_h``      1     m      height of the ground under the aircraft above the reference ground (up)
``tas_scale``      1     -      airspeed scale error: ``tas_measured = (1 + tas_scale) * tas_true``
``att_delay``      1     s      time misalignment of the AHRS attitude: a sample stamped ``t`` describes the
                                body at ``t - att_delay`` (the AHRS latency not compensated upstream)
``side_force_ofs`` 1     m/s^2  lateral specific force at zero sideslip, beyond ``accel_bias_b``'s y: what the
                                side-force sideslip subtracts besides that bias (see below)
``aoa_ofs``        1     rad    what the lift-model angle of attack reads beyond the true one, besides
                                ``accel_bias_b``'s z share: AHRS pitch error, lift-model offset (see below)
``base_pos_ne``    2     m      stochastic clone of ``pos_ne`` at the optical cycle's base snapshot
``base_pos_d``     1     m      stochastic clone of ``pos_d`` at the base snapshot
=================  ====  =====  ============================================================================

Why this set
    * Position, ground velocity (3-D) and wind (N, E) are the outputs.  The vertical channel is modelled because
      the true airspeed is a 3-D quantity (climbs and descents change ``|v_ground - wind|``) and because the
      optical measurement's ground sample distance depends on the height at the base snapshot.
    * Wind is horizontal only: the vertical wind is not observable from airspeed + baro and is small.  It is the
      total wind the aircraft flies in (steady + turbulence), since that is what the airspeed and ground velocity
      difference measures and what the drift and the ATA depend on.
    * ``wind_mean_ne``: the total wind is modelled as a slowly walking mean plus first-order Gauss-Markov turbulence
      (``wind_ne - wind_mean_ne``, standard deviation ``wind.turb_sigma_m_s``, correlation time
      ``wind.turb_corr_time_s``; :mod:`fusion.config`).  A pure random walk on the total wind (the earlier model)
      lets the wind follow a pitot scale error, which turns with the heading, so the scale was never observable in
      turbulence (in the Monte Carlo campaign the estimated scale walked +2 % in 300 s whatever the true one);
      turbulence that returns to a mean cannot follow the heading for long, so loops of turns show the scale.
    * ``wind_d``: the air velocity is 3-D, ``[v_ne - wind_ne, v_d - wind_d]``.  In level flight the vertical wind
      moves neither the airspeed (to first order) nor the sideslip, but in a bank of ``phi`` the body y axis takes
      ``sin(phi)`` of the vertical air velocity, so a vertical gust reads as sideslip: with the vertical wind taken
      as 0, the side-force sideslip puts ``tan(phi) wind_d`` into the cross-heading wind.  In the Monte Carlo
      campaign's turbulence (vertical gusts of 0.6-0.9 m/s rms) the sideslip predicted without it was off by
      0.55-0.95 deg rms (0.2-0.33 m/s of cross-heading wind), mostly at the 5-30 s periods of the turns, where the
      side-force sideslip itself is within 0.1 deg.  First-order Gauss-Markov with no mean: standard deviation
      ``wind.vertical_sigma_ratio`` times the adapted horizontal turbulence sigma (Dryden below 1000 ft: 0.6-1.0),
      correlation time ``wind.vertical_corr_time_s`` (Dryden ``L_w / V`` = height / airspeed).  The lift-model angle of
      attack (:class:`fusion.measurements.LiftAngleOfAttack`) observes it at any bank (it fixes the body-frame air
      velocity's third component); without it, only in banked flight, where the sideslip's innovation is shared
      between it and the horizontal wind by their covariances (correlation with the truth in banks 0.61 without,
      0.93 with; :class:`fusion.config.EkfConfig`).
    * ``accel_bias_b`` (3): the IMU drives the prediction; a MEMS bias of 0.05 m/s^2 integrates to 90 m in 60 s,
      and an AHRS tilt error appears as a body-fixed specific-force error of ``g * tilt``.  All three axes, since the
      vertical one is observable from baro/GNSS and costs little.
    * ``yaw_bias``: the AHRS (magnetometer) heading is typically 1 deg off.  It rotates the optical displacement
      (measured in the base-heading frame), the synthetic-sideslip direction and the IMU's horizontal specific
      force; a 1 deg error alone is a 1.7 % cross-track dead-reckoning error.  It is observable while GNSS (or
      optical + GNSS) is available and is then held through an outage.
    * ``opt_rot``: the optical estimator builds each cycle's stabilised frame from its own attitude (base attitude
      and gyro-integrated rotation, with its own gyro-bias filter), so the frame's heading error is not the AHRS's:
      in the simulator the optical displacement is rotated by +2.3 deg at start-up, decaying to +0.1 deg as that
      gyro-bias filter converges.  Folded into ``yaw_bias`` it drove the AHRS heading correction 2.4 deg the wrong
      way; as its own state, GNSS + IMU + airspeed/sideslip fix ``yaw_bias`` and optical against GNSS fixes
      ``opt_rot``, and both are held through an outage.  (Optical *scale* errors are absorbed by ``terrain_h``,
      which only the optical model uses.  An additive height matches a focal-length error at one height only: in
      the Monte Carlo campaign, with a -2.9 % focal error and heights of 88-163 m, the filter's height ratio went
      from -2.3 % to -5.3 % as the aircraft climbed and sank.  A multiplicative optical-scale state was measured
      (32 recorded runs, EKF-only replay): NEES in bounds 0.870 -> 0.871, dead reckoning median 0.232 -> 0.229 %;
      better where the focal error dominates (0.77 -> 0.97), worse where the fisheye's off-nadir stretch in turns
      makes the scale it learns overshoot (+6.4 % for a +3 % error: 0.68 -> 0.61), and 2-7 points lower over
      low-texture ground; not adopted.)
    * ``baro_bias`` and ``terrain_h``: the optical scale is ``height_agl / focal``, so a height error is a velocity
      scale error.  Baro altitude drifts with the weather (``baro_bias``); the ground under the aircraft need not be
      at the reference height (``terrain_h``).  GNSS height separates the two from the true height; the optical
      scale against GNSS velocity separates the terrain from the aircraft's height.
    * ``tas_scale``: pitot calibration errors of a few percent bias the wind along the heading; the scale is
      observable in turns while the ground velocity is known (GNSS or optical).
    * ``att_delay``: an AHRS whose attitude lags by ``tau`` rotates the specific force late: the velocity direction
      lags the turn by ``turn rate * tau`` (a roll-in at 45 deg of bank with a 0.1 s lag is a 0.7 m/s lateral
      error that no white acceleration noise describes, since it is the same every turn).  The true attitude is
      ``R_ahrs (I + [omega x] tau)`` (body rates ``omega`` from the IMU's gyro), so the prediction carries the
      term ``tau R_ahrs (omega x f)``, linear in ``tau``; turns against GNSS, optical and airspeed data make it
      observable.  It is a constant of the installation (a slow random walk lets it follow a compensation that
      changes upstream).  The measurement models take the attitude as given (the sideslip's heading lag, ``turn
      rate * tau``, is well inside its sigma; the optical frames carry the optical estimator's own attitude).
    * ``side_force_ofs``: the side-force sideslip (:class:`fusion.measurements.SyntheticSideslip`) reads
      ``beta = k (f_y - b_y)`` from the accelerometer's lateral channel less its bias.  But ``accel_bias_b`` is the
      bias *the prediction* needs, and that includes the AHRS tilt error: a roll error ``d_phi`` rotates gravity into
      the filter's body y axis, and the bias state takes ``-g d_phi`` of it, which the accelerometer never read.  In
      the Monte Carlo campaign this made the measured sideslip wrong by about the AHRS roll error (a 1.34 deg roll
      error: +1.45 deg of sideslip, a -0.53 m/s cross-heading wind bias).  The offset is what the sideslip must
      subtract besides ``b_y`` (the tilt share, and on a real airframe any side force at zero sideslip: propeller
      slipstream, an accelerometer mounted off the aircraft's axis), a constant of the installation; observable
      while the wind is known (GNSS or optical velocity, with airspeed, in turns).  Unused (and unobservable) with the
      zero-sideslip pseudo-measurement.
    * ``aoa_ofs``: the lift-model angle of attack ``-k (f_z - b_z) - C_L0 / C_Lalpha`` is off by whatever the lift
      model gets wrong at a constant (C_L0, the wing's incidence) and the filter predicts it from the AHRS attitude,
      so a pitch error fixed in the body shifts the prediction by that error.  The offset holds both, a constant
      of the installation; observable because the vertical wind it competes with has no mean.  A pitch error
      about the heading's lateral axis moves the angle of attack by ``cos(phi)`` and the sideslip by ``sin(phi)``
      of it, as a steady vertical wind would, so part of such an error stays in ``wind_d``.
    * ``base_pos_ne``/``base_pos_d``: the optical measurement is a position *change* since the base snapshot
      (stochastic cloning): at the snapshot the position and its covariance rows are copied into the clone, which
      is then constant (identity transition, no process noise) while the current position moves on.  The
      displacement ``pos - base_pos`` keeps the correlation a per-frame velocity would throw away.
    * Not estimated: attitude (taken from the AHRS, its noise is in the process noise), gyro bias (attitude is not
      a state), a separate vertical wind and the terrain slope (flat ground, as the optical estimator assumes).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray


class StateLayout:
    """Named, contiguous fields of a state vector.

    Parameters
    ----------
    fields
        ``(name, size)`` pairs in vector order.
    groups
        ``name -> (field, field, ...)``: consecutive fields exposed as one slice.

    ``layout.<name>`` is the field's (or group's) ``slice``; :meth:`idx` gives integer indices of several fields in the
    order asked (for non-contiguous selections).
    """

    def __init__(self, fields: Sequence[tuple[str, int]], groups: Mapping[str, Sequence[str]] | None = None) -> None:
        slices: dict[str, slice] = {}
        start = 0
        for name, size in fields:
            if not name.isidentifier() or name in slices:
                raise ValueError(f"state field {name!r}: not a fresh identifier")
            if size < 1:
                raise ValueError(f"state field {name!r}: size must be >= 1, got {size}")
            slices[name] = slice(start, start + size)
            start += size
        self._fields = tuple(name for name, _ in fields)
        for gname, members in (groups or {}).items():
            if gname in slices:
                raise ValueError(f"state group {gname!r}: name already used")
            parts = [slices[m] for m in members]
            for a, b in zip(parts, parts[1:], strict=False):
                if a.stop != b.start:
                    raise ValueError(f"state group {gname!r}: fields {list(members)} are not contiguous")
            slices[gname] = slice(parts[0].start, parts[-1].stop)
        self._slices = slices
        self.dim = start
        for name, sl in slices.items():        # plain attributes: ``S.wind_ne`` is a dict lookup, not a call
            setattr(self, name, sl)

    def __getattr__(self, name: str) -> slice:
        # only reached for names that are not fields
        raise AttributeError(f"state has no field {name!r} (fields: {', '.join(self.__dict__.get('_fields', ()))})")

    @property
    def fields(self) -> tuple[str, ...]:
        return self._fields

    def size(self, name: str) -> int:
        s = getattr(self, name)
        return int(s.stop - s.start)

    def idx(self, *names: str) -> NDArray[np.intp]:
        """Integer indices of the named fields, concatenated in the order given."""
        return np.concatenate([np.arange(getattr(self, n).start, getattr(self, n).stop) for n in names])

    def describe(self) -> dict[str, tuple[int, int]]:
        """``name -> (start, stop)`` of every field (for logs)."""
        return {n: (self._slices[n].start, self._slices[n].stop) for n in self._fields}


#: The navigation filter's state (see the module docstring for the meaning and units of each field).
S = StateLayout(
    [
        ("pos_ne", 2),
        ("pos_d", 1),
        ("vel_ne", 2),
        ("vel_d", 1),
        ("wind_ne", 2),
        ("wind_mean_ne", 2),
        ("wind_d", 1),
        ("accel_bias_b", 3),
        ("yaw_bias", 1),
        ("opt_rot", 1),
        ("baro_bias", 1),
        ("terrain_h", 1),
        ("tas_scale", 1),
        ("att_delay", 1),
        ("side_force_ofs", 1),
        ("aoa_ofs", 1),
        ("base_pos_ne", 2),
        ("base_pos_d", 1),
    ],
    groups={
        "pos_ned": ("pos_ne", "pos_d"),
        "vel_ned": ("vel_ne", "vel_d"),
        "base_pos_ned": ("base_pos_ne", "base_pos_d"),
    },
)
