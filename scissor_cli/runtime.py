"""Process-wide settings for a scissor run, applied at start-up, never on import.

`configure()` is called by the command line's start-up, by each trial
worker process and by the benchmarks; importing scissor changes nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util


def configure() -> None:
    """One BLAS thread, and freed array memory kept in the heap. Idempotent."""
    limit_blas_threads()
    keep_freed_memory()


def limit_blas_threads() -> None:
    """One BLAS thread per process.

    scissor's array work is many small operations, parallelised across
    processes (trials) rather than threads. A multi-threaded BLAS hands a
    large dot product to a second thread, and on a busy 2-core machine that
    hand-off waits for the scheduler: ADMM ran much slower under load
    (docs/performance.md, "Why the runtime settings").
    """
    # threadpoolctl limits only libraries already loaded: load every BLAS
    # scissor uses (numpy's, scipy's own, cvxopt's) before limiting them.
    import cvxopt  # noqa: F401
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")


def keep_freed_memory() -> None:
    """Let glibc reuse freed array memory instead of returning it to the kernel.

    A solver step allocates and frees the same few MB-sized arrays (element
    matrices, tangents) again and again. glibc serves them with mmap or trims
    them off the heap top, so every call faults its pages in anew, and a
    first touch of a page is expensive on a small VM (see docs/performance.md).
    Serving blocks below 32 MiB from the heap and trimming only beyond
    256 MiB of free heap keeps those pages mapped. No-op off glibc.
    """
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return
    M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
    mallopt(M_MMAP_THRESHOLD, 32 * 2**20)
    mallopt(M_TRIM_THRESHOLD, 256 * 2**20)
