"""The bottom package every other imports: the sample vocabulary (:mod:`common.samples`), angle helpers
(:mod:`common.angles`), the configuration machinery (:mod:`common.config`, :mod:`common.configfile`) and the
log format (:mod:`common.logio`).  It imports no other package of the project.  Conventions as in :mod:`gsoe`."""
