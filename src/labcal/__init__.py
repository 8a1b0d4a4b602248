"""labcal: calibrate serial industrial robots from three-target tracker measurements."""

import os as _os

# Every matrix labcal solves is small (at most a few thousand rows by a few hundred columns). Multithreaded BLAS
# gains nothing there, and on a busy 2-core machine its spinning threads made a 0.5 s fit take 90 s; a single
# thread also keeps reductions in one order, so the same data and seed give bit-identical fits. This takes
# effect when labcal is imported before numpy (the CLI, `python -m labcal…`); the Makefile sets it for the rest.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
