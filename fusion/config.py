"""What the navigation EKF assumes: process noise, wind model, initial sigmas, airframe, one section per aid source,
gates, timing and validity of the output.

Built from the ``[ekf]`` table of the configuration file with :func:`ekf_config_from_raw`, one nested table per
section (``[ekf.airspeed]``); every field is validated and a bad one raises :class:`common.config.ConfigError`
naming ``ekf.<section>.<field>``.  ``[ekf.profiles.<name>]`` tables hold named sets of changes on top of ``[ekf]``
(e.g. ``telemetry_replay``).  The *true* sensor errors of a simulation live in the scenario (``sim``), not here
(STYLE section 8).  How the defaults were chosen, with the figures and the commands that reproduce them:
``docs/ekf-tuning.md``.

Units are in the names.  Noise densities are root power spectral densities: ``*_per_rt_hz`` for white noise on a
rate and ``*_per_rt_s`` for random walks (the one-sigma change after one second).  Angles are degrees here (an
edge); code reads the ``*_rad`` properties.  Gates are thresholds on the normalised innovation squared (NIS),
chi-square quantiles of the measurement's dimension: 10.83, 13.82 and 16.27 are the 99.9 % points for 1, 2 and 3
degrees of freedom.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any

from common.config import ConfigError, In, Radians, Validated, build, require


@dataclass(frozen=True)
class ProcessNoise(Validated):
    """What drives the non-wind states between measurements (the wind has its own section)."""

    accel_noise_m_s2_per_rt_hz: Annotated[float, In(
        1e-4, 10.0, doc="white acceleration per NED axis: IMU, vibration, AHRS x g ((m/s^2)/rt Hz)")] = 0.05
    accel_bias_rw_m_s2_per_rt_s: Annotated[float, In(0.0, 1.0, doc="accelerometer bias walk (m/s^2 after 1 s)")] = 1e-3
    yaw_bias_rw_deg_per_rt_s: Annotated[float, In(0.0, 10.0, doc="AHRS heading error walk (deg after 1 s)")] = 0.002
    opt_rot_rw_deg_per_rt_s: Annotated[float, In(
        0.0, 10.0, doc="optical frame heading error walk, its gyro-bias filter (deg)")] = 0.05
    baro_bias_rw_m_per_rt_s: Annotated[float, In(0.0, 10.0, doc="baro bias walk, weather (m after 1 s)")] = 0.03
    terrain_rw_m_per_rt_s: Annotated[float, In(
        0.0, 100.0, doc="ground height walk under the aircraft, flat ground (m)")] = 0.02
    tas_scale_rw_per_rt_s: Annotated[float, In(0.0, 0.1, doc="pitot scale error walk (fraction after 1 s)")] = 0.0
    att_delay_rw_s_per_rt_s: Annotated[float, In(
        0.0, 0.1, doc="AHRS latency walk, an installation constant (s after 1 s)")] = 1e-3
    side_force_ofs_rw_m_s2_per_rt_s: Annotated[float, In(
        0.0, 1.0, doc="side-force sideslip offset walk (m/s^2 after 1 s)")] = 1e-3
    aoa_ofs_rw_deg_per_rt_s: Annotated[float, In(
        0.0, 1.0, doc="lift-model angle-of-attack offset walk (deg after 1 s)")] = 0.005

    yaw_bias_rw_rad_per_rt_s = Radians("yaw_bias_rw_deg_per_rt_s")
    opt_rot_rw_rad_per_rt_s = Radians("opt_rot_rw_deg_per_rt_s")
    aoa_ofs_rw_rad_per_rt_s = Radians("aoa_ofs_rw_deg_per_rt_s")


@dataclass(frozen=True)
class WindModel(Validated):
    """Total wind = a walking mean + first-order Gauss-Markov turbulence whose level adapts in flight; the vertical
    wind is turbulence of a fixed ratio of that level (:mod:`fusion.process`, :mod:`fusion.state`)."""

    mean_rw_m_s_per_rt_s: Annotated[float, In(0.0, 10.0, doc="mean wind walk: weather, shear (m/s after 1 s)")] = 0.015
    turb_sigma_m_s: Annotated[float, In(1e-3, 20.0, doc="turbulence per axis, initial level (m/s; 0.001: off)")] = 1.0
    turb_corr_time_s: Annotated[float, In(0.1, 3600.0, doc="turbulence correlation time, Dryden L/V (s)")] = 10.0
    turb_adapt_time_s: Annotated[float, In(
        0.0, 3600.0, doc="averaging time of the in-flight turbulence level (s; 0: fixed)")] = 60.0
    turb_adapt_var_weight: Annotated[float, In(
        0.0, 1.0, doc="share of the turbulence estimate's own variance in it (0-1)")] = 0.5
    turb_sigma_min_m_s: Annotated[float, In(1e-3, 20.0, doc="lower bound of the adapted turbulence (m/s)")] = 0.2
    turb_sigma_max_m_s: Annotated[float, In(1e-3, 20.0, doc="upper bound of the adapted turbulence (m/s)")] = 5.0
    vertical_sigma_ratio: Annotated[float, In(
        0.0, 3.0, doc="vertical / horizontal turbulence sigma (-; 0: no vertical wind)")] = 0.8
    vertical_corr_time_s: Annotated[float, In(
        0.1, 3600.0, doc="vertical turbulence correlation time, Dryden L_w/V (s)")] = 5.0

    def __post_init__(self) -> None:
        super().__post_init__()
        require(self.turb_sigma_min_m_s <= self.turb_sigma_m_s <= self.turb_sigma_max_m_s, "turb_sigma_m_s",
                f"must lie in [turb_sigma_min_m_s, turb_sigma_max_m_s] = [{self.turb_sigma_min_m_s}, "
                f"{self.turb_sigma_max_m_s}], got {self.turb_sigma_m_s}")


@dataclass(frozen=True)
class InitialSigmas(Validated):
    """One-sigma uncertainty of each state at start; also what a covariance reset restores."""

    pos_ne_sigma_m: Annotated[float, In(1e-3, 1e5, doc="horizontal position (m)")] = 10.0
    pos_d_sigma_m: Annotated[float, In(1e-3, 1e4, doc="down position (m)")] = 5.0
    vel_ne_sigma_m_s: Annotated[float, In(1e-3, 100.0, doc="horizontal ground velocity (m/s)")] = 5.0
    vel_d_sigma_m_s: Annotated[float, In(1e-3, 100.0, doc="vertical ground velocity (m/s)")] = 2.0
    wind_sigma_m_s: Annotated[float, In(1e-3, 50.0, doc="horizontal wind and its mean (m/s)")] = 5.0
    accel_bias_sigma_m_s2: Annotated[float, In(1e-5, 5.0, doc="accelerometer bias (m/s^2)")] = 0.1
    yaw_bias_sigma_deg: Annotated[float, In(1e-3, 180.0, doc="AHRS heading error (deg)")] = 3.0
    opt_rot_sigma_deg: Annotated[float, In(1e-3, 180.0, doc="optical frame heading error (deg)")] = 3.0
    baro_bias_sigma_m: Annotated[float, In(1e-3, 1e4, doc="baro bias (m)")] = 2.0
    terrain_sigma_m: Annotated[float, In(1e-3, 1e4, doc="ground height under the aircraft (m)")] = 2.0
    tas_scale_sigma: Annotated[float, In(
        1e-5, 0.5, doc="pitot scale error, the calibration's uncertainty (fraction)")] = 0.03
    att_delay_sigma_s: Annotated[float, In(1e-5, 1.0, doc="AHRS latency, unknown at start (s)")] = 0.05
    side_force_ofs_sigma_m_s2: Annotated[float, In(
        1e-5, 5.0, doc="side-force sideslip offset, g x roll error + trim (m/s^2)")] = 0.2
    aoa_ofs_sigma_deg: Annotated[float, In(1e-3, 30.0, doc="lift-model angle-of-attack offset (deg)")] = 2.0

    yaw_bias_sigma_rad = Radians("yaw_bias_sigma_deg")
    opt_rot_sigma_rad = Radians("opt_rot_sigma_deg")
    aoa_ofs_sigma_rad = Radians("aoa_ofs_sigma_deg")


@dataclass(frozen=True)
class Airframe(Validated):
    """The airframe's numbers the side-force sideslip and the lift-model angle of attack use (defaults: the
    simulator's Talon, ``sim/aircraft/talon/talon.xml``)."""

    mass_kg: Annotated[float, In(0.05, 1000.0, doc="mass (kg)")] = 3.5
    wing_area_m2: Annotated[float, In(1e-3, 100.0, doc="wing reference area (m^2)")] = 0.42
    air_density_kg_m3: Annotated[float, In(0.1, 1.5, doc="ISA sea level, about -1 % per 100 m (kg/m^3)")] = 1.225
    side_force_coef_per_rad: Annotated[float, In(
        -10.0, 0.0, doc="C_Ybeta, negative (per rad; 0: zero-sideslip measurement)")] = -0.35
    lift_slope_per_rad: Annotated[float, In(
        0.0, 20.0, doc="C_Lalpha in the linear range (per rad; 0: no angle of attack)")] = 4.5
    lift_coef_zero: Annotated[float, In(-2.0, 2.0, doc="C_L0, lift coefficient at zero angle of attack (-)")] = 0.15
    accel_tau_s: Annotated[float, In(0.0, 10.0, doc="low-pass of the lateral and normal specific forces (s)")] = 0.1

    def accel_gain_m(self, coef_per_rad: float) -> float:
        """``2 m / (rho S C)`` (m): the angle (rad) whose aerodynamic force coefficient slope is ``C`` per rad reads
        this times the specific force over ``V^2`` (``q S C angle = m f``); 0 for ``C`` = 0 (model off)."""
        if coef_per_rad == 0.0:
            return 0.0
        return 2.0 * self.mass_kg / (self.air_density_kg_m3 * self.wing_area_m2 * coef_per_rad)

    @property
    def sideslip_accel_gain_m(self) -> float:
        """``2 m / (rho S C_Ybeta)`` (m, negative): sideslip (rad) = this * lateral specific force / airspeed^2."""
        return self.accel_gain_m(self.side_force_coef_per_rad)

    @property
    def aoa_accel_gain_m(self) -> float:
        """``2 m / (rho S C_Lalpha)`` (m): angle of attack (rad) = ``-(this * f_z / V^2) - alpha_0``."""
        return self.accel_gain_m(self.lift_slope_per_rad)

    @property
    def aoa_zero_lift_rad(self) -> float:
        """``alpha_0 = C_L0 / C_Lalpha`` (rad): minus the zero-lift angle of attack."""
        c = self.lift_slope_per_rad
        return self.lift_coef_zero / c if c else 0.0


