"""numba's ``njit`` for rigctl's compiled kernels, whose on-disk cache loads without numba's
target refresh.

numba keeps a compiled kernel on disk (``cache=True``) and a later process loads it instead of
compiling it. Its loader (``numba.core.caching.Cache.load_overload``) first calls the CPU
target's ``refresh()``, which imports and registers every implementation numba's *compiler*
uses (numba.np.arrayobj, linalg, random, typed containers, jitclass, ...): ~0.6 s of CPU on the
shared test machine, once per process, in every emulated ``rigctl run``, ``rigctl resume``,
``rigctl sim up`` and Allan analysis, although loading compiled code uses none of it. Unpickling
the cached library and linking it needs only what the target context set up when it was made
(numba's C helpers and the C math functions in LLVM's symbol table) and the runtime's
(NRT_*) symbols, which ``rtsys.initialize`` registers. The kernels decorated here load their
cached overloads that way; the machine code is the same file numba would load, so every result is
the same bit for bit. A kernel that is not in the cache is compiled by numba as before (its
compiler refreshes the target itself: numba.core.compiler.compile_extra), and on a numba
release not in :data:`VERIFIED_NUMBA` (or whose internals differ from what this expects) the
kernel keeps numba's own loader. Parallel kernels keep working: their thread pool is started by the library's
``reload_init`` (numba's ``_reload_parfors``), which the load runs.

Importing this module imports numba; without numba (the ``fast`` extra) it raises ImportError,
as ``from numba import njit`` did in the kernel modules.
"""
from __future__ import annotations

import functools
from typing import Any, Callable

import numba

#: numba releases (major.minor) on which loading without the refresh was checked (the cached
#: library links with the symbols the target context registered when it was made: no unresolved
#: symbol, which LLVM would report by aborting the process, not by a Python exception). On any
#: other release the kernels keep numba's own loader; check a new release with
#: tests/test_jit_load.py and add it here.
VERIFIED_NUMBA = ("0.68",)

try:  # numba's internals this uses (where they moved, the kernels keep numba's own loader)
    from numba.core import caching
    from numba.core.runtime import rtsys
except ImportError:  # pragma: no cover - another numba layout
    caching = rtsys = None
if ".".join(numba.__version__.split(".")[:2]) not in VERIFIED_NUMBA:  # pragma: no cover
    caching = rtsys = None


def _load_without_refresh(cache: Any, sig: Any, target_context: Any) -> Any:
    """``Cache.load_overload`` without its ``target_context.refresh()``: the runtime's symbols,
    then numba's own load (None when the signature is not cached: numba compiles it)."""
    rtsys.initialize(target_context)
    with cache._guard_against_spurious_io_errors():
        return cache._load_overload(sig, target_context)


def loads_without_refresh(dispatcher: Any) -> Any:
    """Make ``dispatcher`` (a numba CPU dispatcher with ``cache=True``) load its cached overloads
    with :func:`_load_without_refresh`; a dispatcher without a disk cache, or a numba whose cache
    object lacks what that uses, is left as it is. Returns the dispatcher."""
    cache = getattr(dispatcher, "_cache", None)
    if (caching is not None and isinstance(cache, caching.Cache) and callable(getattr(cache, "_load_overload", None))
            and callable(getattr(cache, "_guard_against_spurious_io_errors", None))):
        cache.load_overload = functools.partial(_load_without_refresh, cache)
    return dispatcher


def njit(*args: Any, **options: Any) -> Any:
    """``numba.njit`` with the same arguments, its cached overloads loaded by
    :func:`loads_without_refresh`: ``@njit(cache=True, nogil=True)`` or ``njit(fn, ...)``."""
    if args and callable(args[0]):
        return loads_without_refresh(numba.njit(*args, **options))
    decorate = numba.njit(*args, **options)

    def wrap(fn: Callable[..., Any]) -> Any:
        return loads_without_refresh(decorate(fn))
    return wrap
