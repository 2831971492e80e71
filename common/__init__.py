"""The bottom package every other imports: the sample vocabulary (:mod:`common.samples`), angle helpers
(:mod:`common.angles`), the configuration machinery (:mod:`common.config`, :mod:`common.configfile`) and the
log format (:mod:`common.logio`), the accuracy figures and the files every flight report writes
(:mod:`common.metrics`, :mod:`common.report`) and the simulator's camera frame stream format
(:mod:`common.framestream`).  It imports no other package of the project (``tests/test_layers.py`` checks the
layers).  Conventions as in :mod:`gsoe`."""
