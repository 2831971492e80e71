"""The I/O side of the module: configuration files, the command line, the companion app, MAVLink/MAVSDK links,
log replay and benchmarks.  Conventions as in :mod:`gsoe`."""
