"""scissor: simulate robot-assisted breast intervention from a YAML scene."""

import ctypes as _ctypes
import ctypes.util as _ctypes_util

from threadpoolctl import threadpool_limits as _threadpool_limits

__version__ = "0.1.0"

# scissor's array work is many small operations, parallelised across processes
# (trials) rather than threads. A multi-threaded BLAS hands a large dot product
# to a second thread, and on a busy 2-core machine that hand-off waits for the
# scheduler: ADMM ran 2.4x slower under load. One BLAS thread per process.
_threadpool_limits(limits=1, user_api="blas")


def _keep_freed_memory() -> None:
    """Let glibc reuse freed array memory instead of returning it to the kernel.

    A solver step allocates and frees the same few MB-sized arrays (element
    matrices, tangents) again and again. glibc serves them with mmap or trims
    them off the heap top, so every call faults its pages in anew, and on
    this VM a first touch costs ~4 µs per 4 KiB page: element_matrices at
    15.7k elements took 7 ms instead of 3.7 ms, a Newton solve 10 % longer.
    Serving blocks below 32 MiB from the heap and trimming only beyond
    256 MiB of free heap keeps those pages mapped. No-op off glibc.
    """
    try:
        libc = _ctypes.CDLL(_ctypes_util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return
    M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
    mallopt(M_MMAP_THRESHOLD, 32 * 2**20)
    mallopt(M_TRIM_THRESHOLD, 256 * 2**20)


_keep_freed_memory()
