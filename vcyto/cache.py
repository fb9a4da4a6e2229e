"""The disk cache of set-up results: what ``sim`` hands over as named arrays (``sim.fast.store``), kept between runs.

Where: ``$VCYTO_CACHE_DIR`` if set, else the user cache directory (``platformdirs``: ``~/.cache/vcyto`` on
Linux, ``$XDG_CACHE_HOME/vcyto`` when that is set). ``VCYTO_CACHE=off`` turns it off; ``vcyto cache
clear`` empties it; ``vcyto cache`` says where it is and how large.

An entry is one ``.npz`` file named by the SHA-256 of its key: the kind, every field ``sim`` names (the
whole scenario, the numerics, the matrix digest, MKL's version, ...), the vcyto and numpy versions and
this file's format number. It holds its key and its arrays' names again, and the zip format keeps a CRC-32 of
each array, which is checked as the array is read: an entry whose key or names do not match (a hash collision, a
damaged directory of the zip file) or that fails a CRC or cannot be read (a torn or corrupted file) is rebuilt
and rewritten. (Format 1 kept a SHA-256 of the arrays instead of their names: the CRCs see the same damage as
they are read, where hashing took ~0.2 s of a tolerance run's start.) Writes go to a
temporary file in the same directory and are moved in place with ``os.replace`` (atomic): concurrent runs
never see half an entry; the last writer wins with identical content.

Files a library writes itself (PARDISO's factorisations, ``sim.fast.linalg.Pardiso``: 24 MB per half of the paper
mesh's split solve) are kept as a directory named like an entry, holding them and an ``entry.npz`` with the key,
each file's size and CRC-32 and the arrays. The directory is written under a temporary name and renamed into
place; a directory that fails its key, sizes or checksums is replaced; when another run put a valid one in
place first, ours is dropped.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import secrets
import shutil
import tempfile
import threading
import zlib
from pathlib import Path

import numpy as np
import platformdirs

from sim.fast import store
from sim.fast.store import digest

from . import __version__
from .outputs import create_new

FORMAT = 2          # the arrays' names stored and checked (format 1 held a SHA-256 of the arrays)
LOG = logging.getLogger(__name__)


def cache_directory() -> Path:
    """Where entries go: ``$VCYTO_CACHE_DIR`` or the user cache directory of vcyto."""
    configured = os.environ.get("VCYTO_CACHE_DIR")
    return Path(configured) if configured else Path(platformdirs.user_cache_dir("vcyto", appauthor=False))


def cache_enabled() -> bool:
    return os.environ.get("VCYTO_CACHE", "on").strip().lower() not in ("off", "0", "false", "no")


class DiskCache:
    """``sim.fast.store.ArrayStore`` on disk; ``hits``, ``misses`` and ``rebuilt`` count what happened."""

    def __init__(self, directory: Path | str | None = None):
        self.directory = Path(directory) if directory is not None else cache_directory()
        self.hits = self.misses = self.rebuilt = self.evicted = 0
        self.unwritable = False
        self._lock = threading.Lock()
        self.budget = directory_budget()      # bytes of directory entries per kind; a bad setting is refused here

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

    def _load(self, path: Path, full_key: str, quiet: bool = False) -> dict | None:
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {name: data[name] for name in data.files}
        except Exception as error:  # unreadable: torn, truncated, not an npz
            if not quiet:
                LOG.warning("cache entry %s is unreadable (%s): rebuilding it", path, error)
            return None
        # every array was read to its end, so zipfile checked its CRC-32 (a mismatch raised BadZipFile above)
        stored_key = arrays.pop("_key", np.array("")).item()
        names = arrays.pop("_names", np.array("")).item()
        if stored_key != full_key or names != _names(arrays):
            if not quiet:
                LOG.warning("cache entry %s does not match its key or its list of arrays: rebuilding it", path)
            return None
        return arrays

    def _save(self, path: Path, full_key: str, arrays: dict):
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".tmp")
            try:
                with os.fdopen(handle, "wb") as file:
                    _write_entry(file, full_key, arrays)
                os.replace(temporary, path)
            except BaseException:
                Path(temporary).unlink(missing_ok=True)
                raise
        except OSError as error:  # a read-only or full disk costs the next run its set-up, nothing else
            self._unwritable_warning(path, error)

    def _unwritable_warning(self, path: Path, error: OSError):
        if not self.unwritable:       # said once; the other entries of the run would fail the same way
            LOG.warning("the set-up cache cannot be written (%s: %s); runs go on and pay their set-up each time: "
                        "set VCYTO_CACHE_DIR to a writable directory, or VCYTO_CACHE=off", path, error)
        self.unwritable = True


    # ------------------------------------------------------------------ directories (sim.fast.store's second kind)
    def _count(self, name: str):
        with self._lock:                  # the split solve's two halves ask the store from two threads at once
            setattr(self, name, getattr(self, name) + 1)

    def find_directory(self, kind: str, key: dict) -> tuple[str, dict] | None:
        """The directory kept for (kind, key) and its arrays, when its key, sizes and checksums hold; else None."""
        path = self.path(kind, key).with_suffix("")
        arrays = self._verified(path, self._full_key(kind, key)) if path.is_dir() else None
        if arrays is None:
            if path.is_dir():             # (not one another run is deleting this moment)
                LOG.warning("cache entry %s does not match its checksums or key: rebuilding it", path)
                self._count("rebuilt")
            else:
                self._count("misses")
            return None
        self._count("hits")
        try:
            os.utime(path / ENTRY)        # recently used: the last to go when the budget is exceeded
        except OSError:
            pass
        return str(path), arrays

    def _verified(self, path: Path, full_key: str) -> dict | None:
        """The arrays of the directory entry at ``path`` when its key, sizes and CRC-32s hold (MKL's restore does not
        check its input: a flipped byte restores without error and solves wrong, so the check is never skipped)."""
        arrays = self._load(path / ENTRY, full_key, quiet=True)
        if arrays is None:
            return None
        files = json.loads(str(arrays.pop("_files", np.array("{}")).item()))
        if not files or any(_file_sum(path / name) != tuple(summed) for name, summed in files.items()):
            return None
        return arrays

    def keep_directory(self, kind: str, key: dict, write) -> None:
        """Keep what ``write(directory)`` writes (and the arrays it returns) under (kind, key), unless a valid entry
        is there; a failure to write is said once and costs only the next run's set-up."""
        path, full_key = self.path(kind, key).with_suffix(""), self._full_key(kind, key)
        if self.budget == 0 or (path.is_dir() and self._verified(path, full_key) is not None):
            return
        temporary = stale = None
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            temporary = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
            arrays = {name: np.asarray(value) for name, value in write(str(temporary)).items()}
            files = {item.name: _file_sum(item) for item in sorted(temporary.iterdir())}
            with open(temporary / ENTRY, "wb") as file:
                _write_entry(file, full_key, {**arrays, "_files": np.array(json.dumps(files))})
            if path.exists():
                if self._verified(path, full_key) is not None:
                    return                          # another run kept it meanwhile
                stale = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
                try:
                    os.replace(path, stale / "old")     # the invalid one out of the way at once; deleted below
                except FileNotFoundError:
                    pass                                # another run removed it meanwhile
            try:
                os.replace(temporary, path)
            except OSError:
                if path.is_dir():
                    return                              # another run put one in place first
                raise
            temporary = None
            self._evict(path.parent, keep=path)
        except OSError as error:
            self._unwritable_warning(path, error)
        finally:
            for leftover in (temporary, stale):
                if leftover is not None:
                    shutil.rmtree(leftover, ignore_errors=True)

    def discard_directory(self, kind: str, key: dict, why: str) -> None:
        """Delete the entry of (kind, key), which passed its checks but could not be used (``why``)."""
        path = self.path(kind, key).with_suffix("")
        LOG.warning("cache entry %s: %s; rebuilding it", path, why)
        self._count("rebuilt")
        _remove_entry(path)

    def _evict(self, kind: Path, keep: Path):
        """Delete the least recently used entries of ``kind`` until they hold at most the budget's bytes (``keep``,
        the one just written, stays). Entries another run deletes meanwhile are skipped."""
        entries = []
        for entry in _entries(kind):
            if entry != keep:
                try:
                    entries.append(((entry / ENTRY).stat().st_mtime, entry, _size(entry)))
                except OSError:
                    continue
        total = sum(size for _, _, size in entries) + _size(keep)
        for _, entry, size in sorted(entries, key=lambda item: item[0]):
            if total <= self.budget:
                break
            _remove_entry(entry)
            total -= size
            self._count("evicted")