@dataclass(frozen=True)
class AirspeedConfig(Validated):
    """True airspeed, and the partial update (Schmidt) of its scale state (:mod:`fusion.aid.airspeed`)."""

    sigma_m_s: Annotated[float, In(1e-3, 20.0, doc="pitot noise, white (m/s)")] = 0.5
    turb_noise_factor: Annotated[float, In(
        0.0, 10.0, doc="+ (factor x turbulence sigma)^2 m^2/s^2: turbulence the wind does not follow (-)")] = 1.4
    min_m_s: Annotated[float, In(0.0, 100.0, doc="no airspeed, sideslip, angle of attack below (m/s)")] = 6.0
    scale_update_fraction: Annotated[float, In(
        0.0, 1.0, doc="share of the scale's gain used in turbulence (0-1; 0: consider)")] = 0.3
    scale_calm_fraction: Annotated[float, In(0.0, 1.0, doc="share used while the turbulence is calm (0-1)")] = 1.0
    scale_calm_turb_sigma_max_m_s: Annotated[float, In(
        0.0, 20.0, doc="adapted turbulence sigma up to which the air is calm (m/s)")] = 1.6


@dataclass(frozen=True)
class SideslipConfig(Validated):
    """Synthetic sideslip, fused with every airspeed sample (:mod:`fusion.aid.sideslip`)."""

    enabled: bool = True                             # fuse the sideslip with every airspeed sample (bool)
    sigma_deg: Annotated[float, In(1e-3, 90.0, doc="the side-force sideslip's own error (deg)")] = 5.0
    turb_noise_factor: Annotated[float, In(
        0.0, 10.0, doc="+ (factor x turbulence sigma / airspeed)^2 rad^2: lateral turbulence not followed (-)")] = 1.4

    sigma_rad = Radians("sigma_deg")


