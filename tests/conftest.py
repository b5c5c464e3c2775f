import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from scissor_cli import runtime  # noqa: E402

# the same process settings as a scissor run (one BLAS thread, heap kept)
runtime.configure()
