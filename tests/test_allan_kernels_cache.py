"""numba's on-disk cache of the Allan kernels (rigctl.solvers.allan_kernels_jit, cache=True) from a
read-only install: where neither the source's __pycache__ nor the user's cache directory can
be written, the import used to fail (numba: "cannot cache function ...: no locator
available"); it now keeps the kernels in the user's own directory under the temporary
directory, compiled by the first process and loaded by the next. The install is made
read-only for real: a bind mount, read-only, in a mount namespace of its own (unshare -m;
skipped where the system does not allow one)."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from rigctl.solvers import allan_kernels as K

ROOT = Path(__file__).resolve().parents[1]

_CHILD = """
import json, os, sys
import numpy as np
from rk import allan_kernels as K
x = K.phase(np.arange(1000.0), 0.5, 0.0)  # compiles _phase (or loads it from the cache)
st = K._phase.stats
print(json.dumps({"cache": bool(K._CACHE), "sum": float(x.sum()),
                  "hits": sum(st.cache_hits.values()), "misses": sum(st.cache_misses.values())}))
"""


def _readonly_run(pkg: Path, env: dict) -> subprocess.CompletedProcess:
    script = (f"mount --bind -o ro {pkg} {pkg} && touch {pkg}/w 2>/dev/null && exit 9; "
              f"exec {sys.executable} -c '{_CHILD}'")
    return subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True,
                          text=True, env=env, cwd=pkg, timeout=120)


def test_kernels_import_and_cache_from_a_readonly_install(tmp_path: Path) -> None:
    if not K.HAVE_NUMBA:
        pytest.skip("numba (the fast extra) not installed")
    if shutil.which("unshare") is None or subprocess.run(
            ["unshare", "-m", "sh", "-c", f"mount --bind -o ro {tmp_path} {tmp_path}"],
            capture_output=True).returncode:
        pytest.skip("no mount namespace here (unshare -m, mount --bind): needs privileges")
    pkg = tmp_path / "site"
    (pkg / "rk").mkdir(parents=True)
    (pkg / "rk" / "__init__.py").write_text("")
    for name in ("allan_kernels.py", "allan_kernels_jit.py"):  # (numpy and numba only)
        shutil.copy(ROOT / "rigctl" / "solvers" / name, pkg / "rk")
    home_cache = tmp_path / "site" / "no-cache"  # inside the read-only mount: not writable
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {**os.environ, "PYTHONPATH": str(pkg), "XDG_CACHE_HOME": str(home_cache),
           "TMPDIR": str(tmp), "PYTHONDONTWRITEBYTECODE": "1"}
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("NUMBA_DISABLE_JIT", None)
    first = _readonly_run(pkg, env)
    assert first.returncode == 0, first.stderr[-2000:]
    import json

    a = json.loads(first.stdout.strip().splitlines()[-1])
    assert a["cache"] and a["misses"] == 1 and a["hits"] == 0
    assert a["sum"] == pytest.approx(0.5 * sum(sum(range(k)) for k in range(1001)))
    place = tmp / f"rigctl-numba-{os.getuid()}"
    assert place.is_dir() and (place.stat().st_mode & 0o777) == 0o700
    assert any(p.suffix == ".nbi" for p in place.rglob("*")), sorted(place.rglob("*"))
    assert not (pkg / "rk" / "__pycache__").exists()
    second = _readonly_run(pkg, env)
    assert second.returncode == 0, second.stderr[-2000:]
    b = json.loads(second.stdout.strip().splitlines()[-1])
    assert b["hits"] == 1 and b["misses"] == 0 and b["sum"] == a["sum"]
    # a directory of that name that another user could write is not used (numba's index
    # files are pickles): compiled in the process, nothing kept
    shutil.rmtree(place)
    place.mkdir(mode=0o777)
    place.chmod(0o777)
    third = _readonly_run(pkg, env)
    assert third.returncode == 0, third.stderr[-2000:]
    c = json.loads(third.stdout.strip().splitlines()[-1])
    assert not c["cache"] and c["hits"] == 0 and c["sum"] == a["sum"]
    assert not any(place.rglob("*"))
