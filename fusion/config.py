"""What the navigation EKF assumes: process noise, initial uncertainty, measurement noise, gates, timing, validity.

Built from the ``[ekf]`` table of the configuration file with :func:`ekf_config_from_raw` (``raw`` is the mapping
:func:`pipeline.config.load_gsoe_config` returns next to the optical config); every field is validated and a bad one
raises :class:`gsoe.config.ConfigError` naming ``ekf.<field>``.  The *true* sensor errors of a simulation live in
the scenario (``sim``), not here (STYLE section 8).

Units are in the names.  Noise densities are root power spectral densities: ``*_per_rt_hz`` for white noise on a
rate (``(m/s^2)/sqrt(Hz)`` for acceleration) and ``*_per_rt_s`` for random walks (the one-sigma change after one
second).  Angles are degrees here (an edge); code reads the ``*_rad`` properties.  Gates are thresholds on the
normalised innovation squared (NIS), i.e. chi-square quantiles of the measurement's dimension: 10.83, 13.82 and
16.27 are the 99.9 % points for 1, 2 and 3 degrees of freedom.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from common.config import ConfigError, build, in_range


@dataclass(frozen=True)
class EkfConfig:
    """Navigation EKF parameters (``[ekf]`` in ``config/default.toml``; the defaults below are the same values).

    Process noise
        ``accel_noise_m_s2_per_rt_hz``: white acceleration noise driving the velocity (IMU noise, vibration, AHRS
        attitude noise times g, AHRS latency in turns), per NED axis.  It is larger than the IMU's own noise
        because it carries the attitude's dynamic errors: 0.02 (plus a manoeuvre term ``|omega x f|`` x 0.01 s)
        made dead reckoning over featureless ground consistent but left moderate-turbulence runs overconfident
        (campaign NEES 0.872 -> 0.866, worst dead reckoning 11.4 -> 14.1 % of distance).
        The wind state ``wind_ne`` is the total wind the aircraft flies in: a mean ``wind_mean_ne`` that walks
        with ``wind_rw_m_s_per_rt_s`` (weather, shear with height, slow gust trains) plus first-order
        Gauss-Markov turbulence ``wind_ne - wind_mean_ne`` of standard deviation ``wind_turb_sigma_m_s`` (m/s,
        per axis) and correlation time ``wind_turb_corr_time_s`` (s): Dryden turbulence at 50-300 m seen at
        18-25 m/s has ``L / V`` ~ 7-15 s and, over the campaign's light to severe levels, sigma ~0.3-4 m/s.  Over
        less than ``tau`` the total wind walks with ``sqrt(2 sigma^2 / tau)`` (the earlier random-walk model's
        0.7 at the defaults), so gusts are followed as fast as before, but a wind error that persists longer
        than ``tau`` must be explained by the mean, which cannot turn with the heading: a pitot scale error then
        shows in loops of turns instead of being absorbed by the wind (see :mod:`fusion.state`).
        ``wind_rw_m_s_per_rt_s`` is 0.015 (0.9 m/s in an hour): PX4 EKF2's 0.05 is the walk of a total wind that
        must also follow the turbulence, which here has its own term, so the mean walks only with the weather and
        the shear of height changes.  With 0.05 the wind and position sigmas of an outage over featureless ground
        grew twice as fast as their errors (run 27: wind sigma 0.57 m/s against 0.28, position 27 m against 14).
        On the Monte Carlo campaign's first 40 runs (with the vertical wind below) 0.05 -> 0.015: NEES in bounds
        0.898 -> 0.903, wind speed RMSE median 0.340 -> 0.334 m/s.  Measured and not adopted: ArduPilot EKF3's
        height-rate scaling (``EK3_WIND_PSCALE``: the walk ``1 + k |v_d|`` times faster while climbing or sinking,
        for the shear), k = 1 s/m on 0.015 without the vertical wind: NEES 0.894 -> 0.888 (the campaign's log
        shear changes the wind by 0.016 m/s per metre at most); ``accel_noise_m_s2_per_rt_hz`` 0.04 (with the
        vertical wind and 0.015): NEES 0.903 -> 0.899.
        ``wind_turb_adapt_time_s`` (s; 0: ``sigma`` fixed): the turbulence level differs from flight to flight (the
        campaign's light to severe), so ``sigma^2`` is estimated in flight as an exponential average over this time
        of ``|wind - wind_mean|^2 / 2`` (the estimated turbulence, per axis), starting at
        ``wind_turb_sigma_m_s`` and kept within ``wind_turb_sigma_min_m_s``-``wind_turb_sigma_max_m_s``.
        ``wind_turb_adapt_var_weight`` (0-1, default 0.5): the share of the estimated turbulence's own variance
        (from ``P``) counted in that average.  All of it (1, the expectation-maximisation form) is a fixed point
        wherever the measurements cannot split the wind into mean and turbulence, so the level falls slowly from
        its prior in calm air (0.72 -> 0.32 m/s over 500 s against a true 0.06); 0.5 measured on the campaign's
        first 40 runs (with the vertical wind and the 5 deg sideslip): NEES in bounds 0.9035 -> 0.9067 (steps
        below the interval 6.3 -> 5.0 %, above 3.2 -> 4.1 %), wind speed RMSE median 0.311 -> 0.313 m/s.
        ``wind_d_sigma_ratio`` (0: no vertical wind, the PX4 EKF2 / ArduPilot model) and ``wind_d_corr_time_s``: the
        vertical wind ``wind_d`` is Gauss-Markov turbulence of that ratio times the adapted horizontal sigma (Dryden
        below 1000 ft: ``sigma_w / sigma_u`` = 0.63 at 50 m, 0.73 at 100 m, 0.88 at 200 m, 1.0 at 300 m) and that
        correlation time (Dryden ``L_w / V`` = height / airspeed, 2.5-15 s over the campaign's 50-300 m and 18-25 m/s).
        Why it is modelled (:mod:`fusion.state`): in a bank a vertical gust reads as sideslip.  On the Monte Carlo
        campaign's first 40 runs (0.8, 5 s against none): wind speed RMSE median 0.353 -> 0.340 m/s, mean 0.485 ->
        0.435 m/s (better in 35 runs), wind direction better in 36, NEES in bounds 0.888 -> 0.898.
        ``accel_bias_rw_m_s2_per_rt_s``, ``yaw_bias_rw_deg_per_rt_s``, ``opt_rot_rw_deg_per_rt_s`` (the optical frame's
        heading error follows the optical estimator's gyro-bias filter, so it moves faster than the AHRS's),
        ``baro_bias_rw_m_per_rt_s``, ``terrain_rw_m_per_rt_s``, ``tas_scale_rw_per_rt_s``: random walks of the
        slowly varying states.  ``att_delay_rw_s_per_rt_s``: of the AHRS time misalignment (a property of the
        installation; the walk lets it follow an upstream latency compensation that changes in flight).
        ``side_force_ofs_rw_m_s2_per_rt_s``: of the side-force sideslip's offset (an installation constant too).
    Initial one-sigma uncertainties
        ``init_*_sigma_*``; also the values a covariance reset restores.  ``init_att_delay_sigma_s``: the AHRS
        attitude's latency, unknown at start (autopilot telemetry and companion links: 0-0.1 s).
        ``init_side_force_ofs_sigma_m_s2``: the side-force sideslip's offset (``g`` times an AHRS roll error of up to
        about 1 deg, plus an airframe's trim side force).
        ``init_tas_scale_sigma`` is the pitot calibration's uncertainty (3 %: installation errors of a few percent;
        the Monte Carlo campaign draws each run's scale error with a standard deviation uniform in 0-5 %, 2.9 % over
        the campaign, and a 2 % prior put a 7.6 % error at 3.8 sigma and the wind 1.8 m/s outside its sigma, while
        5 % made the wind sigma of the 2 % paper_sil pitot too wide for the NEES interval).  On long slow upwind
        legs the scale and the along-heading wind are degenerate, and the residual bias of ``|v - wind|`` in
        turbulence (the filter's smoothed wind against a convex function) walks an estimated scale away: in the
        simulator's strong-wind scenario a fully updated 2 % prior ends at +5 to +22 % (true -3.9 to +2.7 %) and the
        wind 1-2 m/s off, while a near-fixed 0.3 % prior hides the pitot error from the wind sigma (wind error/sigma
        2-3).  Hence
        ``tas_scale_update_fraction`` (0-1, default 0.3): the scale's gain is scaled by it in every update
        (partial-update Schmidt filter, see :mod:`fusion.ekf`), so its variance and correlations (and hence the
        wind sigma) stay honest while its estimate moves slowly.  0: a pure consider state; 1: the full EKF update
        (flights with long crosswind legs in calm air).
        0 (a consider state) suits strong turbulence, 0.03 was the default for the rest (with 0 the short paper_sil
        acceptance flight's wind error is 0.53 m/s against 0.45, and the default flight's NEES 78 % against 82 %; on six
        Monte Carlo runs the two are within 0.04 m/s but for a moderate-turbulence run, 1.41 against 1.50 m/s).  The
        Monte Carlo campaign showed the learnt scale walking the wrong way in moderate to severe turbulence whatever the
        true one (+2.2 % after 300 s in runs with true -8.1 % and -0.35 %, +6 to +8 % with the full update, with either
        wind model; +1 % in light turbulence with a true ~0): the untracked 3-D turbulence makes the measured airspeed
        exceed ``|v - wind|`` on every heading by about ``(sigma_lateral^2 + sigma_vertical^2) / (2 V)`` (0.1 m/s, 0.5
        %), and the near-degenerate scale integrates that.
        A fraction gated by the adapted turbulence level (1 while sigma <= 0.35 m/s, falling as sigma^-2 to 0.03)
        was measured and not adopted: over the 100-run campaign wind 0.395 -> 0.388 m/s (runs with 4-8 % pitot
        errors 0.75 -> 0.64), but even with an exact pitot the fully updated scale settled at +2.6 to +4 % in three
        light-turbulence runs (the bias lies in the filter, not the sensor), and the paper SIL flight's NEES fell
        from 84 to 78 %.  So was a turn gate: the full update only while the heading turns at >= 10 deg/s and the
        adapted turbulence sigma is <= 1.3 m/s (0.03 otherwise).  On 32 recorded Monte Carlo runs (EKF-only
        replay) pitot errors of -5.6 to -7.6 % were learnt to within 1.2 %, wind speed median 0.420 -> 0.388 m/s,
        NEES in bounds 0.862 -> 0.877; but in the paper_sil flight (light turbulence, true -0.55 %) the scale went
        to +1.5 to +2.1 %, NEES 84 -> 67 % and wind 0.40 -> 0.46 m/s: the same bias, in turns.  With a 0.9 m/s
        limit paper_sil kept 83.5 % but the replays gained nothing (0.866, 0.420 m/s).
        Where that bias comes from (one light-turbulence run, exact airspeed ``|v - wind|``, full update, no
        sideslip fusion): it needs turbulence in the measured airspeed (the truth wind replaced by its
        60 s mean: +0.4 % instead of +4 %, also with the turbulence sigma held at 1.5 m/s), but not its link to
        the flight (the turbulence shifted by 100 or 237 s against the trajectory: +3.9 %), nor the linearisation
        (an iterated airspeed update: +4.6 %); it grows with the filter's turbulence sigma (fixed 0.2 / 0.5 / 1.5
        m/s: +1.0 / +2.3 / +4.2 %), and it builds up on straight legs (about +0.1 % per 5 s) and partly unwinds
        in turns: a drift along the degenerate scale / along-heading wind direction.
    Airspeed in turbulence, and the scale in calm air
        ``tas_turb_noise_factor`` (default 1.4): the airspeed's variance is ``tas_sigma_m_s^2 + (factor *
        sigma_turb)^2`` with the adapted turbulence sigma.  The turbulence the Gauss-Markov wind does not follow
        is airspeed noise correlated over a second or more; fused as white at 50 Hz it is weighted as fifty
        independent samples a second, and through the near-degenerate scale / along-heading wind pair it walks the
        scale.  This was the filter-side bias of the scale found above.  Kinematic check
        (``tests/test_fusion_wind_model.py``): an exact pitot plus a 1 m/s Gauss-Markov fluctuation along the air
        velocity, fully updated scale, 300 s of turns:
        - correlation time 1 s: the scale walks to +19 % without the term, +2.9 % with it;
        - 10 s: +0.9 % without, +0.4 % with;
        - a white 1 m/s fluctuation instead: -2.9 % with the plain 0.5 m/s sigma, -0.05 % with 2 m/s.
        ``tas_scale_calm_fraction`` (default 1) while the adapted turbulence sigma is at most
        ``tas_scale_calm_turb_sigma_max_m_s`` (default 1.6 m/s), else ``tas_scale_update_fraction``; checked at
        every airspeed sample, applied to every update, and not before one ``wind_turb_adapt_time_s`` from the
        start (until then the sigma is the prior, not a measurement of calm air; the 120 s paper_sil acceptance
        run's NEES 0.77 without the wait).  Measured on 32 recorded Monte Carlo runs (EKF-only
        replay of the campaign's sensor data, against their truth):
        - NEES in bounds 0.862 -> 0.892, wind speed RMSE median 0.420 -> 0.410 m/s, mean 0.573 -> 0.513;
        - pitot errors of -5.6 to -7.6 % learnt to -4.6 to -6.4 % (wind 1.12 -> 0.44, 0.60 -> 0.23, 0.69 -> 0.45);
        - runs in severe turbulence stay within 0.04 of their NEES; without the noise term the full update ran
          away there (+9 to +26 %);
        - the noise term alone (fraction 0.03): 0.867 and 0.417 m/s; factor 2.0: 0.887 and 0.406 m/s;
        - the paper_sil flight: NEES 84 % (unchanged), wind 0.40 -> 0.41 m/s; its scale settles at +1.2 to
          +1.4 % against a true -0.55 % (what remains of the bias).
        The fraction in turbulence was 0.03 until, with the noise term, the calm fraction and the side-force
        sideslip in place, the 100-run campaign showed its cost: in a moderate-turbulence run (adapted sigma 2.5-3.5
        m/s) with a +7.2 % pitot error the scale had reached +2.3 % after 600 s, and the along-heading wind was
        1.2 m/s off throughout.  On the campaign's first 40 runs 0.03 / 0.1 / 0.3 gave wind speed RMSE median 0.366
        / 0.362 / 0.357 m/s (mean 0.494 / 0.482 / 0.484) and NEES in bounds 0.8855 / 0.8860 / 0.8865; over the 100
        runs 0.3 against 0.03: median 0.323 -> 0.315 m/s (better in 69 runs), NEES 0.874 -> 0.875.
    Side-force sideslip (what the sideslip pseudo-measurement measures)
        The airframe's side force ``q S C_Ybeta beta`` is what the accelerometer's lateral channel reads (times
        ``1 / m``), so ``beta = 2 m f_y / (rho S C_Ybeta V^2)`` with ``f_y`` the lateral specific force low-passed
        over ``sideslip_accel_tau_s`` (less the accelerometer-bias state) and ``V`` the pitot airspeed corrected by
        the scale state.  ``sideslip_side_force_coef_per_rad`` (C_Ybeta, negative; 0 = the classic zero-sideslip
        pseudo-measurement), ``airframe_mass_kg``, ``airframe_wing_area_m2``, ``air_density_kg_m3``: the
        airframe's numbers (defaults: the simulator's Talon, ``sim/aircraft/talon/talon.xml``; the rudder's side
        force and the yaw-rate term are left out).  Why: the true sideslip in turbulence is 0.4-1.4 deg rms,
        correlated over seconds, which the zero-sideslip assumption puts straight into the cross-heading wind
        (0.35 m/s at 20 m/s per degree).  On the simulated Talon ``2 m f_y / (rho S C_Ybeta V^2)`` tracks JSBSim's
        sideslip with a correlation of 0.94-0.98 (a least-squares fit gives -31 to -35 m against the formula's
        -39 m).  Measured on 32 recorded Monte Carlo runs (EKF-only replay): wind speed RMSE median 0.393 -> 0.347
        m/s, mean 0.521 -> 0.482 m/s; the true sideslip itself in its place: 0.339 m/s.  ``sideslip_sigma_deg``
        stays 10: 6 or 3 deg made the wind worse (0.365 / 0.411 m/s) and the NEES worse, also with the true
        sideslip (1 deg: 0.563 m/s): the sideslip's residual is correlated over seconds and is fused at 50 Hz.
        Leaving out the bias state's share: 0.391 m/s.  Compensating the AHRS latency in the sideslip's
        attitude: no change.  The accelerometer-bias state also holds ``g`` times the AHRS roll error, which the
        accelerometer never read, so the sideslip subtracts the ``side_force_ofs`` state as well
        (:mod:`fusion.state`); on the campaign's first 40 runs: wind speed RMSE median 0.373 -> 0.366 m/s, mean
        0.518 -> 0.494 m/s (runs with a 1-2 deg roll error 0.57 -> 0.20, 0.66 -> 0.39), NEES in bounds 0.887 ->
        0.886.  With the offset, measured on the same 40 runs and not adopted: ``sideslip_sigma_deg`` 5: 0.392 m/s,
        NEES 0.872; 15: 0.375 m/s, NEES 0.890; ``tas_turb_noise_factor`` 1.0: worse wind in 11 of the first 14
        runs; ``wind_turb_sigma_m_s`` 0.7 (the initial level; it adapts down slowly in calm air, where the
        unresolved turbulence's variance holds it up): 0.359 m/s, NEES 0.887 (the calm runs better, e.g. 0.60 ->
        0.75, turbulent runs overconfident at the start, 0.96 -> 0.91).  1.0 (was 1.5) is the default: over the
        100-run campaign (with ``tas_scale_update_fraction`` 0.3) wind 0.315 -> 0.312 m/s, NEES in bounds 0.875 ->
        0.881; the 120 s paper_sil acceptance flight's NEES 0.775 -> 0.827 (its start-up was underconfident).
        Why a tighter sideslip made things worse: the vertical wind was not modelled, and in banks its gusts are
        sideslip error correlated over seconds (``wind_d``, :mod:`fusion.state`).  With the vertical wind,
        ``sideslip_sigma_deg`` is 5 (was 10) plus the lateral turbulence the wind state does not follow,
        ``(sideslip_turb_noise_factor * sigma_turb / V)^2`` with the adapted sigma (1.4, as for the airspeed).  On
        the campaign's first 40 runs: 5 deg alone (with the vertical wind) helped light turbulence and hurt the
        turbulent runs (median 0.340 -> 0.320 m/s, mean 0.435 -> 0.475, a severe run 1.05 -> 1.55); 5 deg + 1.4
        (with ``wind_rw_m_s_per_rt_s`` 0.015): median 0.334 -> 0.311 m/s (better in 32 of 40), mean 0.434 -> 0.420,
        NEES in bounds 0.903 either way; 4 deg + 2.0: 0.310 m/s, mean 0.416, NEES 0.903 (not significantly
        different, better in 25 of 40).  ``wind_d_sigma_ratio`` 1.0 instead of 0.8: wind worse in 23 of 34 runs.
        Re-flown with logs, the eight runs near the first 50 runs' wind median (1, 2, 3, 8, 9, 15, 28, 37; mean
        wind speed RMSE 0.313 m/s, NEES in bounds 0.940), one change at a time, none adopted:
        ``tas_turb_noise_factor`` 0.7 / 1.0 / 2.0: 0.331 / 0.320 / 0.310 m/s (2.0: NEES 0.935);
        ``wind_turb_corr_time_s`` 5 / 15 / 20: 0.329 / 0.315 / 0.325 (15 and 20: NEES 0.929 / 0.906);
        ``tas_sigma_m_s`` 0.3: 0.314; ``sideslip_turb_noise_factor`` 0.7 / 1.0: 0.312 / 0.312;
        ``sideslip_sigma_deg`` 2.5: 0.309 (run 2's dead reckoning 1.2 -> 2.5 % of distance); 2.5 with factor 0.5:
        0.317; 1.5 with factor 0: 0.370 (the cross-heading wind follows the true wind better, 0.43 -> 0.36 m/s in
        the GNSS phases, but the airspeed scale walks 1.5-2.7 % away and biases the wind along the heading by
        +0.3-0.4 m/s); ``tas_scale_calm_turb_sigma_max_m_s`` 0.8: 0.317.  Where the error sits: the estimate lags
        the 5 s centred truth by 0.5-1 s, and every causal smoothing of it added in post (trailing means, blends)
        scored worse.  An estimate equal to the true instantaneous wind scores 0.285 m/s on these runs, and the
        best causal blend of the true wind's past 2.5 s with its present 0.204 m/s.  A direct wind triangle
        (ground velocity minus the air velocity from the airspeed, the side-force sideslip and the AHRS, with the
        filter's calibration states), averaged over 0.5 s, is 0.33 m/s off the instantaneous wind speed: no closer
        than the filter.
    Lift-model angle of attack (what the angle-of-attack pseudo-measurement measures)
        The wing's lift is what the accelerometer's normal channel reads, ``-m f_z = q S (C_L0 + C_Lalpha alpha)``,
        so ``alpha = -2 m f_z / (rho S C_Lalpha V^2) - C_L0 / C_Lalpha``
        (:class:`fusion.measurements.LiftAngleOfAttack`, fused with every airspeed sample when ``aoa_fusion`` and
        ``aoa_lift_slope_per_rad`` > 0; ``f_z`` low-passed over ``sideslip_accel_tau_s``, less the accelerometer-bias
        state, plus the ``aoa_ofs`` state).  ``aoa_lift_slope_per_rad`` (C_Lalpha) and ``aoa_lift_coef_zero``
        (C_L0): the airframe's lift curve in its linear range (defaults: the simulator's Talon,
        ``sim/aircraft/talon/talon.xml``; the elevator's and the pitch rate's lift are left out, as the sideslip
        leaves out the rudder's side force).  ``aoa_sigma_deg`` plus
        ``(aoa_turb_noise_factor * wind_d_sigma_ratio * sigma_turb / V)^2``: its noise (the vertical turbulence the
        ``wind_d`` state does not follow, the counterpart of the sideslip's term).  ``aoa_ofs_rw_deg_per_rt_s``,
        ``init_aoa_ofs_sigma_deg``: the offset state (an installation constant: the lift model's offset, the part of
        an AHRS pitch error fixed in the body).  ``aoa_max_deg``: a reading beyond it is not fused (status reason
        "lift-model angle of attack outside ..."): the lift curve is linear only below the stall (the Talon's to
        about 10 deg), so a stall or a hard pull would read wrong.  It needs the vertical wind state
        (``wind_d_sigma_ratio`` > 0): without it the angle could only move the vertical velocity (a paper_sil flight
        in moderate turbulence: wind 1.29 m/s off and the GNSS velocity rejected), so the config refuses that pair.
        Why: the airspeed and the sideslip fix two components of the body-frame air velocity; the angle of attack
        fixes the third, so the vertical air velocity and with the ground's vertical velocity the vertical wind,
        which in a bank is sideslip and so cross-heading wind (``wind_d``, :mod:`fusion.state`).  Before it the
        vertical wind was seen only by the sideslip in banks: on the campaign's runs 1 and 2 its error was 0.70-0.81
        m/s rms against a true 0.80-0.89, and the wind's error against the instantaneous wind was 0.45-0.57 m/s
        across the heading.  On the simulated Talon the lift-model angle tracks JSBSim's with 0.26-0.44 deg rms of
        residual against 1.0-1.3 deg of spread (fitting the slope and offset gives back 4.40-4.46 per rad and
        C_L0 / C_Lalpha within 0.002 rad of the table's).  Measured, on the eight runs near the first 50 runs'
        wind median (1, 2, 3, 8, 9, 15, 28, 37; mean wind speed RMSE 0.313 m/s, NEES in bounds 0.940):
        ``aoa_sigma_deg`` 0.5 / 1 / 2 / 3 with no turbulence term: 0.344 / 0.283 / 0.279 / 0.277 m/s (NEES 0.928 /
        0.923 / 0.927 / 0.929); 2 with factor 1: 0.277; 1 with factor 1.4 (the default): 0.276 (median 0.268, better
        in 7 of 8, NEES 0.927).  Over the campaign's first 50 runs, against the same code without it: wind speed
        RMSE median 0.313 -> 0.268 m/s (mean 0.408 -> 0.349, p95 1.01 -> 0.82, better in 44 of 50), wind direction
        RMSE median 4.95 -> 4.61 deg (better in 43), NEES in bounds 0.904 -> 0.908, dead reckoning median 0.237 ->
        0.210 % of distance (mean 0.83 -> 0.86), drift MAE unchanged (0.209 deg).
        Limit: an AHRS pitch error about the heading's lateral axis (the simulator's Euler-angle bias) shifts the
        predicted angle of attack by ``d_theta cos(phi)`` and the sideslip by ``d_theta sin(phi)``, just as a steady
        vertical wind of ``V d_theta`` would; a body-fixed offset cannot hold it, so part of it stays in ``wind_d``
        (a 3.3 deg pitch error: ``aoa_ofs`` -1.1 deg, the vertical wind 0.75 m/s off on average).  A constant error
        of the lift model itself is learnt (tests/test_sim.py: C_L0 0.1 off, offset -1.45 deg against -1.27).
    Measurement noise (one sigma, used when the sensor does not report its own accuracy)
        ``tas_sigma_m_s`` (true airspeed, white; the turbulence's part is added above), ``sideslip_sigma_deg``
        (the sideslip pseudo-measurement, fused with every airspeed sample when ``sideslip_fusion``), ``baro_sigma_m``,
        ``gnss_pos_ne_sigma_m``, ``gnss_pos_d_sigma_m``, ``gnss_vel_ne_sigma_m_s``, ``gnss_vel_d_sigma_m_s``.
        ``tas_min_m_s``: airspeed below which neither airspeed nor sideslip is fused (on the ground, pitot noise).
        ``gnss_pos_corr_time_s``: correlation time of the receiver's position error (it wanders slowly); fixes
        closer together than that do not carry independent errors, so each fix's variance is multiplied by
        ``max(1, 2 tau / dt)`` (``dt``: time since the previous fix), the information rate of a first-order
        Gauss-Markov error.  0: white errors.
    Optical noise model (pixels in the cycle's stabilised frame; see :class:`fusion.measurements.OpticalDisplacement`)
        ``optical_match_sigma_px``: the matcher's sub-pixel error at good quality; it grows as ``psr_ref / psr``
        below ``optical_psr_ref``, by at most ``1 / optical_quality_floor``; and it is at least
        ``optical_ssd_sigma_factor`` times the precision the match's own SSD surface implies
        (``MatchQuality.match_sigma_px``, :func:`gsoe.matching.ssd_precision_px`; 0, the default: not used).  That
        precision is calibrated on the real tiles (tests/test_matching.py) and tells smooth ground: on the 5 m
        farmland imagery seen at 0.35 m/px it is about 0.17 px against 0.035 px on the 10 cm forest tile, and the
        errors' normalised squares have a median of 5.2 against the PSR model's 24 (the chi-square's: 1.39).  Yet
        over the 100-run campaign, factor 1 made the farmland runs worse: dead reckoning median 1.25 -> 1.97 % of
        distance, NEES in bounds 0.868 -> 0.840 (the other textures within 0.01; over all runs 0.9019 -> 0.9007).
        The farmland matches that pass the gates are biased, not only noisy (run 86: the migration 14 % long, mostly
        along track), and weighting them less leaves the bias and loses their information.  So it stays off.
        ``optical_att_rel_sigma_deg`` +
        ``optical_att_rel_sigma_per_rad * rel_rot_rad`` + ``optical_att_rel_sigma_deg_per_s * (t - base_t)``:
        one-sigma relative attitude error between the base and the current frame (AHRS/gyro noise, gyro scale error
        over the rotation ``rel_rot_rad``, residual gyro bias integrated since the base snapshot); it moves the
        template by ``focal_px`` times that angle, independent of altitude.  The defaults are fitted to the pixel
        errors of the simulator's paper_sil flight against its truth (99.7 % of steps inside the optical gate).
        ``optical_rel_rot_fallback_deg``: rotation assumed when a step carries no finite ``rel_rot_rad``.
        ``optical_min_height_m``: no optical fusion below this height above ground (the ground sample distance
        degenerates).
    Gates (NIS thresholds; a measurement whose NIS exceeds its gate is rejected, ``test_ratio = NIS / gate``)
        ``gate_optical_nis`` (2 dof), ``gate_airspeed_nis``, ``gate_sideslip_nis``, ``gate_baro_nis`` (1 dof),
        ``gate_gnss_pos_nis``, ``gate_gnss_vel_nis`` (3 dof; also used for the 2-dof horizontal-only forms).
        ``gnss_reset_after_s``: after GNSS position (velocity) has been rejected continuously for this long, the
        position (velocity) is reset to the GNSS value (e.g. GNSS back after a long outage).
    Timing
        ``fusion_delay_s``: the filter runs this far behind the newest IMU sample (a delayed fusion horizon, as PX4
        EKF2), so measurements stamped up to this much before the newest IMU sample are still fused at their own
        time.  Set it to at least the camera's processing latency; 0 when samples arrive in time order.
        ``predict_period_s``: the covariance is predicted at the stamp of every measurement and, while only IMU
        samples arrive, once this much time has been accumulated (the accumulated mean is exact for any length,
        see :mod:`fusion.ekf`, so this only bounds how far the state's time lags the newest consumed IMU sample).
        ``buffer_max_events``: at most this many measurements wait in the buffer (a flood of future-stamped samples
        is rejected).  ``att_max_age_s``: an IMU sample whose attitude is older (or newer) than this is rejected.
        ``imu_max_gap_s``: a longer gap between IMU samples is flagged in the ``imu`` status.
    Validity of the output
        The estimate is valid when the horizontal velocity sigma is at most ``valid_vel_sigma_max_m_s``, the drift
        sigma at most ``valid_drift_sigma_max_deg``, the ground speed at least ``valid_min_ground_speed_m_s`` (drift
        and course are undefined at rest), and optical or GNSS data was fused within ``valid_aid_timeout_s``.
    """

    # process noise
    accel_noise_m_s2_per_rt_hz: float = 0.05
    accel_bias_rw_m_s2_per_rt_s: float = 1e-3
    wind_rw_m_s_per_rt_s: float = 0.015
    wind_turb_sigma_m_s: float = 1.0
    wind_turb_corr_time_s: float = 10.0
    wind_turb_adapt_time_s: float = 60.0
    wind_turb_adapt_var_weight: float = 0.5
    wind_turb_sigma_min_m_s: float = 0.2
    wind_turb_sigma_max_m_s: float = 5.0
    wind_d_sigma_ratio: float = 0.8
    wind_d_corr_time_s: float = 5.0
    yaw_bias_rw_deg_per_rt_s: float = 0.002
    opt_rot_rw_deg_per_rt_s: float = 0.05
    baro_bias_rw_m_per_rt_s: float = 0.03
    terrain_rw_m_per_rt_s: float = 0.02
    tas_scale_rw_per_rt_s: float = 0.0
    att_delay_rw_s_per_rt_s: float = 1e-3
    side_force_ofs_rw_m_s2_per_rt_s: float = 1e-3
    aoa_ofs_rw_deg_per_rt_s: float = 0.005
    # initial uncertainty
    init_pos_ne_sigma_m: float = 10.0
    init_pos_d_sigma_m: float = 5.0
    init_vel_ne_sigma_m_s: float = 5.0
    init_vel_d_sigma_m_s: float = 2.0
    init_wind_sigma_m_s: float = 5.0
    init_accel_bias_sigma_m_s2: float = 0.1
    init_yaw_bias_sigma_deg: float = 3.0
    init_opt_rot_sigma_deg: float = 3.0
    init_baro_bias_sigma_m: float = 2.0
    init_terrain_sigma_m: float = 2.0
    init_tas_scale_sigma: float = 0.03
    init_att_delay_sigma_s: float = 0.05
    init_side_force_ofs_sigma_m_s2: float = 0.2
    init_aoa_ofs_sigma_deg: float = 2.0
    tas_scale_update_fraction: float = 0.3
    tas_scale_calm_fraction: float = 1.0
    tas_scale_calm_turb_sigma_max_m_s: float = 1.6
    # measurement noise
    tas_sigma_m_s: float = 0.5
    tas_turb_noise_factor: float = 1.4
    tas_min_m_s: float = 6.0
    sideslip_fusion: bool = True
    sideslip_sigma_deg: float = 5.0
    sideslip_turb_noise_factor: float = 1.4
    sideslip_side_force_coef_per_rad: float = -0.35
    airframe_mass_kg: float = 3.5
    airframe_wing_area_m2: float = 0.42
    air_density_kg_m3: float = 1.225
    sideslip_accel_tau_s: float = 0.1
    aoa_fusion: bool = True
    aoa_lift_slope_per_rad: float = 4.5
    aoa_lift_coef_zero: float = 0.15
    aoa_sigma_deg: float = 1.0
    aoa_turb_noise_factor: float = 1.4
    aoa_max_deg: float = 10.0
    baro_sigma_m: float = 1.0
    gnss_pos_ne_sigma_m: float = 1.5
    gnss_pos_d_sigma_m: float = 3.0
    gnss_vel_ne_sigma_m_s: float = 0.15
    gnss_vel_d_sigma_m_s: float = 0.2
    gnss_pos_corr_time_s: float = 30.0
    # optical noise model
    optical_match_sigma_px: float = 0.1
    optical_psr_ref: float = 4.0
    optical_quality_floor: float = 0.2
    optical_ssd_sigma_factor: float = 0.0
    optical_att_rel_sigma_deg: float = 0.01
    optical_att_rel_sigma_per_rad: float = 0.03
    optical_att_rel_sigma_deg_per_s: float = 0.12
    optical_rel_rot_fallback_deg: float = 10.0
    optical_min_height_m: float = 5.0
    # gates
    gate_optical_nis: float = 13.82
    gate_airspeed_nis: float = 10.83
    gate_sideslip_nis: float = 10.83
    gate_aoa_nis: float = 10.83
    gate_baro_nis: float = 10.83
    gate_gnss_pos_nis: float = 16.27
    gate_gnss_vel_nis: float = 16.27
    gnss_reset_after_s: float = 5.0
    # timing
    fusion_delay_s: float = 0.1
    predict_period_s: float = 0.05
    buffer_max_events: int = 2000
    att_max_age_s: float = 0.1
    imu_max_gap_s: float = 0.1
    # validity
    valid_vel_sigma_max_m_s: float = 1.0
    valid_drift_sigma_max_deg: float = 3.0
    valid_min_ground_speed_m_s: float = 3.0
    valid_aid_timeout_s: float = 2.0

    def __post_init__(self) -> None:
        pos = {
            "accel_noise_m_s2_per_rt_hz": (1e-4, 10.0),
            "init_pos_ne_sigma_m": (1e-3, 1e5),
            "init_pos_d_sigma_m": (1e-3, 1e4),
            "init_vel_ne_sigma_m_s": (1e-3, 100.0),
            "init_vel_d_sigma_m_s": (1e-3, 100.0),
            "init_wind_sigma_m_s": (1e-3, 50.0),
            "wind_turb_sigma_m_s": (1e-3, 20.0),
            "wind_turb_corr_time_s": (0.1, 3600.0),
            "wind_d_corr_time_s": (0.1, 3600.0),
            "wind_turb_sigma_min_m_s": (1e-3, 20.0),
            "wind_turb_sigma_max_m_s": (1e-3, 20.0),
            "init_accel_bias_sigma_m_s2": (1e-5, 5.0),
            "init_yaw_bias_sigma_deg": (1e-3, 180.0),
            "init_opt_rot_sigma_deg": (1e-3, 180.0),
            "init_baro_bias_sigma_m": (1e-3, 1e4),
            "init_terrain_sigma_m": (1e-3, 1e4),
            "init_tas_scale_sigma": (1e-5, 0.5),
            "init_att_delay_sigma_s": (1e-5, 1.0),
            "init_side_force_ofs_sigma_m_s2": (1e-5, 5.0),
            "init_aoa_ofs_sigma_deg": (1e-3, 30.0),
            "aoa_sigma_deg": (1e-3, 90.0),
            "aoa_max_deg": (0.1, 45.0),
            "tas_sigma_m_s": (1e-3, 20.0),
            "sideslip_sigma_deg": (1e-3, 90.0),
            "airframe_mass_kg": (0.05, 1000.0),
            "airframe_wing_area_m2": (1e-3, 100.0),
            "air_density_kg_m3": (0.1, 1.5),
            "baro_sigma_m": (1e-3, 100.0),
            "gnss_pos_ne_sigma_m": (1e-3, 1e3),
            "gnss_pos_d_sigma_m": (1e-3, 1e3),
            "gnss_vel_ne_sigma_m_s": (1e-3, 50.0),
            "gnss_vel_d_sigma_m_s": (1e-3, 50.0),
            "optical_match_sigma_px": (1e-3, 50.0),
            "optical_psr_ref": (1e-3, 1e3),
            "optical_quality_floor": (1e-3, 1.0),
            "optical_ssd_sigma_factor": (0.0, 100.0),
            "optical_min_height_m": (0.1, 1e4),
            "gate_optical_nis": (0.1, 1e6),
            "gate_airspeed_nis": (0.1, 1e6),
            "gate_sideslip_nis": (0.1, 1e6),
            "gate_aoa_nis": (0.1, 1e6),
            "gate_baro_nis": (0.1, 1e6),
            "gate_gnss_pos_nis": (0.1, 1e6),
            "gate_gnss_vel_nis": (0.1, 1e6),
            "valid_vel_sigma_max_m_s": (1e-3, 100.0),
            "valid_drift_sigma_max_deg": (1e-3, 180.0),
            "valid_aid_timeout_s": (1e-3, 1e4),
            "att_max_age_s": (1e-4, 10.0),
            "imu_max_gap_s": (1e-4, 10.0),
            "gnss_reset_after_s": (1e-3, 1e4),
        }
        for name, (lo, hi) in pos.items():
            in_range(getattr(self, name), lo, hi, name)
        nonneg = {
            "accel_bias_rw_m_s2_per_rt_s": 1.0,
            "wind_rw_m_s_per_rt_s": 10.0,
            "yaw_bias_rw_deg_per_rt_s": 10.0,
            "opt_rot_rw_deg_per_rt_s": 10.0,
            "baro_bias_rw_m_per_rt_s": 10.0,
            "terrain_rw_m_per_rt_s": 100.0,
            "tas_scale_rw_per_rt_s": 0.1,
            "att_delay_rw_s_per_rt_s": 0.1,
            "side_force_ofs_rw_m_s2_per_rt_s": 1.0,
            "aoa_ofs_rw_deg_per_rt_s": 1.0,
            "aoa_turb_noise_factor": 10.0,
            "aoa_lift_slope_per_rad": 20.0,
            "tas_scale_update_fraction": 1.0,
            "tas_scale_calm_fraction": 1.0,
            "tas_scale_calm_turb_sigma_max_m_s": 20.0,
            "tas_turb_noise_factor": 10.0,
            "sideslip_turb_noise_factor": 10.0,
            "wind_turb_adapt_time_s": 3600.0,
            "wind_d_sigma_ratio": 3.0,
            "wind_turb_adapt_var_weight": 1.0,
            "tas_min_m_s": 100.0,
            "sideslip_accel_tau_s": 10.0,
            "gnss_pos_corr_time_s": 3600.0,
            "optical_att_rel_sigma_deg": 30.0,
            "optical_att_rel_sigma_per_rad": 1.0,
            "optical_att_rel_sigma_deg_per_s": 30.0,
            "optical_rel_rot_fallback_deg": 180.0,
            "fusion_delay_s": 5.0,
            "predict_period_s": 1.0,
            "valid_min_ground_speed_m_s": 100.0,
        }
        for name, hi in nonneg.items():
            in_range(getattr(self, name), 0.0, hi, name)
        in_range(self.buffer_max_events, 10, 1_000_000, "buffer_max_events")
        # C_Ybeta is negative (the side force opposes the sideslip); 0 switches the side-force model off
        in_range(self.sideslip_side_force_coef_per_rad, -10.0, 0.0, "sideslip_side_force_coef_per_rad")
        in_range(self.aoa_lift_coef_zero, -2.0, 2.0, "aoa_lift_coef_zero")
        if self.aoa_fusion and self.aoa_lift_slope_per_rad > 0.0 and self.wind_d_sigma_ratio == 0.0:
            # without the vertical wind state the angle of attack could only move the vertical velocity
            raise ConfigError("aoa_fusion", "the lift-model angle of attack needs the vertical wind state "
                              "(wind_d_sigma_ratio > 0); set aoa_fusion = false to run without it")
        if not self.wind_turb_sigma_min_m_s <= self.wind_turb_sigma_m_s <= self.wind_turb_sigma_max_m_s:
            raise ConfigError("wind_turb_sigma_m_s", f"must lie in [wind_turb_sigma_min_m_s, wind_turb_sigma_max_m_s] "
                              f"= [{self.wind_turb_sigma_min_m_s}, {self.wind_turb_sigma_max_m_s}], "
                              f"got {self.wind_turb_sigma_m_s}")

    # radians for the code
    @property
    def yaw_bias_rw_rad_per_rt_s(self) -> float:
        return math.radians(self.yaw_bias_rw_deg_per_rt_s)

    @property
    def init_yaw_bias_sigma_rad(self) -> float:
        return math.radians(self.init_yaw_bias_sigma_deg)

    @property
    def opt_rot_rw_rad_per_rt_s(self) -> float:
        return math.radians(self.opt_rot_rw_deg_per_rt_s)

    @property
    def init_opt_rot_sigma_rad(self) -> float:
        return math.radians(self.init_opt_rot_sigma_deg)

    @property
    def sideslip_sigma_rad(self) -> float:
        return math.radians(self.sideslip_sigma_deg)

    @property
    def aoa_sigma_rad(self) -> float:
        return math.radians(self.aoa_sigma_deg)

    @property
    def aoa_ofs_rw_rad_per_rt_s(self) -> float:
        return math.radians(self.aoa_ofs_rw_deg_per_rt_s)

    @property
    def aoa_accel_gain_m(self) -> float:
        """``2 m / (rho S C_Lalpha)`` (m, positive): angle of attack (rad) = ``-(this * f_z / V^2) - alpha_0`` from
        the normal specific force ``f_z`` (FRD, about ``-g`` in level flight); 0 when ``aoa_lift_slope_per_rad`` is 0
        (no angle-of-attack measurement)."""
        return self._accel_gain_m(self.aoa_lift_slope_per_rad)

    @property
    def aoa_zero_lift_rad(self) -> float:
        """``alpha_0 = C_L0 / C_Lalpha`` (rad): minus the zero-lift angle of attack."""
        c = self.aoa_lift_slope_per_rad
        return self.aoa_lift_coef_zero / c if c else 0.0

    @property
    def sideslip_accel_gain_m(self) -> float:
        """``2 m / (rho S C_Ybeta)`` (m, negative): sideslip (rad) = this * lateral specific force / airspeed^2;
        0 when ``sideslip_side_force_coef_per_rad`` is 0 (zero-sideslip pseudo-measurement)."""
        return self._accel_gain_m(self.sideslip_side_force_coef_per_rad)

    def _accel_gain_m(self, coef_per_rad: float) -> float:
        """``2 m / (rho S C)`` (m): the angle (rad) whose aerodynamic force coefficient slope is ``C`` per rad reads
        this times the specific force over ``V^2`` (``q S C angle = m f``); 0 for ``C`` = 0 (model off)."""
        if coef_per_rad == 0.0:
            return 0.0
        return 2.0 * self.airframe_mass_kg / (self.air_density_kg_m3 * self.airframe_wing_area_m2 * coef_per_rad)

    @property
    def optical_att_rel_sigma_rad(self) -> float:
        return math.radians(self.optical_att_rel_sigma_deg)

    @property
    def optical_att_rel_sigma_rad_per_s(self) -> float:
        return math.radians(self.optical_att_rel_sigma_deg_per_s)

    @property
    def optical_rel_rot_fallback_rad(self) -> float:
        return math.radians(self.optical_rel_rot_fallback_deg)

    @property
    def valid_drift_sigma_max_rad(self) -> float:
        return math.radians(self.valid_drift_sigma_max_deg)


#: Top-level sections of the configuration file that are not the EKF's: their presence marks a whole-file mapping.
_OTHER_SECTIONS = frozenset({"camera", "stab", "match", "cycle", "integrity", "companion"})


def ekf_config_from_raw(raw: Mapping[str, Any]) -> EkfConfig:
    """Build the EKF config from the raw configuration mapping.

    ``raw`` is either the whole file's mapping (its ``ekf`` table is used; a file without one gives the defaults)
    or the ``ekf`` table itself (``raw["ekf"]``).  A mapping with an ``ekf`` key or any other known top-level
    section counts as the whole file; anything else is the table, so a misspelt key is an error naming
    ``ekf.<key>``, never silently ignored.
    """
    if not isinstance(raw, Mapping):
        raise ConfigError("ekf", f"must be a table, got {type(raw).__name__}")
    if "ekf" in raw:
        table = raw["ekf"]
    elif _OTHER_SECTIONS.intersection(raw):
        table = {}
    else:
        table = raw
    if not isinstance(table, Mapping):
        raise ConfigError("ekf", f"must be a table, got {type(table).__name__}")
    return build(EkfConfig, table, "ekf")
