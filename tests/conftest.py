import compileall
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from scissor_cli import runtime  # noqa: E402

# xdist's workers share the cores: one compiled-loop thread each, and in the scissor processes they start
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault(runtime.THREADS_VARIABLE, "1")
# the same process settings as a scissor run (one BLAS thread, heap kept)
runtime.configure()


def pytest_sessionstart(session):
    """Byte-compile the checkout's scissor_cli once, in the controller, before any test starts a process.

    The tests' subprocesses and trial workers import scissor_cli from the checkout (PYTHONPATH), not from the
    installed copy pip compiled. Where PYTHONDONTWRITEBYTECODE is set (as on the CI machines) no import writes
    a .pyc, so every one of those processes compiled each module it imports from source again. compileall
    writes them regardless; a module edited later is recompiled by the import as usual (the .pyc records
    its source's time and size).
    """
    if not hasattr(session.config, "workerinput"):  # the xdist controller, or a run without workers
        compileall.compile_dir(os.path.join(ROOT, "scissor_cli"), quiet=1)
