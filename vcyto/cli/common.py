"""What every command shares: exit statuses, the run-stopped signal, progress on stderr, --json/--quiet, output
paths checked (and reserved) before any work, and the number lists several options take."""

from __future__ import annotations

import argparse
import gc
import math
import os
import shutil
import sys
from contextlib import contextmanager
from pathlib import Path

from .. import outputs, units
from ..options import UsageError
from ..outputs import strict_json

__all__ = ["EXIT_INPUT", "EXIT_INTERNAL", "EXIT_NUMERICAL", "EXIT_SIGINT", "EXIT_SIGTERM", "RunStopped", "UsageError",
           "emit", "non_negative_list", "output_directory", "output_options", "output_path", "plain_number",
           "positive_list", "signals_seen", "stderr_progress", "check_switches", "own_process", "settle_collector"]


EXIT_INPUT = 2
EXIT_NUMERICAL = 1
EXIT_INTERNAL = 3
EXIT_SIGINT = 130           # 128 + SIGINT, as shells report it
EXIT_SIGTERM = 143          # 128 + SIGTERM
EXIT_PIPE = 141             # 128 + SIGPIPE: the reader of stdout went away (`vcyto ... | head`)
MIN_FREE_BYTES = 100e6      # a stream's recordings
SMALL_FILES_BYTES = 5e6     # tables, summaries and figures (calibrate, sweep, tradeoff)


# vcyto's switches read from the environment -> the values each takes (case and surrounding spaces aside)
ON_OFF = ("on", "off", "1", "0", "true", "false", "yes", "no")
SWITCHES = {"VCYTO_CACHE": ON_OFF, "VCYTO_C_KERNELS": ON_OFF, "VCYTO_PREFETCH": ("1", "0"),
            "VCYTO_SPLIT_SOLVE": ("1", "0"), "VCYTO_OWN_SUBSTITUTIONS": ("1", "0")}


def check_switches(environment=None) -> None:
    """Refuse, before any work, a switch of ``SWITCHES`` set to a value it does not take (``VCYTO_CACHE=maybe``
    would otherwise be read as on without a word)."""
    environment = os.environ if environment is None else environment
    for name, values in SWITCHES.items():
        value = environment.get(name)
        if value is not None and value.strip().lower() not in values:
            shown = " or ".join(values[:2])
            raise UsageError(f"{name}: {value[:40]!r} is not a value of this switch; set it to {shown} (or unset it)")


class RunStopped(Exception):
    """A run that stopped early and has said so (files written, paths printed); ``status`` is the exit status."""

    def __init__(self, status: int):
        super().__init__(status)
        self.status = status


signals_seen: dict[str, str] = {}      # "last": the name of the last signal turned into KeyboardInterrupt

# Young objects allocated between two collections during a run, in the executable's own process (Python's default:
# 700). A recorded sort makes and keeps for a while many small objects a step (records, cells' truths, the recorders'
# rows): at 700 the collector walked them ~1,100 times and their older generation ~100 times per 2x10^4 events.
COLLECTOR_THRESHOLD = 7000
_own_process = False


def own_process() -> None:
    """Called by the ``vcyto`` executable (``vcyto.cli.run``) for its own process: ``settle_collector`` acts only
    there (a Python user's process keeps its collector as it is)."""
    global _own_process
    _own_process = True


def settle_collector() -> None:
    """Once a run is set up (its plant built: the flows, the compiled kernels; its recorders open), in the
    executable's own process only: what exists then is frozen (``gc.freeze``: no later collection walks it again,
    as the executable does after its imports, ``vcyto.__main__``) and the youngest generation is collected every
    ``COLLECTOR_THRESHOLD`` allocations. Measured on the 40,000 cells offered of ``vcyto bench sort --no-rerun``
    (19,929 events, the MCAP recorded; four runs on a loaded 2-core host): 0.37-0.78 s of collections in a 6 s loop,
    0.20-0.23 s with both."""
    if not _own_process:
        return
    gc.freeze()
    gc.set_threshold(COLLECTOR_THRESHOLD, *gc.get_threshold()[1:])


def stderr_progress(quiet: bool):
    def report(message: str):
        if not quiet:
            print(f"  .. {message}", file=sys.stderr, flush=True)
    return report


def output_options(parser: argparse.ArgumentParser):
    parser.add_argument("--json", action="store_true", help="print a machine-readable result on stdout")
    parser.add_argument("--quiet", action="store_true", help="no progress messages on stderr")