@dataclass(frozen=True)
class AoaConfig(Validated):
    """Lift-model angle of attack, fused with every airspeed sample (:mod:`fusion.aid.aoa`)."""

    enabled: bool = True                             # fuse it with every airspeed sample; needs the vertical wind
    sigma_deg: Annotated[float, In(1e-3, 90.0, doc="the lift model's own error (deg)")] = 1.0
    turb_noise_factor: Annotated[float, In(
        0.0, 10.0, doc="+ (factor x vertical_sigma_ratio x turbulence sigma / airspeed)^2 rad^2 (-)")] = 1.4
    max_deg: Annotated[float, In(0.1, 45.0, doc="not fused beyond: the stall ends the linear lift curve (deg)")] = 10.0

    sigma_rad = Radians("sigma_deg")


@dataclass(frozen=True)
class BaroConfig(Validated):
    """Barometric altitude (:mod:`fusion.aid.baro`)."""

    sigma_m: Annotated[float, In(1e-3, 100.0, doc="baro altitude noise (m)")] = 1.0


@dataclass(frozen=True)
class GnssConfig(Validated):
    """GNSS position and velocity (:mod:`fusion.aid.gnss`); the sigmas apply when the receiver reports none."""

    pos_ne_sigma_m: Annotated[float, In(1e-3, 1e3, doc="horizontal position noise (m)")] = 1.5
    pos_d_sigma_m: Annotated[float, In(1e-3, 1e3, doc="vertical position noise (m)")] = 3.0
    vel_ne_sigma_m_s: Annotated[float, In(1e-3, 50.0, doc="horizontal velocity noise (m/s)")] = 0.15
    vel_d_sigma_m_s: Annotated[float, In(1e-3, 50.0, doc="vertical velocity noise (m/s)")] = 0.2
    pos_corr_time_s: Annotated[float, In(0.0, 3600.0, doc="position error correlation time (s; 0: white)")] = 30.0
    reset_after_s: Annotated[float, In(1e-3, 1e4, doc="rejected this long: position/velocity reset to it (s)")] = 5.0


