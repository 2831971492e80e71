"""The EKF that fuses the optical displacements of :mod:`gsoe` with IMU, airspeed, baro and GNSS, and estimates
the wind.  Pure: no I/O.  Conventions as in :mod:`gsoe` (NED ``n``, FRD ``b``, ``R_ab``, SI units, radians).

Modules
    :mod:`fusion.state`         the state layout ``S`` (named slices: ``x[S.wind_ne]``) and why each state is there
    :mod:`fusion.config`        :class:`~fusion.config.EkfConfig` (``[ekf]`` in ``config/default.toml``): what the
                                filter assumes; :func:`~fusion.config.ekf_config_from_raw` builds it
    :mod:`fusion.measurements`  one class per measurement: optical displacement (stochastic clone), true airspeed,
                                sideslip (side-force or zero), baro altitude, GNSS position and velocity
    :mod:`fusion.ekf`           :class:`~fusion.ekf.NavEkf` (delayed-horizon time handling, gating, status records)
                                and its output :class:`~fusion.ekf.NavEstimate`
    :mod:`fusion.consistency`   NEES and chi-square intervals
    :mod:`fusion.bench`         :func:`~fusion.bench.bench_ekf_step` (the EKF cost per camera frame)

Usage: build ``NavEkf(cfg, t_us=..., pos_ned_m=..., vel_ned_m_s=...)`` once; push every sample with its own
``t_us`` (``predict(imu, att)``, ``fuse_airspeed``, ``fuse_baro``, ``fuse_gnss``, ``fuse_optical``); read
``estimate()`` and ``status()`` whenever needed.  Angles in the outputs are radians, clockwise from north; the wind
direction is where it blows *from* (MAVLink WIND).
"""