def output_path(path: str | None, default: bool = False, option: str = "--png", suffix: str = ".png") -> Path | None:
    """Check before any work that an output file can be written, and reserve it: a file that exists is never
    overwritten (a default name becomes NAME-2, NAME-3, ...; a name the user gave is refused). A file that cannot
    be written is bad input (``UsageError`` naming ``option``), refused before the run."""
    if path is None:
        return None
    target = Path(path)
    if suffix and target.suffix.lower() != suffix:
        raise UsageError(f"{option}: {path[:80]} does not end in {suffix}, but the file written is one; name it "
                         f"e.g. {target.with_suffix(suffix).name[:80]}")
    directory = target.parent if str(target.parent) else Path(".")
    if default:
        directory.mkdir(parents=True, exist_ok=True)
    if not directory.is_dir():
        raise UsageError(f"{option}: cannot write {path}: {directory} is not an existing directory")
    if not os.access(directory, os.W_OK):
        raise UsageError(f"{option}: cannot write {path}: the directory {directory} is not writable")
    if default:
        return outputs.unique_path(target)
    if target.exists():
        raise UsageError(f"{option}: {path} exists: a run never overwrites a file; choose another name or remove it")
    return target


@contextmanager
def removed_unless_written(path: Path | None):
    """Around the work that writes ``path`` (a file ``output_path`` reserved): if that work ends with an error or an
    interrupt before writing it, the empty file is removed, so a failed run leaves no empty file holding the name."""
    try:
        yield path
    except BaseException:
        if path is not None and path.is_file() and path.stat().st_size == 0:
            path.unlink()
        raise


def emit(args, result: dict, lines: list[str]):
    if args.json:
        print(strict_json(result))
    else:
        print("\n".join(lines))


def output_directory(path: str | None, option: str = "--output", min_free: float = MIN_FREE_BYTES,
                     made: list | None = None) -> Path | None:
    """Create (if needed) and check the output directory before any work; a directory that cannot be created or
    written, or with less than ``min_free`` bytes free (recordings need room; tables and figures little), is bad
    input (``UsageError`` naming ``option``), refused before the run, and a directory created here is removed
    again. ``made`` (a list) receives the directories created here, innermost first (``remove_if_empty``)."""
    if path is None or path == "":
        return None
    directory = Path(path)
    try:
        created = [p for p in (directory, *directory.parents) if not p.exists()]    # innermost first
    except OSError as error:            # a name too long for the filesystem, a loop of links
        raise UsageError(f"{option}: cannot use the directory {path[:60]!r}{'...' if len(path) > 60 else ''} "
                         f"({error.strerror}); choose a shorter or another path") from None
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise UsageError(f"{option}: cannot create the directory {path} ({error.strerror}); choose a directory "
                         "you can write to") from None
    try:
        if not os.access(directory, os.W_OK):
            raise UsageError(f"{option}: the directory {path} is not writable; choose a directory you can write to")
        free = shutil.disk_usage(directory).free
        if free < min_free:
            raise UsageError(f"{option}: only {free / 1e6:.0f} MB free in {path}: this command's files need at "
                             f"least {min_free / 1e6:.0f} MB; free some space or choose another {option}")
    except UsageError:
        remove_if_empty(created)        # empty: made just now
        raise
    if made is not None:
        made.extend(created)
    return directory


def remove_if_empty(directories) -> None:
    """Remove each of ``directories`` (innermost first) that is empty: what a run that saved nothing created."""
    for directory in directories:
        try:
            directory.rmdir()
        except OSError:                 # not empty (or gone): keep it and everything outside it
            return


def positive_list(text: str, option: str, example: str, parse) -> list[float]:
    return _number_list(text, option, example, parse, lambda v: v > 0, "positive")


def non_negative_list(text: str, option: str, example: str) -> list[float]:
    return _number_list(text, option, example, plain_number(option), lambda v: v >= 0, "non-negative")


def plain_number(option: str):
    return lambda part: units.parse_quantity(part, "dimensionless", field=option)


def _number_list(text: str, option: str, example: str, parse, valid, kind: str) -> list[float]:
    try:
        values = [parse(part) for part in text.split(",")]
    except ValueError:
        values = []
    if not values or not all(math.isfinite(v) and valid(v) for v in values):
        raise UsageError(f"{option}: needs {kind} numbers separated by commas, such as {example} (got {text!r})")
    return values
