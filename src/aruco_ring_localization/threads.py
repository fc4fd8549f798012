"""Thread pools sized for a node process that handles small problems.

NumPy's OpenBLAS starts one worker thread per core, and they spin-wait on every small matrix
product: the localizer node ran 34 threads and measured 116 ms CPU per ring frame with them,
13 ms with ``OPENBLAS_NUM_THREADS=1`` (docs/benchmarks.md, "nodes"). OpenCV's own pool does the
same for the detector's thresholding when 8 detector processes share 2 cores. The matrices here
are 6x6 to 48x48 and the images are handled one per process: one thread each is what they need.

:func:`limit_threads` is called first thing by every node's ``main()``, so a user's own launch
file gets the limit too; the stock launch files also set ``OPENBLAS_NUM_THREADS=1`` and
``OMP_NUM_THREADS=1`` in the node's environment (``<env>``), which keeps OpenBLAS from even
starting its workers. ``ARUCO_RING_THREADS=N`` overrides the limit (N > 1 for a machine with
cores to spare and a large bundle adjustment).
"""
from __future__ import annotations

import logging
import os
from typing import Optional

import cv2

logger = logging.getLogger(__name__)

#: Environment variable overriding the number of BLAS / OpenCV threads of a node.
ENV_VAR = "ARUCO_RING_THREADS"

_limiter = None  # threadpoolctl's limiter object, kept so the limit is not garbage-collected


def limit_threads(n: Optional[int] = None) -> int:
    """Limit the BLAS/OpenMP pools (threadpoolctl) and OpenCV's pool to ``n`` threads.

    Args:
        n: threads per pool; default ``$ARUCO_RING_THREADS`` or 1.

    Returns:
        The limit applied.
    """
    global _limiter
    if n is None:
        text = os.environ.get(ENV_VAR, "").strip()
        try:
            n = int(text) if text else 1
        except ValueError:
            logger.warning("%s=%r is not an integer; using 1 thread", ENV_VAR, text)
            n = 1
    n = max(1, int(n))
    from threadpoolctl import threadpool_limits

    _limiter = threadpool_limits(limits=n)
    cv2.setNumThreads(n)
    return n
