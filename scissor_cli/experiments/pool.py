"""Worker processes that never outlive the run, and signals that stop it cleanly.

A run with `--jobs N` starts N worker processes. However the run ends they
end with it (docs/contract.md#resume):

* **SIGKILL of the run.** Nothing in the run gets to act, so each worker
  asks the kernel, as it starts, to be killed when its parent dies
  (Linux `prctl(PR_SET_PDEATHSIG, SIGKILL)`).
* **SIGTERM, SIGINT (Ctrl-C), SIGHUP.** `install_signal_handlers` turns
  them into `Interrupted` in the run's main thread. Leaving the pool on
  that exception kills the workers at once (their current trials are lost;
  finished ones are already stored) and the run closes its file as
  `failed`, `interrupted`. Workers ignore these signals, so a Ctrl-C (or a
  SIGTERM) sent to the whole process group is handled by the run alone; a
  worker ends when the run kills it or dies.
* **A worker killed on its own** (SIGKILL, the out-of-memory killer) makes
  the pool raise `WorkerLost`; the run fails (exit 1), keeping what
  finished.
* **Storing a trial** is not cut short by a signal: inside
  `deferred_signals()` a signal is noted and raised when the block ends.
* **A stop that got lost.** Python drops an exception raised by a handler
  that runs inside a finaliser or a garbage-collector callback ("Exception
  ignored in ..."); the run then went on, ignoring later signals as the
  clean-up's. The pool's wait wakes every STOP_POLL_S and raises the stop
  again, so a run in its trials stops within that time whatever the
  handler met.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import multiprocessing
import os
import signal
import sys
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from typing import Callable, Iterable, Iterator, TypeVar

from scissor_cli import runtime

T = TypeVar("T")

PR_SET_PDEATHSIG = 1
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)


class Interrupted(KeyboardInterrupt):
    """The run was asked to stop by a signal; `exit_code` is 128 + the signal number."""

    def __init__(self, signum: int):
        self.signum = int(signum)
        super().__init__(signal.Signals(self.signum).name)

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


class WorkerLost(RuntimeError):
    """A worker process died while the run was going (killed on its own, or out of memory)."""


#: signum: the stop signal once the run is stopping (None before); pending: one held by `deferred_signals`
_state = {"defer": 0, "pending": None, "signum": None}
#: how often (s) the pool's wait looks for a stop whose exception was lost
STOP_POLL_S = 1.0


def _on_signal(signum, frame) -> None:
    if _state["signum"] is not None:
        return  # already stopping: a second Ctrl-C does not cut the clean-up short
    if _state["defer"]:
        _state["pending"] = signum
        return
    _state["signum"] = signum
    raise Interrupted(signum)


def install_signal_handlers() -> None:
    """SIGTERM, SIGINT and SIGHUP raise `Interrupted` in the main thread (once; later ones are ignored)."""
    _state.update(defer=0, pending=None, signum=None)
    for sig in STOP_SIGNALS:
        signal.signal(sig, _on_signal)


@contextmanager
def deferred_signals():
    """Hold a stop signal that arrives inside the block until the block has finished.

    Only effective with `install_signal_handlers`; without it Python's own
    KeyboardInterrupt may still arrive anywhere.
    """
    _state["defer"] += 1
    try:
        yield
    finally:
        _state["defer"] -= 1
    if not _state["defer"] and _state["pending"] is not None and _state["signum"] is None:
        signum, _state["pending"] = _state["pending"], None
        _state["signum"] = signum
        raise Interrupted(signum)


def die_with_parent() -> None:
    """Ask the kernel to SIGKILL this process when its parent dies (Linux; elsewhere a no-op).

    The parent may already have died between the fork and this call; then
    the request comes too late and the process exits at once.
    """
    if not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    parent = multiprocessing.parent_process()
    if parent is not None and not parent.is_alive():
        os._exit(1)


def init_worker() -> None:
    """The pool's initializer: the run's process settings (one thread: the workers share the cores), death with the
    parent, stop signals left to the run."""
    runtime.configure(threads=1)
    die_with_parent()
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)


def kill_workers(pool: ProcessPoolExecutor) -> None:
    """SIGKILL every worker of the pool and wait until the pool's manager thread has ended.

    `shutdown(cancel_futures=True)` alone lets each worker finish the batch it
    is running (seconds), and the interpreter waits for that on exit. The
    manager thread notices the dead workers and ends at once; waiting for it
    here also keeps it from racing the interpreter's exit hook (which then
    writes to the pipe the thread has just closed).
    """
    processes = list((getattr(pool, "_processes", None) or {}).values())  # no public API before Python 3.14
    manager = getattr(pool, "_executor_manager_thread", None)
    for p in processes:
        try:
            p.kill()
        except (OSError, ValueError, AttributeError):
            pass
    pool.shutdown(wait=False, cancel_futures=True)
    if manager is not None:
        manager.join(timeout=3.0)
    for p in processes:
        try:
            p.join(timeout=1.0)
        except (OSError, ValueError, AssertionError):
            pass


def run_pool(fn: Callable[..., list[T]], batches: Iterable[tuple], jobs: int) -> Iterator[T]:
    """fn(*batch) for every batch on `jobs` worker processes; yields the items of each result as it finishes.

    Any exception in the consumer or here (including `Interrupted` and the
    generator being closed) kills the workers before it propagates.
    """
    pool = ProcessPoolExecutor(max_workers=jobs, initializer=init_worker)
    try:
        pending = {pool.submit(fn, *batch) for batch in batches}
        while pending:
            done, pending = wait(pending, timeout=STOP_POLL_S, return_when=FIRST_COMPLETED)
            if _state["signum"] is not None:
                raise Interrupted(_state["signum"])  # (its first raise was lost: see the module doc)
            for future in done:
                try:
                    items = future.result()
                except BrokenProcessPool as exc:
                    raise WorkerLost(f"a trial worker process died ({exc}); the finished trials are kept: "
                                     f"finish the run with --resume") from None
                yield from items
    except BaseException:
        kill_workers(pool)
        raise
    else:
        pool.shutdown(wait=True)
