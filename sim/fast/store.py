"""What the simulator can reuse from an earlier run, as named arrays; where they are kept is the application's business.

``sim`` does no file I/O. Expensive set-up results (the steady start flows, the split solver's coupling
matrices) are computed through ``reuse(kind, key, build)``: with no store installed (the default, and in
the tests of ``sim``) ``build()`` runs; an application installs a store (``install``) with a
``fetch(kind, key, build)`` method that returns the arrays saved under ``key`` or builds and saves them.
``key`` is a dict of plain values naming everything the arrays depend on.

Some results are files a library writes itself (PARDISO's factorisations: ``pardiso_handle_store`` writes its
internal structures into a directory). For those a store may also offer ``find_directory(kind, key)``, the
directory of a verified entry and its arrays (or None), and ``keep_directory(kind, key, write)``, which calls
``write(directory)`` on a fresh directory of its choosing and keeps what it wrote with the arrays it returns
(``write`` raises OSError when it cannot). ``sim`` only names the directory to the library; the store owns it.
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


def installed() -> ArrayStore | None:
    """The store in use (None: everything is recomputed)."""
    return _store


def reuse(kind: str, key: dict, build: Callable[[], Arrays]) -> Arrays:
    """The arrays of ``kind`` for ``key``: from the installed store, or ``build()``."""
    if _store is None:
        return build()
    return _store.fetch(kind, key, build)


def stored_directory(kind: str, key: dict) -> tuple[str, Arrays] | None:
    """The directory kept for (kind, key) and its arrays, or None (no store, no such entry, or a store that keeps
    no directories)."""
    finder = getattr(_store, "find_directory", None)
    return None if finder is None else finder(kind, key)


def keep_directory(kind: str, key: dict, write: Callable[[str], Arrays]) -> None:
    """Keep, under (kind, key), the files ``write(directory)`` puts in a directory and the arrays it returns
    (nothing without a store that keeps directories)."""
    keeper = getattr(_store, "keep_directory", None)
    if keeper is not None:
        keeper(kind, key, write)


def discard_directory(kind: str, key: dict, why: str) -> None:
    """Drop the directory kept for (kind, key): it passed the store's checks but the library could not use it."""
    discarder = getattr(_store, "discard_directory", None)
    if discarder is not None:
        discarder(kind, key, why)


def digest(*arrays: np.ndarray) -> str:
    """A SHA-256 of arrays' dtypes, shapes and bytes: a key part for data too large to name."""
    hasher = hashlib.sha256()
    for array in arrays:
        array = np.ascontiguousarray(array)
        hasher.update(f"{array.dtype.str}{array.shape}".encode())
        hasher.update(array)                     # its buffer: the same bytes as tobytes(), without the copy
    return hasher.hexdigest()


def code_digest(*functions) -> str:
    """A SHA-256 of functions' bytecode, constants and names (nested code objects by their own bytecode): a key
    part naming the code that computes a stored result, so an edited function misses instead of reusing.
    Numba's compiled functions are named by their Python source's code (``py_func``)."""
    def constant(c):
        if hasattr(c, "co_code"):
            return shape(c)
        if isinstance(c, frozenset):          # ``x in {"a", "b"}``: its repr's order changes with string hashing
            return ("frozenset", tuple(sorted(repr(item) for item in c)))
        return c

    def shape(code):
        return (code.co_code, tuple(constant(c) for c in code.co_consts), code.co_names)

    def named(function):
        # its defaults and the values it closes over (a kernel built by a factory) name it too
        closure = tuple(constant(cell.cell_contents) for cell in (function.__closure__ or ())
                        if isinstance(cell.cell_contents, (bool, int, float, str, tuple)))
        return (shape(function.__code__), repr(function.__defaults__), repr(function.__kwdefaults__), closure)
    return hashlib.sha256(repr([named(getattr(f, "py_func", f)) for f in functions]).encode()).hexdigest()


def module_digest(*modules) -> str:
    """``code_digest`` of every function, numba kernel and method defined in ``modules`` (in name order): a key part
    for a stored result computed through them, so editing any of them (a kernel whose bits change, a solver) makes
    the stored result miss instead of giving a warm run other bits than a cold one."""
    functions = []
    for module in modules:
        for name, value in sorted(vars(module).items()):
            if getattr(value, "__module__", None) != module.__name__:
                continue
            if isinstance(value, type):
                functions += [getattr(member, "__func__", member) for _, member in sorted(vars(value).items())
                              if hasattr(getattr(member, "__func__", member), "__code__")]
            elif hasattr(getattr(value, "py_func", value), "__code__"):
                functions.append(value)
    return code_digest(*functions)