ENTRY = "entry.npz"                 # in a directory entry: its key, its files' sizes and CRC-32s, its arrays
_NAME = re.compile(r"\.?[0-9a-f]{64}(\..*\.tmp)?")     # an entry (a key's hash), or a hidden one being written


def _directories(kind: Path) -> list[Path]:
    """The directories the cache made in ``kind``: entries and (hidden) ones being written."""
    try:
        return [entry for entry in kind.iterdir() if entry.is_dir() and _NAME.fullmatch(entry.name)]
    except OSError:
        return []


def _entries(kind: Path) -> list[Path]:
    """The directory entries of a kind (not those being written)."""
    return [entry for entry in _directories(kind) if not entry.name.startswith(".")]


def _entry_directories(directory: Path) -> list[Path]:
    """Every directory the cache made for entries under ``directory`` (kept or being written), nothing else."""
    kinds = [kind for kind in directory.iterdir() if kind.is_dir()] if directory.is_dir() else []
    return [entry for kind in kinds for entry in _directories(kind)]


def _entry_files(directory: Path) -> list[Path]:
    """The cache's own files under ``directory``: the ``.npz`` entries named by their keys' hashes, their temporary
    files, and the unit memo (``units/*.json``, vcyto.units' memo of pint's answers)."""
    if not directory.is_dir():
        return []
    found = [path for path in directory.glob("units/*.json") if path.is_file()]
    for path in directory.glob("*/*"):
        if path.is_file() and (re.fullmatch(r"[0-9a-f]{64}\.npz", path.name) or _NAME.fullmatch(path.name)):
            found.append(path)
    return found


