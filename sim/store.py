"""What the simulator can reuse from an earlier run, as named arrays; where they are kept is the application's business.

``sim`` does no file I/O. Expensive set-up results (the steady start flows, the split solver's coupling
matrices) are computed through ``reuse(kind, key, build)``: with no store installed (the default, and in
the tests of ``sim``) ``build()`` runs; an application installs a store (``install``) with a
``fetch(kind, key, build)`` method that returns the arrays saved under ``key`` or builds and saves them.
``key`` is a dict of plain values naming everything the arrays depend on.
"""

from __future__ import annotations

import hashlib
from typing import Callable, Protocol

import numpy as np

Arrays = dict  # str -> np.ndarray


class ArrayStore(Protocol):
    def fetch(self, kind: str, key: dict, build: Callable[[], Arrays]) -> Arrays: ...


_store: ArrayStore | None = None


def install(store: ArrayStore | None) -> ArrayStore | None:
    """Use ``store`` for set-up results from now on (None: recompute everything); returns the previous one."""
    global _store
    previous, _store = _store, store
    return previous


def reuse(kind: str, key: dict, build: Callable[[], Arrays]) -> Arrays:
    """The arrays of ``kind`` for ``key``: from the installed store, or ``build()``."""
    if _store is None:
        return build()
    return _store.fetch(kind, key, build)


def digest(*arrays: np.ndarray) -> str:
    """A SHA-256 of arrays' dtypes, shapes and bytes: a key part for data too large to name."""
    hasher = hashlib.sha256()
    for array in arrays:
        array = np.ascontiguousarray(array)
        hasher.update(f"{array.dtype.str}{array.shape}".encode())
        hasher.update(array.tobytes())
    return hasher.hexdigest()


def code_digest(*functions) -> str:
    """A SHA-256 of functions' bytecode, constants and names (nested code objects by their own bytecode): a key
    part naming the code that computes a stored result, so an edited function misses instead of reusing."""
    def shape(code):
        consts = tuple(shape(c) if hasattr(c, "co_code") else c for c in code.co_consts)
        return (code.co_code, consts, code.co_names)
    return hashlib.sha256(repr([shape(f.__code__) for f in functions]).encode()).hexdigest()
