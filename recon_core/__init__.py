"""AE-Rec reconstruction core: affine reconstruction per date group, Euclidean upgrade by GCPs.

The core never imports the viewer (`aerec_viewer`).
"""

import os as _os
import sys as _sys

# The core's linear algebra is many small systems (3 x 3 blocks, a few hundred camera
# parameters): multi-threaded BLAS only adds overhead there, and on a loaded 2-core machine a
# spinning OpenBLAS turns a 0.4 ms Cholesky into 140 ms. Big kernels (SIFT, SGBM, warps) are
# OpenCV's own. Applied only if numpy is not imported yet; an explicit setting wins.
if "numpy" not in _sys.modules:
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        _os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
