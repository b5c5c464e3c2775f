"""Messages and progress bars of long work, without a reporter passed through every call.

The CLI decides what a terminal shows (`reporting(ConsoleReporter(...))`);
the stages below it call `info` and `bar`. Nothing is shown unless a caller
set a reporter: library use, tests and worker processes stay silent.
"""

from __future__ import annotations

from contextlib import contextmanager
from contextvars import ContextVar
from typing import Callable, Iterator, Protocol

#: advance(n=1): move a bar on by n steps
Advance = Callable[..., None]


class Reporter(Protocol):
    def info(self, message: str) -> None: ...

    def progress(self, description: str, total: int) -> Advance: ...


class SilentReporter:
    """Shows nothing."""

    def info(self, message: str) -> None:
        pass

    def progress(self, description: str, total: int) -> Advance:
        return lambda advance=1: None


_REPORTER: ContextVar[Reporter] = ContextVar("scissor_reporter", default=SilentReporter())


@contextmanager
def reporting(reporter: Reporter) -> Iterator[Reporter]:
    """Send the messages and bars of the work inside the block to `reporter`."""
    token = _REPORTER.set(reporter)
    try:
        yield reporter
    finally:
        _REPORTER.reset(token)


def info(message: str) -> None:
    """One line for the user (a stage's result, a note)."""
    _REPORTER.get().info(message)


def bar(description: str, total: int) -> Advance:
    """A progress bar over `total` steps; returns its advance(n=1)."""
    return _REPORTER.get().progress(description, total)
