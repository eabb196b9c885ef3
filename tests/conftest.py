"""Shared pytest configuration.

* tests/support is importable: the helper modules shared by the tests.
* Hypothesis is derandomised and keeps no example database: every run (and CI on a
  clean clone) explores the same cases, so a result is reproducible; long randomised
  runs live in ``benchmarks/fuzz_parsers.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from hypothesis import settings

sys.path.insert(0, str(Path(__file__).parent / "support"))

settings.register_profile("cellcal", derandomize=True, database=None, print_blob=True)
settings.load_profile("cellcal")
