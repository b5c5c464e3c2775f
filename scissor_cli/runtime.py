"""Process-wide settings for a scissor run, applied at start-up, never on import.

`configure()` is called by the command line's start-up, by each trial
worker process and by the benchmarks; importing scissor changes nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, TypeVar

T = TypeVar("T")

#: OpenBLAS core names (`OPENBLAS_CORETYPE`) that cvxopt's bundled OpenBLAS knows, by the name numpy's newer
#: OpenBLAS reports for the same machine; a newer core maps to the older one whose kernels it runs
KNOWN_CORES = {"Sandybridge": "Sandybridge", "Haswell": "Haswell", "SkylakeX": "SkylakeX",
               "Cooperlake": "Cooperlake", "SapphireRapids": "SkylakeX", "Zen": "Zen"}


#: the environment variable that sets `configure`'s thread count (1 or 2) for a process and those it starts
THREADS_VARIABLE = "SCISSOR_THREADS"
#: the most threads a compiled loop splits its work across: it splits it into this many fixed parts
MOST_THREADS = 2
#: threads this process's compiled loops may use (`set_threads`); 1 until start-up says more
_threads = 1
#: (pid, executor) of the helper thread: made on first use in each process, since a forked child has none
_helper: tuple[int, ThreadPoolExecutor] | None = None


def configure(threads: int | None = None) -> None:
    """cvxopt's BLAS kernels matched to the CPU, one BLAS thread, freed array memory kept in the heap, and the
    threads the compiled loops may use (`set_threads`: threads, else SCISSOR_THREADS, else every core up to
    MOST_THREADS; a trial worker passes 1). Idempotent."""
    match_blas_kernels()
    limit_blas_threads()
    keep_freed_memory()
    if threads is None:
        threads = _threads_from_environment()
    set_threads(threads)


def _threads_from_environment() -> int:
    value = os.environ.get(THREADS_VARIABLE, "").strip()
    if value in {str(k) for k in range(1, MOST_THREADS + 1)}:
        return int(value)
    if value:
        raise ValueError(f"{THREADS_VARIABLE}={value!r}: allowed values are 1 to {MOST_THREADS}")
    return max(1, min(MOST_THREADS, os.cpu_count() or 1))


def set_threads(threads: int) -> None:
    """Let the compiled loops that split their work (`in_parts`) run threads (1 to MOST_THREADS) parts at once.

    The loops split their work into the same MOST_THREADS parts whatever
    the count and add the parts' sums in the same order, so the count
    changes the time, never a number. A trial worker runs on one thread:
    its processes already share the cores.
    """
    global _threads
    if not 1 <= threads <= MOST_THREADS:
        raise ValueError(f"threads: {threads}; allowed values are 1 to {MOST_THREADS}")
    _threads = int(threads)


def threads() -> int:
    """The threads this process's compiled loops may use (`set_threads`)."""
    return _threads


def part_bounds(count: int) -> list[int]:
    """The bounds (MOST_THREADS + 1 ints) of MOST_THREADS equal runs of range(count): a loop's fixed parts."""
    return [k * count // MOST_THREADS for k in range(MOST_THREADS + 1)]


def in_parts(*parts: Callable[[], T]) -> list[T]:
    """Each of parts called, the last on this thread and the others on helper threads when `threads` allows,
    else in turn; their results in order. The parts must not write what another reads: they are the fixed
    split of a compiled loop that releases the GIL (`nogil`)."""
    if _threads == 1 or len(parts) == 1:
        return [part() for part in parts]
    global _helper
    if _helper is None or _helper[0] != os.getpid():
        _helper = (os.getpid(), ThreadPoolExecutor(MOST_THREADS - 1, thread_name_prefix="scissor-part"))
    futures = [_helper[1].submit(part) for part in parts[:-1]]
    last = parts[-1]()
    return [f.result() for f in futures] + [last]


def match_blas_kernels() -> None:
    """Let cvxopt's OpenBLAS (CHOLMOD's dense kernels) run the kernels numpy's OpenBLAS picked for this CPU.

    cvxopt's wheel bundles an older OpenBLAS that does not recognise recent
    CPUs and falls back to its generic Prescott (SSE3) kernels, several times
    slower on a 3-D factorisation (docs/performance.md, "Why the runtime
    settings"; benchmarks/bench_slab_ladder.py). OpenBLAS reads `OPENBLAS_CORETYPE` when it
    is loaded, so this runs before cvxopt is imported, and does nothing when
    it already is, when the user set the variable, or when numpy's BLAS is not
    an OpenBLAS naming a core in KNOWN_CORES. The variable is inherited by
    worker processes; numpy's own OpenBLAS, loaded first, is not changed.
    """
    if "OPENBLAS_CORETYPE" in os.environ or "cvxopt" in sys.modules:
        return
    import numpy  # noqa: F401  (its OpenBLAS detects the core)
    from threadpoolctl import threadpool_info

    cores = {i.get("architecture") for i in threadpool_info() if i.get("internal_api") == "openblas"}
    known = sorted({KNOWN_CORES[c] for c in cores if c in KNOWN_CORES})
    if len(known) == 1:
        os.environ["OPENBLAS_CORETYPE"] = known[0]


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
