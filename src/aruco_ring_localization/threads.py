"""Thread pools and malloc sized for a node process that handles small problems.

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

:func:`tune_malloc` (also called by every node's ``main()``): rospy reads each subscription with
``sock.recv(buff_size)``, which allocates a ``buff_size`` bytes object and shrinks it to what
arrived. Our subscriptions use large buffers (16 MB: ``ring_input.BUFF_SIZE``, the detector's
image buffer), above glibc's mmap threshold (128 kB, raised only when a chunk that large is freed,
which never happens: each one is shrunk first), so every read was a fresh ``mmap`` whose pages the
kernel zeroes as the message is written into them, then ``mremap`` and ``munmap``: per read,
system time and page faults in proportion to the message (1.2 MB for an image). With the mmap
threshold at its maximum (32 MB) those buffers come from the heap and with a trim threshold above
them the heap keeps its pages: the next read reuses them. The same as setting
``MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=134217728`` in the node's environment,
but done by the node, so a launch file of your own gets it too. ``ARUCO_RING_MALLOC=default``
leaves malloc as it is.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
from typing import Optional, Tuple

import cv2

logger = logging.getLogger(__name__)

#: Environment variable overriding the number of BLAS / OpenCV threads of a node.
ENV_VAR = "ARUCO_RING_THREADS"

#: Environment variable: ``default`` keeps glibc's malloc settings (:func:`tune_malloc` does nothing).
MALLOC_ENV_VAR = "ARUCO_RING_MALLOC"

# glibc's mallopt parameters (malloc.h) and the largest mmap threshold it accepts on 64-bit
# (HEAP_MAX_SIZE / 2): requests below the threshold come from the heap.
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 * 1024 * 1024
TRIM_THRESHOLD = 128 * 1024 * 1024

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


def tune_malloc(mmap_threshold: int = MMAP_THRESHOLD, trim_threshold: int = TRIM_THRESHOLD) -> Tuple[bool, str]:
    """Raise glibc's mmap and trim thresholds (``mallopt``) so that rospy's large receive buffers
    are reused heap memory instead of a fresh ``mmap`` per read (module docstring).

    Args:
        mmap_threshold: bytes; requests below it come from the heap (glibc caps it at 32 MB).
        trim_threshold: bytes of free memory at the top of a heap kept rather than returned.

    Returns:
        (applied, why not) - ``(False, reason)`` without glibc's ``mallopt`` (another C library),
        when ``mallopt`` refuses a value, or with ``ARUCO_RING_MALLOC=default``.
    """
    if os.environ.get(MALLOC_ENV_VAR, "").strip().lower() == "default":
        return False, f"{MALLOC_ENV_VAR}=default"
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None)
        mallopt = libc.mallopt
    except (OSError, AttributeError) as exc:
        return False, f"no mallopt in the C library ({exc})"
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    for name, param, value in (("M_MMAP_THRESHOLD", M_MMAP_THRESHOLD, mmap_threshold),
                               ("M_TRIM_THRESHOLD", M_TRIM_THRESHOLD, trim_threshold)):
        if mallopt(param, int(value)) != 1:
            return False, f"mallopt({name}, {int(value)}) refused"
    return True, ""
