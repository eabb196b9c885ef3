"""Shared pytest configuration.

* tests/support is importable: the helper modules shared by the tests.
* Hypothesis is derandomised and keeps no example database: every run (and CI on a
  clean clone) explores the same cases, so a result is reproducible; long randomised
  runs live in ``benchmarks/fuzz_parsers.py``.
* Ctrl-C works as in a terminal however pytest was started: a background job or a CI
  runner may start it with SIGINT ignored, which every child process would inherit (a
  ``cellcal`` started by a test would then rightly ignore the test's Ctrl-C). Python's
  own handler is put back, so children start with the default action.
"""

from __future__ import annotations

import signal
import sys
from pathlib import Path

from hypothesis import settings

sys.path.insert(0, str(Path(__file__).parent / "support"))

settings.register_profile("cellcal", derandomize=True, database=None, print_blob=True)
settings.load_profile("cellcal")

if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)
