"""fleetslam: multi-robot RGB-D SLAM with partial offloading and FS-HICP map merging."""

import os

__version__ = "0.1.0"

# numpy's OpenBLAS starts a thread per core for every matrix product, even N x 3 by 3 x 3.
# Robot, cloud and their workers share a few cores, and there those threads wait on each
# other: 25 ms instead of 2 for 70k points on a busy 2-core machine, the robot's CPU 1.4x
# (docs/benchmarks.md, "One BLAS thread a process"). Set before numpy is first imported (a
# fleetslam process imports this package first); a value in the environment is kept.
BLAS_THREADS = "1"
os.environ.setdefault("OPENBLAS_NUM_THREADS", BLAS_THREADS)