@dataclass(frozen=True)
class OpticalConfig(Validated):
    """Optical displacement noise model, pixels in the cycle's stabilised frame (:mod:`fusion.aid.optical`)."""

    match_sigma_px: Annotated[float, In(1e-3, 50.0, doc="matcher error at psr >= psr_ref (px)")] = 0.1
    psr_ref: Annotated[float, In(1e-3, 1e3, doc="peak-to-sidelobe ratio of a good match (-)")] = 4.0
    quality_floor: Annotated[float, In(1e-3, 1.0, doc="matcher sigma grows to at most 1 / floor times (-)")] = 0.2
    ssd_sigma_factor: Annotated[float, In(
        0.0, 100.0, doc="sigma at least this x the SSD surface's precision (-; 0: off)")] = 0.0
    att_rel_sigma_deg: Annotated[float, In(0.0, 30.0, doc="relative attitude error base -> current frame (deg)")] = 0.01
    att_rel_sigma_per_rad: Annotated[float, In(
        0.0, 1.0, doc="... plus this fraction of the rotation since the base (-)")] = 0.03
    att_rel_sigma_deg_per_s: Annotated[float, In(
        0.0, 30.0, doc="... plus this growth since the base, gyro bias (deg/s)")] = 0.12
    rel_rot_fallback_deg: Annotated[float, In(0.0, 180.0, doc="rotation assumed when a step has none (deg)")] = 10.0
    min_height_m: Annotated[float, In(0.1, 1e4, doc="no optical fusion below this height above ground (m)")] = 20.0

    att_rel_sigma_rad = Radians("att_rel_sigma_deg")
    att_rel_sigma_rad_per_s = Radians("att_rel_sigma_deg_per_s")
    rel_rot_fallback_rad = Radians("rel_rot_fallback_deg")


@dataclass(frozen=True)
class Gates(Validated):
    """NIS thresholds: a measurement whose NIS exceeds its gate is rejected (``test_ratio = NIS / gate``)."""

    optical_nis: Annotated[float, In(0.1, 1e6, doc="optical displacement, 2 dof (NIS)")] = 13.82
    airspeed_nis: Annotated[float, In(0.1, 1e6, doc="airspeed, 1 dof (NIS)")] = 10.83
    sideslip_nis: Annotated[float, In(0.1, 1e6, doc="sideslip, 1 dof (NIS)")] = 10.83
    aoa_nis: Annotated[float, In(0.1, 1e6, doc="angle of attack, 1 dof (NIS)")] = 10.83
    baro_nis: Annotated[float, In(0.1, 1e6, doc="baro, 1 dof (NIS)")] = 10.83
    gnss_pos_nis: Annotated[float, In(0.1, 1e6, doc="GNSS position, 3 dof, also for 2-D fixes (NIS)")] = 16.27
    gnss_vel_nis: Annotated[float, In(0.1, 1e6, doc="GNSS velocity, 3 dof, also for 2-D fixes (NIS)")] = 16.27


