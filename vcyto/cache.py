"""The disk cache of set-up results: what ``sim`` hands over as named arrays (``sim.store``), kept between runs.

Where: ``$VCYTO_CACHE_DIR`` if set, else the user cache directory (``platformdirs``: ``~/.cache/vcyto`` on
Linux, ``$XDG_CACHE_HOME/vcyto`` when that is set). ``VCYTO_CACHE=off`` turns it off; ``vcyto cache
clear`` empties it; ``vcyto cache`` says where it is and how large.

An entry is one ``.npz`` file named by the SHA-256 of its key: the kind, every field ``sim`` names (the
whole scenario, the numerics, the matrix digest, MKL's version, ...), the vcyto and numpy versions and
this file's format number. It holds its key again and a SHA-256 of its arrays: an entry whose checksum or
key does not match (a torn or corrupted file, a hash collision) is rebuilt and rewritten. Writes go to a
temporary file in the same directory and are moved in place with ``os.replace`` (atomic): concurrent runs
never see half an entry; the last writer wins with identical content.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
from pathlib import Path

import numpy as np
import platformdirs

from sim import store
from sim.store import digest

from . import __version__
from .outputs import create_new

FORMAT = 1
LOG = logging.getLogger(__name__)


def cache_directory() -> Path:
    """Where entries go: ``$VCYTO_CACHE_DIR`` or the user cache directory of vcyto."""
    configured = os.environ.get("VCYTO_CACHE_DIR")
    return Path(configured) if configured else Path(platformdirs.user_cache_dir("vcyto", appauthor=False))


def cache_enabled() -> bool:
    return os.environ.get("VCYTO_CACHE", "on").strip().lower() not in ("off", "0", "false", "no")


class DiskCache:
    """``sim.store.ArrayStore`` on disk; ``hits``, ``misses`` and ``rebuilt`` count what happened."""

    def __init__(self, directory: Path | str | None = None):
        self.directory = Path(directory) if directory is not None else cache_directory()
        self.hits = self.misses = self.rebuilt = 0
        self.unwritable = False

    def _full_key(self, kind: str, key: dict) -> str:
        return json.dumps({"kind": kind, "key": key, "vcyto": __version__, "numpy": np.__version__,
                           "format": FORMAT}, sort_keys=True, default=repr)

    def path(self, kind: str, key: dict) -> Path:
        name = digest(np.frombuffer(self._full_key(kind, key).encode(), dtype=np.uint8))
        return self.directory / kind / f"{name}.npz"

    def fetch(self, kind: str, key: dict, build) -> dict:
        """The arrays stored for (kind, key), or ``build()``'s, saved for the next run."""
        path, full_key = self.path(kind, key), self._full_key(kind, key)
        if path.exists():
            arrays = self._load(path, full_key)
            if arrays is not None:
                self.hits += 1
                return arrays
            self.rebuilt += 1
        else:
            self.misses += 1
        arrays = {name: np.asarray(value) for name, value in build().items()}
        self._save(path, full_key, arrays)
        return arrays

    def _load(self, path: Path, full_key: str) -> dict | None:
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {name: data[name] for name in data.files}
        except Exception as error:  # unreadable: torn, truncated, not an npz
            LOG.warning("cache entry %s is unreadable (%s): rebuilding it", path, error)
            return None
        stored_key = arrays.pop("_key", np.array("")).item()
        checksum = arrays.pop("_checksum", np.array("")).item()
        if stored_key != full_key or checksum != _checksum(arrays):
            LOG.warning("cache entry %s does not match its checksum or key: rebuilding it", path)
            return None
        return arrays

    def _save(self, path: Path, full_key: str, arrays: dict):
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".tmp")
            try:
                with os.fdopen(handle, "wb") as file:
                    np.savez(file, _key=np.array(full_key), _checksum=np.array(_checksum(arrays)), **arrays)
                os.replace(temporary, path)
            except BaseException:
                Path(temporary).unlink(missing_ok=True)
                raise
        except OSError as error:  # a read-only or full disk costs the next run its set-up, nothing else
            if not self.unwritable:       # said once; the other entries of the run would fail the same way
                LOG.warning("the set-up cache cannot be written (%s: %s); runs go on and pay their set-up each time: "
                            "set VCYTO_CACHE_DIR to a writable directory, or VCYTO_CACHE=off", path, error)
            self.unwritable = True


def _checksum(arrays: dict) -> str:
    return digest(*(np.frombuffer(name.encode(), dtype=np.uint8) for name in sorted(arrays)),
                  *(arrays[name] for name in sorted(arrays)))


def install_default() -> DiskCache | None:
    """Install the disk cache for ``sim`` unless ``VCYTO_CACHE=off``; returns it (or None)."""
    cache = DiskCache() if cache_enabled() else None
    store.install(cache)
    return cache


def usage(directory: Path | None = None) -> dict:
    """Where the cache is, whether it is on, and how many entries (the unit memo counted as one) and bytes it holds."""
    directory = directory or cache_directory()
    files = [*directory.rglob("*.npz"), *directory.glob("units/*.json")] if directory.exists() else []
    return {"directory": str(directory), "enabled": cache_enabled(), "entries": len(files),
            "bytes": sum(p.stat().st_size for p in files), "writable": _writable(directory)}


def _writable(directory: Path) -> bool:
    """Whether an entry can be created in ``directory`` (created if missing), probed by creating a file: a
    read-only mount or an immutable directory refuses even root."""
    probe = directory / f".probe.{os.getpid()}.tmp"
    try:
        directory.mkdir(parents=True, exist_ok=True)
        create_new(probe)
        probe.unlink()
        return True
    except OSError:
        return False


def clear(directory: Path | None = None) -> int:
    """Delete every entry (and stray temporary files); returns how many files went."""
    directory = directory or cache_directory()
    removed = 0
    if directory.exists():
        for pattern in ("*.npz", ".*.tmp", "units/*.json"):      # units/: vcyto.units' memo of pint's answers
            for path in directory.rglob(pattern):
                path.unlink(missing_ok=True)
                removed += 1
    return removed
