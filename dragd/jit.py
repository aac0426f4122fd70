"""numba for the cycle's compiled kernels (dragd/control/fused.py, guard.py, safety.py; dragd/daemon/kernels.py).

Set up once per process and compiled ahead — or loaded from numba's on-disk cache — before the first cycle, with the
cycle's argument types (a kernel meeting new types would compile inside a cycle: tests check one signature each).
numba imports scipy to check its version and, on its first compilation, scipy.linalg for its BLAS support; the
kernels use neither and the daemon never loads scipy (its trajectories are planned in another process,
tests/test_daemon_track.py), so where scipy is not loaded yet numba is set up and compiles without it.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

_COMPILED: dict[str, dict[str, Any] | None] = {}  # module name → its kernels (None: numba missing)


def compile_kernels(namespace: dict[str, Any], helpers: tuple[str, ...],
                    kernels: dict[str, tuple[Callable[..., Any], tuple[Any, ...]]]) -> dict[str, Any] | None:
    """Jit ``helpers`` (names in ``namespace``, replaced there: the kernels call them as globals) and ``kernels``
    (name → (function, warm-up arguments of the cycle's types)); call each kernel once with its warm-up arguments.
    Once per module (``namespace``'s): later calls return the same kernels. None where numba cannot be imported
    (the callers keep their numpy reference paths)."""
    module = namespace["__name__"]
    if module not in _COMPILED:
        _COMPILED[module] = _compile(namespace, helpers, kernels)
    return _COMPILED[module]


def _compile(namespace: dict[str, Any], helpers: tuple[str, ...],
             kernels: dict[str, tuple[Callable[..., Any], tuple[Any, ...]]]) -> dict[str, Any] | None:
    hide = "scipy" not in sys.modules
    if hide:
        sys.modules["scipy"] = None  # type: ignore[assignment]  # (an import of it raises ImportError)
    try:
        try:
            import numba
        except ImportError:  # pragma: no cover - only where numba is missing
            return None

        # (not nogil: a kernel that dropped the GIL for its few µs would hand it to any other thread of the daemon,
        # and the cycle thread would then wait for it back — up to the switch interval)
        def jit(f: Callable[..., Any]) -> Any:
            # cached on disk where numba finds a writable directory (NUMBA_CACHE_DIR, the package's __pycache__, the
            # user's cache); compiled in each process where none is
            try:
                return numba.njit(cache=True, error_model="numpy")(f)
            except RuntimeError:  # "cannot cache function ...: no locator available"
                return numba.njit(cache=False, error_model="numpy")(f)

        for name in helpers:
            namespace[name] = jit(namespace[name])
        out = {}
        for name, (f, args) in kernels.items():
            k = jit(f)
            k(*args)
            out[name] = k
        return out
    finally:
        if hide:
            del sys.modules["scipy"]
