"""ptz_selfcal: online self-calibration of rotating and zooming cameras."""

import os as _os

# The nodes solve many small dense systems (bundle adjustment's reduced camera system, LM); a
# multi-threaded BLAS on a small shared machine makes them 5-20x slower through thread contention.
# Every node, tool and test process imports this package before numpy, so one BLAS thread is the
# default; set the variables in the environment to override.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
