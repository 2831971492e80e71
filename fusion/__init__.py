"""The EKF that fuses the optical displacements of :mod:`gsoe` with IMU, airspeed, baro and GNSS, and estimates
the wind.  Pure: no I/O.  Conventions as in :mod:`gsoe` (NED ``n``, FRD ``b``, ``R_ab``, SI units, radians)."""
