"""numba, when installed: the one ``njit`` setting of the package's compiled loops, and whether numba is usable.

Kept apart from the backends so that the compiled checks (:mod:`anm_torchrl.grid.fastchecks`) and output passes
(:mod:`anm_torchrl.grid.fastoutput`) need not import a backend, and the numba backend can import them.
"""

from __future__ import annotations

try:
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; the torch backend is the fallback
    numba = None


def available() -> bool:
    """True when numba is importable (the ``numba`` backend and the compiled passes can be used)."""
    return numba is not None


def njit(**kw):
    """``numba.njit(cache=True, nogil=True, **kw)`` (on-disk cache; the GIL released for the kernel's thread
    pool), or the identity without numba (the functions then stay plain Python, unused on the hot paths)."""
    return numba.njit(cache=True, nogil=True, **kw) if numba is not None else (lambda f: f)