@dataclass(frozen=True)
class Timing(Validated):
    """The delayed fusion horizon and the input checks (:mod:`fusion.timeline`)."""

    fusion_delay_s: Annotated[float, In(
        0.0, 5.0, doc="horizon behind the newest IMU sample, >= camera latency (s)")] = 0.1
    predict_period_s: Annotated[float, In(0.0, 1.0, doc="covariance predicted at least this often (s)")] = 0.05
    buffer_max_events: Annotated[int, In(10, 1_000_000, doc="measurements waiting at most (-)")] = 2000
    att_max_age_s: Annotated[float, In(1e-4, 10.0, doc="attitude this close to the IMU stamp, else rejected (s)")] = 0.1
    imu_max_gap_s: Annotated[float, In(1e-4, 10.0, doc="longer IMU gaps are flagged in the imu status (s)")] = 0.1


@dataclass(frozen=True)
class Validity(Validated):
    """When the output may be used (``NavEstimate.valid``)."""

    vel_sigma_max_m_s: Annotated[float, In(1e-3, 100.0, doc="horizontal velocity sigma at most (m/s)")] = 1.0
    drift_sigma_max_deg: Annotated[float, In(1e-3, 180.0, doc="drift sigma at most (deg)")] = 3.0
    min_ground_speed_m_s: Annotated[float, In(
        0.0, 100.0, doc="ground speed at least: drift undefined at rest (m/s)")] = 3.0
    aid_timeout_s: Annotated[float, In(1e-3, 1e4, doc="optical or GNSS fused within (s)")] = 2.0

    drift_sigma_max_rad = Radians("drift_sigma_max_deg")


