"""Software-in-the-loop simulator: camera renderer, JSBSim flight dynamics, wind, sensors, scenarios and the
simulated-flight runner.  ``sim`` owns the truth (true wind, true sensor errors); ``config/`` owns what the
estimators assume (STYLE section 8).  Conventions as in :mod:`gsoe`."""
