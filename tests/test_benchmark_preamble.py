"""The Monte Carlo benchmarks' preamble is one piece, benchmarks/_common.py (one BLAS thread per
process before numpy loads, a caller's setting kept; tests/ and benchmarks/ importable), which
allan_completed_dof, allan_interval_mc and allan_quickstart_cov import first. Before, each of
the three carried its own copy.
"""
from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parent.parent / "benchmarks"
USERS = ("allan_completed_dof", "allan_interval_mc", "allan_quickstart_cov")
THREADS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def _imports(path: Path) -> list[str]:
    """The top-level modules ``path`` imports, in order."""
    out = []
    for n in ast.parse(path.read_text()).body:
        if isinstance(n, ast.Import):
            out += [a.name.split(".")[0] for a in n.names]
        elif isinstance(n, ast.ImportFrom) and n.module:
            out.append(n.module.split(".")[0])
    return out


def test_the_benchmarks_import_the_one_preamble_before_numpy():
    for name in USERS:
        mods = _imports(BENCH / f"{name}.py")
        assert "_common" in mods and mods.index("_common") < mods.index("numpy"), (name, mods)
        src = (BENCH / f"{name}.py").read_text()
        # no copy of its own: thread settings or path insertions
        assert not any(v in src for v in THREADS) and "sys.path.insert" not in src, name


def test_the_preamble_sets_one_thread_and_keeps_a_callers_setting():
    """In a fresh interpreter (OPENBLAS_NUM_THREADS=3 set by the caller, the others unset): each
    benchmark imports (its tests/ and benchmarks/ imports found) and leaves the caller's 3 and
    the others at 1."""
    code = ("import os, sys\nsys.path.insert(0, sys.argv[1])\n"
            + "".join(f"import {m}\n" for m in USERS)
            + f"print(' '.join(os.environ[v] for v in {THREADS!r}))\n")
    env = dict({k: v for k, v in os.environ.items() if k not in THREADS}, OPENBLAS_NUM_THREADS="3")
    r = subprocess.run([sys.executable, "-c", code, str(BENCH)], env=env, cwd="/",
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split("\n")[-2] == "3 1 1", r.stdout