def _size(entry: Path) -> int:
    return sum(path.stat().st_size for path in entry.iterdir() if path.is_file())


def _remove_entry(entry: Path):
    """Delete an entry's directory: renamed away first (a run that looks for it meanwhile misses cleanly)."""
    try:
        gone = entry.with_name(f".{entry.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
        os.replace(entry, gone)
    except OSError:
        return
    shutil.rmtree(gone, ignore_errors=True)


class CacheSettingError(ValueError):
    """An environment variable of the cache holds something it cannot use (bad input: one line, exit 2)."""


def directory_budget() -> int:
    """Bytes the kept directories of one kind may hold: ``$VCYTO_CACHE_FACTORS_MB`` megabytes (default 2048, ~40
    factorisations of the paper's mesh, ~49 MB each; a run keeps one per time-step level)."""
    text = os.environ.get("VCYTO_CACHE_FACTORS_MB", "2048")
    try:
        megabytes = float(text)
    except ValueError:
        megabytes = math.nan
    if not (math.isfinite(megabytes) and megabytes >= 0):
        raise CacheSettingError(f"VCYTO_CACHE_FACTORS_MB={text!r}: give the megabytes the cache may keep of "
                                "factorisations as a number >= 0 (default 2048; 0 keeps none)")
    return int(megabytes * 1e6)


def _file_sum(path: Path) -> tuple[int, int]:
    """(size, CRC-32) of a file, read in 4 MB pieces (-1, 0 when it cannot be read): enough to detect a torn,
    truncated or damaged file, at 5 ms per 24 MB against 14 ms for a SHA-256."""
    crc, size = 0, 0
    try:
        with open(path, "rb") as file:
            while chunk := file.read(4 << 20):
                crc, size = zlib.crc32(chunk, crc), size + len(chunk)
    except OSError:
        return -1, 0
    return size, crc


def _write_entry(file, full_key: str, arrays: dict):
    """An entry's ``.npz``: its key, its arrays' names (``_names``) and the arrays."""
    np.savez(file, _key=np.array(full_key), _names=np.array(_names(arrays)), **arrays)


def _names(arrays: dict) -> str:
    """The arrays' names as an entry keeps them (``_key`` and ``_names`` themselves left out)."""
    return json.dumps(sorted(arrays))


def install_default() -> DiskCache | None:
    """Install the disk cache for ``sim`` unless ``VCYTO_CACHE=off``; returns it (or None)."""
    cache = DiskCache() if cache_enabled() else None      # (it refuses a bad VCYTO_CACHE_FACTORS_MB)
    store.install(cache)
    return cache


_default_chosen = False


def ensure_default() -> None:
    """The Python API's default (``vcyto.run_stream``, ``vcyto.make_plant``): the disk cache, as on the command
    line, installed once per process unless a store is installed already or ``VCYTO_CACHE=off``."""
    global _default_chosen
    if not _default_chosen and store.installed() is None:
        install_default()
    _default_chosen = True


def usage(directory: Path | None = None) -> dict:
    """Where the cache is, whether it is on, and how many entries (the unit memo counted as one) and bytes it holds."""
    directory = directory or cache_directory()
    kept = [entry for entry in _entry_directories(directory) if not entry.name.startswith(".")]
    files = [path for path in _entry_files(directory) if path.suffix != ".tmp"]
    kept_bytes = 0
    for entry in kept:
        try:
            kept_bytes += _size(entry)
        except OSError:                   # deleted by another run meanwhile
            pass
    return {"directory": str(directory), "enabled": cache_enabled(), "entries": len(files) + len(kept),
            "bytes": sum(p.stat().st_size for p in files) + kept_bytes, "writable": _writable(directory)}


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
        # the directory entries (sim.fast.store's second kind, e.g. PARDISO's factorisations), named by their keys'
        # hashes (and hidden ones being written): nothing else under the directory is touched
        for entry in _entry_directories(directory):
            files = [path for path in entry.rglob("*") if path.is_file()]
            shutil.rmtree(entry, ignore_errors=True)
            removed += sum(not path.exists() for path in files)
        for path in _entry_files(directory):
            path.unlink(missing_ok=True)
            removed += 1
    return removed
