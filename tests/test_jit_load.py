"""rigctl.jit: a kernel in numba's on-disk cache loads in a new process without numba's target
refresh (~0.6 s of CPU per process: every emulated run, resume and Allan analysis), and the code
loaded that way computes what numba's own loader's does, bit for bit."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from rigctl.solvers import allan_kernels as K
from rigctl.sim import iir

_CHILD = """
import json, sys
import numpy as np
import numba
from numba.core import base

refreshes = []
_refresh = base.BaseContext.refresh
def counted(self):
    refreshes.append(1)
    return _refresh(self)
base.BaseContext.refresh = counted

from rigctl.sim import iir
from rigctl.solvers import allan_kernels as K

b, a = iir.prepare([0.2, -0.1, 0.05], [1.0, -1.5, 0.7])
x = np.sin(np.arange(5000.0) * 0.01) + 1e-3 * np.arange(5000.0)
y, zf = iir.lfilter_prepared(b, a, x, np.array([0.1, -0.2]))
ph = K.phase(np.cos(np.arange(20000.0) * 0.003), 0.01)
out = {"light_refreshes": len(refreshes),
       "light_hits": sum(iir._df2t.stats.cache_hits.values()) + sum(K._phase.stats.cache_hits.values()),
       "light_misses": sum(iir._df2t.stats.cache_misses.values()) + sum(K._phase.stats.cache_misses.values())}
# the same cached code through numba's own loader: new dispatchers of the same functions read the
# same cache entries (numba keys them by the function's source, not by the dispatcher)
df2t = numba.njit(cache=True, nogil=True)(iir._df2t.py_func)
y2, z2 = np.empty_like(x), np.array([0.1, -0.2])
df2t(b, a, x, z2, y2)
phase = numba.njit(cache=True, nogil=True)(K._phase.py_func)
ph2 = np.empty(20001)
yy = np.cos(np.arange(20000.0) * 0.003)
phase(yy, float(np.mean(yy)), 0.01, ph2)
out.update(numba_refreshes=len(refreshes),
           numba_hits=sum(df2t.stats.cache_hits.values()) + sum(phase.stats.cache_hits.values()),
           same=bool(np.array_equal(y, y2) and np.array_equal(zf, z2) and np.array_equal(ph, ph2)
                     and y.tobytes() == y2.tobytes() and ph.tobytes() == ph2.tobytes()))
print(json.dumps(out))
"""


def test_cached_kernels_load_without_the_target_refresh_and_compute_the_same():
    if not K.HAVE_NUMBA:
        pytest.skip("numba (the fast extra) not installed")
    # in the cache before the child runs (this process compiles them if they are not)
    b, a = iir.prepare([0.2, -0.1, 0.05], [1.0, -1.5, 0.7])
    iir.lfilter_prepared(b, a, np.zeros(3), np.zeros(2))
    K.phase(np.zeros(10), 0.01)
    r = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["light_hits"] == 2 and out["light_misses"] == 0, out   # both loaded from the cache
    import numba
    from rigctl import jit
    if ".".join(numba.__version__.split(".")[:2]) in jit.VERIFIED_NUMBA:
        assert out["light_refreshes"] == 0, out                       # ... without the refresh
    else:  # a release the light loader was not checked on: numba's own loader, which refreshes
        assert out["light_refreshes"] >= 1, out
    assert out["numba_hits"] == 2 and out["numba_refreshes"] >= 1, out  # numba's own loader refreshes
    assert out["same"], out
