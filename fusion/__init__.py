"""The EKF that fuses the optical displacements of :mod:`gsoe` with IMU, airspeed, baro and GNSS, and estimates
the wind.  Pure: no I/O.  Conventions as in :mod:`gsoe` (NED ``n``, FRD ``b``, ``R_ab``, SI units, radians).

Modules
    :mod:`fusion.state`         the state layout ``S`` (named slices: ``x[S.wind_ne]``) and why each state is there
    :mod:`fusion.config`        :class:`~fusion.config.EkfConfig` (``[ekf]`` in ``config/default.toml``): what the
                                filter assumes; :func:`~fusion.config.ekf_config_from_raw` builds it
    :mod:`fusion.ekf`           :class:`~fusion.ekf.NavEkf`, the public face: puts the parts below together
    :mod:`fusion.core`          state, covariance, ``P = F P F' + Q`` and the one gated (Joseph, Schmidt) update
    :mod:`fusion.process`       IMU-driven mean propagation, ``F``, ``Q``, the wind model
    :mod:`fusion.imu`           the IMU samples summed between covariance predictions
    :mod:`fusion.timeline`      IMU FIFO, measurement heap, delayed fusion horizon, same-stamp order, admission
    :mod:`fusion.aid`           one module per aid source (its measurement model and its PX4-style life cycle):
                                optical (stochastic clone), airspeed, sideslip, angle of attack, baro, GNSS
    :mod:`fusion.measurements`  the measurement models gathered from :mod:`fusion.aid`
    :mod:`fusion.status`        the per-source status records (:class:`~fusion.status.AidStatus`)
    :mod:`fusion.estimate`      the output :class:`~fusion.estimate.NavEstimate`
    :mod:`fusion.consistency`   NEES and chi-square intervals
    :mod:`fusion.bench`         :func:`~fusion.bench.bench_ekf_step` (the EKF cost per camera frame)

Usage: build ``NavEkf(cfg, t_us=..., pos_ned_m=..., vel_ned_m_s=...)`` once; push every sample with its own
``t_us`` (``predict(imu, att)``, ``fuse_airspeed``, ``fuse_baro``, ``fuse_gnss``, ``fuse_optical``); read
``estimate()`` and ``status()`` whenever needed.  Angles in the outputs are radians, clockwise from north; the wind
direction is where it blows *from* (MAVLink WIND).
"""
