"""The Allan analysis' numbers do not depend on how many threads OpenBLAS used.

OpenBLAS' threaded Cholesky, inverse and triangular solve round differently from its one-thread
routines on matrices of more than ~66 rows (the step test's are 150 x 150). The analysis ran its
tasks on worker threads with OpenBLAS' default thread count, and whether a call ran on one
thread or two depended on what else was running: `rigctl allan --json` of one emulated record
gave axes.*.excursions.step_test z, size_si, sd_si and threshold_z differing in the last digits
from run to run (3 runs: 2 distinct results). The workers and the calling thread now run every
task with OpenBLAS at one thread (rigctl.solvers.allan_stream.blas_single_thread).
"""
from __future__ import annotations

import os

import numpy as np
import pytest

from rigctl.analysis.allan import _PriorityPool
from rigctl.solvers.allan_stream import _openblas_local, blas_single_thread


def _work(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = np.linalg.cholesky(a)
    return c, np.linalg.inv(c)


@pytest.mark.skipif(not _openblas_local() or (os.cpu_count() or 1) < 2,
                    reason="needs numpy's bundled OpenBLAS and two cores (one thread only otherwise)")
def test_a_worker_task_rounds_as_one_blas_thread():
    rng = np.random.default_rng(3)
    x = rng.standard_normal((400, 300))
    a = x.T @ x / 400 + np.eye(300)
    with blas_single_thread():
        ref = _work(a)
    # the threaded routines do round differently here (else this test could not fail)
    threaded = _work(a)
    assert any(not np.array_equal(r, t) for r, t in zip(ref, threaded)), \
        "OpenBLAS' threaded and one-thread results agree bit for bit on this machine"
    pool = _PriorityPool(2)
    try:
        got = [pool.submit(_work, a) for _ in range(4)]
        got = [f.result(timeout=120) for f in got]
    finally:
        pool.shutdown()
    for g in got:
        assert all(np.array_equal(r, x) for r, x in zip(ref, g))
