"""The one navigation pipeline: everything between sensor samples and an output estimate, driven alike by the
simulator, the companion app, log replay and the Monte Carlo runner.  Conventions as in :mod:`gsoe`."""
