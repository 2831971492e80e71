"""The flight side of the module: the companion app, MAVLink/MAVSDK links, ground-station display, guidance, log
reading and replay, the companion's SIL benchmark.  It does not import :mod:`sim` (the SIL benchmark runs the
simulated vehicle as a separate process); the command line is :mod:`cli`.  Conventions as in :mod:`gsoe`."""
