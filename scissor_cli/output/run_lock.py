"""One run at a time per run directory: an advisory lock held for the run's life.

Two `simulate` processes writing the same directory (a second start with
`--force`, or a `--resume` of a run that is still going) would unlink and
truncate each other's results.h5.tmp and journal: the first run's finished
trials lost. The run takes an exclusive `flock` on `<dir>/.scissor-run.lock`
before it writes anything; the kernel drops it when the process (and the
worker processes that inherited it) are gone, so a SIGKILLed run leaves no
stale lock and `--resume` can take it at once.
"""

from __future__ import annotations

import os
from pathlib import Path

try:
    import fcntl
except ImportError:  # (not POSIX: no lock; one run per directory is then the user's to keep)
    fcntl = None

LOCK_NAME = ".scissor-run.lock"


class RunBusy(RuntimeError):
    """Another process holds the run directory."""


class RunLock:
    """The held lock of one run directory; `release()` (or the process's end) lets it go."""

    def __init__(self, fd: int | None):
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def claim(directory: Path | str) -> RunLock:
    """Take `directory`'s run lock (creating the directory); RunBusy naming the holder's pid if it is taken."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    if fcntl is None:
        return RunLock(None)
    path = directory / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise RunBusy(f"{directory}: another scissor run (pid {holder}) is writing there; wait for it to finish, "
                      f"stop it, or choose another directory") from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, str(os.getpid()).encode(), 0)
    return RunLock(fd)