@dataclass(frozen=True)
class EkfConfig(Validated):
    """Navigation EKF parameters (``[ekf]`` in ``config/default.toml``, one table per section; the defaults are the
    same values).  ``cfg.replace(timing={"fusion_delay_s": 0.0})`` is a copy with fields of sections changed."""

    process: ProcessNoise = field(default_factory=ProcessNoise)
    wind: WindModel = field(default_factory=WindModel)
    init: InitialSigmas = field(default_factory=InitialSigmas)
    airframe: Airframe = field(default_factory=Airframe)
    airspeed: AirspeedConfig = field(default_factory=AirspeedConfig)
    sideslip: SideslipConfig = field(default_factory=SideslipConfig)
    aoa: AoaConfig = field(default_factory=AoaConfig)
    baro: BaroConfig = field(default_factory=BaroConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    optical: OpticalConfig = field(default_factory=OpticalConfig)
    gates: Gates = field(default_factory=Gates)
    timing: Timing = field(default_factory=Timing)
    validity: Validity = field(default_factory=Validity)

    def __post_init__(self) -> None:
        super().__post_init__()
        # without the vertical wind state the angle of attack could only move the vertical velocity
        require(not (self.aoa.enabled and self.airframe.lift_slope_per_rad > 0.0
                     and self.wind.vertical_sigma_ratio == 0.0), "aoa.enabled",
                "the lift-model angle of attack needs the vertical wind state (wind.vertical_sigma_ratio > 0); "
                "set aoa.enabled = false to run without it")

    def replace(self, **sections: Mapping[str, Any]) -> EkfConfig:
        """A copy with the given fields of the given sections changed (validated as when built)."""
        return dataclasses.replace(self, **{name: dataclasses.replace(getattr(self, name), **changes)
                                            for name, changes in sections.items()})

    def __getattr__(self, name: str) -> Any:
        # the flat names of the configuration before its sections, read-only, for callers not yet moved
        path = LEGACY_KEYS.get(name) or _LEGACY_PROPERTIES.get(name)
        if path is None:
            raise AttributeError(f"{type(self).__name__} has no attribute {name!r}")
        return getattr(getattr(self, path[0]), path[1])


#: The flat ``[ekf]`` keys of before the sections -> (section, field); accepted by :func:`ekf_config_from_raw` (and
#: readable as attributes) until every configuration file and caller uses the sections.
LEGACY_KEYS: dict[str, tuple[str, str]] = {
    **{k: ("process", k) for k in (f.name for f in dataclasses.fields(ProcessNoise))},
    "wind_rw_m_s_per_rt_s": ("wind", "mean_rw_m_s_per_rt_s"), "wind_d_sigma_ratio": ("wind", "vertical_sigma_ratio"),
    "wind_d_corr_time_s": ("wind", "vertical_corr_time_s"),
    **{f"wind_{k}": ("wind", k) for k in ("turb_sigma_m_s", "turb_corr_time_s", "turb_adapt_time_s",
                                          "turb_adapt_var_weight", "turb_sigma_min_m_s", "turb_sigma_max_m_s")},
    **{f"init_{f.name}": ("init", f.name) for f in dataclasses.fields(InitialSigmas)},
    "airframe_mass_kg": ("airframe", "mass_kg"), "airframe_wing_area_m2": ("airframe", "wing_area_m2"),
    "air_density_kg_m3": ("airframe", "air_density_kg_m3"),
    "sideslip_side_force_coef_per_rad": ("airframe", "side_force_coef_per_rad"),
    "aoa_lift_slope_per_rad": ("airframe", "lift_slope_per_rad"), "aoa_lift_coef_zero": ("airframe", "lift_coef_zero"),
    "sideslip_accel_tau_s": ("airframe", "accel_tau_s"),
    "tas_sigma_m_s": ("airspeed", "sigma_m_s"), "tas_turb_noise_factor": ("airspeed", "turb_noise_factor"),
    "tas_min_m_s": ("airspeed", "min_m_s"),
    **{f"tas_{k}": ("airspeed", k) for k in ("scale_update_fraction", "scale_calm_fraction",
                                             "scale_calm_turb_sigma_max_m_s")},
    "sideslip_fusion": ("sideslip", "enabled"), "sideslip_sigma_deg": ("sideslip", "sigma_deg"),
    "sideslip_turb_noise_factor": ("sideslip", "turb_noise_factor"),
    "aoa_fusion": ("aoa", "enabled"), "aoa_sigma_deg": ("aoa", "sigma_deg"),
    "aoa_turb_noise_factor": ("aoa", "turb_noise_factor"), "aoa_max_deg": ("aoa", "max_deg"),
    "baro_sigma_m": ("baro", "sigma_m"),
    **{f"gnss_{f.name}": ("gnss", f.name) for f in dataclasses.fields(GnssConfig)},
    **{f"optical_{f.name}": ("optical", f.name) for f in dataclasses.fields(OpticalConfig)},
    **{f"gate_{f.name}": ("gates", f.name) for f in dataclasses.fields(Gates)},
    **{f.name: ("timing", f.name) for f in dataclasses.fields(Timing)},
    **{f"valid_{f.name}": ("validity", f.name) for f in dataclasses.fields(Validity)},
}

# the derived values EkfConfig had before its sections -> (section, property), for the read-only flat names
_LEGACY_PROPERTIES: dict[str, tuple[str, str]] = {
    "yaw_bias_rw_rad_per_rt_s": ("process", "yaw_bias_rw_rad_per_rt_s"),
    "opt_rot_rw_rad_per_rt_s": ("process", "opt_rot_rw_rad_per_rt_s"),
    "aoa_ofs_rw_rad_per_rt_s": ("process", "aoa_ofs_rw_rad_per_rt_s"),
    "init_yaw_bias_sigma_rad": ("init", "yaw_bias_sigma_rad"), "init_opt_rot_sigma_rad": ("init", "opt_rot_sigma_rad"),
    "sideslip_sigma_rad": ("sideslip", "sigma_rad"), "aoa_sigma_rad": ("aoa", "sigma_rad"),
    "sideslip_accel_gain_m": ("airframe", "sideslip_accel_gain_m"),
    "aoa_accel_gain_m": ("airframe", "aoa_accel_gain_m"), "aoa_zero_lift_rad": ("airframe", "aoa_zero_lift_rad"),
    "optical_att_rel_sigma_rad": ("optical", "att_rel_sigma_rad"),
    "optical_att_rel_sigma_rad_per_s": ("optical", "att_rel_sigma_rad_per_s"),
    "optical_rel_rot_fallback_rad": ("optical", "rel_rot_fallback_rad"),
    "valid_drift_sigma_max_rad": ("validity", "drift_sigma_max_rad"),
}
#: Top-level sections of the configuration file that are not the EKF's: their presence marks a whole-file mapping.
_OTHER_SECTIONS = frozenset({"camera", "stab", "match", "cycle", "integrity", "companion"})
#: The sections of :class:`EkfConfig` (``[ekf.<section>]``), in order.
EKF_SECTIONS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(EkfConfig))


