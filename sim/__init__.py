"""Software-in-the-loop simulator: camera renderer, JSBSim flight dynamics, wind, sensors, scenarios and the
simulated-flight runner, its report, and Monte Carlo campaigns of simulated flights (:mod:`sim.montecarlo`,
:mod:`sim.mc_report`).  It does not import :mod:`nav`.  ``sim`` owns the truth (true wind, true sensor errors);
``config/`` owns what the estimators assume (STYLE section 8).  Conventions as in :mod:`gsoe`."""
