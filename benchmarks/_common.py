"""The preamble of the Monte Carlo benchmarks that fit many curves (one piece for all of them):
one BLAS / OpenMP thread per process, set before numpy loads (a value the caller set is kept),
the repository root ``ROOT``, and tests/ and benchmarks/ importable (the tests' own generators
and helpers, the other benchmarks).

Import it first, before numpy: ``import _common`` (or ``from _common import ROOT``).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

#: the thread settings of numpy's BLAS / OpenMP (each 1 unless the caller set it)
THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
for _v in THREAD_VARS:
    os.environ.setdefault(_v, "1")

#: the repository's root
ROOT = Path(__file__).resolve().parent.parent
for _d in ("tests", "benchmarks"):  # benchmarks/ first on the path, as each benchmark had it
    if str(ROOT / _d) not in sys.path:
        sys.path.insert(0, str(ROOT / _d))