def _nested(layer: Any, where: str) -> tuple[dict[str, dict[str, Any]], dict[str, str]]:
    """One layer (``[ekf]``, a profile, overrides) as ``{section: {field: value}}``, its flat keys moved into their
    sections; also ``{"section.field": the name it was given under}`` for every field of the layer."""
    if not isinstance(layer, Mapping):
        raise ConfigError(where, f"must be a table, got {type(layer).__name__}")
    out: dict[str, dict[str, Any]] = {}
    given: dict[str, str] = {}
    for key, value in layer.items():
        if key in EKF_SECTIONS:
            if not isinstance(value, Mapping):
                raise ConfigError(f"{where}.{key}", f"must be a table, got {type(value).__name__}")
            out.setdefault(key, {}).update(value)
            given.update({f"{key}.{name}": f"{where}.{key}.{name}" for name in value})
        elif key not in LEGACY_KEYS:
            raise ConfigError(f"{where}.{key}", f"unknown key (sections: {', '.join(EKF_SECTIONS)})")
    for key, value in layer.items():           # flat keys after the sections: they win (a table merged from both)
        if key in LEGACY_KEYS:
            section, name = LEGACY_KEYS[key]
            out.setdefault(section, {})[name] = value
            given[f"{section}.{name}"] = f"{where}.{key}"
    return out, given


def ekf_config_from_raw(raw: Mapping[str, Any], profile: str | None = None, *,
                        overrides: Mapping[str, Any] | None = None) -> EkfConfig:
    """Build the EKF config from the raw configuration mapping.

    ``raw`` is either the whole file's mapping (its ``ekf`` table is used; a file without one gives the defaults)
    or the ``ekf`` table itself.  A mapping with an ``ekf`` key or any other known top-level section counts as the
    whole file; anything else is the table, so a misspelt key is an error naming ``ekf.<key>``.  ``profile``: the
    table ``[ekf.profiles.<profile>]`` is applied on top; ``overrides`` (e.g. ``[replay.ekf]``) last.  Each layer
    may use the sections or the flat keys of :data:`LEGACY_KEYS` (a flat key wins over its field in a section of the
    same layer); an error names the key as it was given.
    """
    if not isinstance(raw, Mapping):
        raise ConfigError("ekf", f"must be a table, got {type(raw).__name__}")
    table = raw["ekf"] if "ekf" in raw else {} if _OTHER_SECTIONS.intersection(raw) else raw
    if not isinstance(table, Mapping):
        raise ConfigError("ekf", f"must be a table, got {type(table).__name__}")
    profiles = table.get("profiles", {})
    if not isinstance(profiles, Mapping):
        raise ConfigError("ekf.profiles", f"must be a table, got {type(profiles).__name__}")
    layers: list[tuple[str, Any]] = [("ekf", {k: v for k, v in table.items() if k != "profiles"})]
    if profile is not None:
        if profile not in profiles:
            raise ConfigError(f"ekf.profiles.{profile}", f"no such profile (known: {', '.join(sorted(profiles))})")
        layers.append((f"ekf.profiles.{profile}", profiles[profile]))
    if overrides is not None:
        layers.append(("ekf", overrides))
    merged: dict[str, dict[str, Any]] = {}
    given: dict[str, str] = {}
    for where, layer in layers:
        nested, given_here = _nested(layer, where)
        for section, values in nested.items():
            merged.setdefault(section, {}).update(values)
        given.update(given_here)
    try:
        return build(EkfConfig, merged, "ekf")
    except ConfigError as e:
        path = e.field_path.removeprefix("ekf.")
        if given.get(path, f"ekf.{path}") != f"ekf.{path}":      # name the key as it was given
            raise ConfigError(given[path], f"{str(e).split(': ', 1)[1]} (ekf.{path})") from None
        raise
