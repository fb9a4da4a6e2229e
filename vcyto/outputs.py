"""The files a run writes: unique names created exclusively (never overwriting another run's), strict JSON.

- ``strict_json``: JSON without NaN or infinity (undefined values are ``null``), numpy values as plain ones;
  every JSON vcyto prints or writes goes through it, so any strict parser reads it.
- ``reserve_run``: a run id unique to this process and moment (``stream-YYYYmmdd-HHMMSS-mmm-PID``, or the
  user's ``--name``) whose files are all created at once with O_EXCL before any work; a clash (the same
  name, or two runs in one millisecond in one process) takes the next free suffix ``-2``, ``-3``, ... (a
  ``--name`` that is taken is refused instead). The summary starts as ``{"status": "running"}``, so a
  killed run's summary says it never finished.
"""

from __future__ import annotations

import json
import math
import os
import re
import secrets
import time
from pathlib import Path

PLACEHOLDER_SUMMARY = {"status": "running", "reason": "the run has not finished (or was killed before it could "
                                                      "write its summary)"}
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,119}")


def plain(value):
    """``value`` as plain JSON data: NaN and infinities as None, numpy scalars and arrays as numbers and lists,
    tuples as lists, other objects as their text."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, dict):
        return {str(key): plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(item) for item in value]
    if hasattr(value, "tolist"):                        # numpy scalars and arrays
        return plain(value.tolist())
    if isinstance(value, Path):
        return str(value)
    return str(value)


def strict_json(value, indent: int | None = 2) -> str:
    """``value`` as strict JSON text (``allow_nan=False`` after ``plain``)."""
    return json.dumps(plain(value), indent=indent, allow_nan=False)


class NameTaken(ValueError):
    """A ``--name`` whose files already exist."""


def check_name(name: str) -> str:
    if not NAME_PATTERN.fullmatch(name) or name.endswith((".mcap", ".json", ".fcs", ".rrd")):
        raise ValueError(f"--name: {name!r} is not a usable file name; use letters, digits, '.', '_' and '-' "
                         "(at most 120, no directory and no extension), e.g. --name melanoma-lead-0.5")
    return name


def default_run_id(prefix: str = "stream") -> str:
    now = time.time()
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now))
    return f"{prefix}-{stamp}-{int(now * 1000) % 1000:03d}-{os.getpid()}"


def reserve_run(directory: Path, suffixes, name: str | None = None, attempts: int = 1000,
                prefix: str = "stream") -> str:
    """A run id whose files ``directory/ID.SUFFIX`` (one per suffix) did not exist and are now created, empty
    (the ``.json`` with the "running" placeholder). Raises ``NameTaken`` if ``name`` is given and taken."""
    base = name or default_run_id(prefix)
    for attempt in range(attempts):
        run_id = base if attempt == 0 else f"{base}-{attempt + 1}"
        created = []
        try:
            for suffix in suffixes:
                path = directory / f"{run_id}.{suffix}"
                descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
                created.append(path)
                with os.fdopen(descriptor, "w") as file:
                    if suffix == "json":
                        file.write(strict_json({**PLACEHOLDER_SUMMARY, "run_id": run_id}) + "\n")
            return run_id
        except FileExistsError as error:
            for path in created:
                path.unlink(missing_ok=True)
            if name is not None:
                raise NameTaken(f"--name: {error.filename} already exists (a run never overwrites another's "
                                "files); choose another --name or --output") from None
    raise OSError(f"no free run id in {directory} after {attempts} attempts")


def create_new(path: Path, mode: int = 0o666) -> None:
    """Create the empty file ``path``, which must not exist (``FileExistsError`` otherwise), with ``mode`` less the
    umask, as any file opened for writing; other ``OSError``s say it cannot be created there."""
    os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode))


def write_whole(path: Path, write) -> None:
    """Give ``path`` the contents ``write(temporary)`` writes into a new file beside it, moved in place with
    ``os.replace``: an interrupted or failed write (a full disk) never leaves a truncated file under the name,
    which keeps what it had (a reserved run's placeholder, or nothing). The file gets the umask's mode, as any
    file opened for writing. A failure names ``path``, not the temporary file."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    try:
        create_new(temporary)
        write(temporary)
        with open(temporary, "rb+") as file:
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        raise OSError(error.errno, error.strerror, str(path)) from None
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def write_into(path: Path, text: str) -> None:
    """Replace the contents of ``path`` (a file this run reserved) by ``text``, whole and durably."""
    write_whole(path, lambda temporary: Path(temporary).write_text(text))


def unique_directory(path: Path) -> Path:
    """A new directory ``path-2``, ``path-3``, ... beside ``path`` (created exclusively)."""
    for attempt in range(2, 1002):
        candidate = path.with_name(f"{path.name}-{attempt}")
        try:
            candidate.mkdir()
            return candidate
        except FileExistsError:
            continue
    raise OSError(f"no free directory name like {path}")


def unique_path(path: Path) -> Path:
    """``path`` if no file is there, else ``stem-2.suffix``, ``stem-3.suffix``, ... (created exclusively)."""
    for attempt in range(1000):
        candidate = path if attempt == 0 else path.with_name(f"{path.stem}-{attempt + 1}{path.suffix}")
        try:
            create_new(candidate, 0o644)
            return candidate
        except FileExistsError:
            continue
    raise OSError(f"no free file name like {path}")
