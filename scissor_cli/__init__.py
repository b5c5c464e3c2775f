"""scissor: simulate robot-assisted breast intervention from a YAML scene."""

from threadpoolctl import threadpool_limits as _threadpool_limits

__version__ = "0.1.0"

# scissor's array work is many small operations, parallelised across processes
# (trials) rather than threads. A multi-threaded BLAS hands a large dot product
# to a second thread, and on a busy 2-core machine that hand-off waits for the
# scheduler: ADMM ran 2.4x slower under load. One BLAS thread per process.
_threadpool_limits(limits=1, user_api="blas")
