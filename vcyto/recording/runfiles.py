"""Where a run's view and files go, and how they are finished whatever way the run ends.

- ``choose_view``: the Rerun target of ``--save`` / ``--connect`` / ``--spawn`` / the default. A viewer that
  cannot be started or reached is said in one line on stderr and the view is saved to an ``.rrd`` instead;
  the viewer vcyto starts is the one installed with rerun-sdk and listens on 127.0.0.1 unless
  ``--viewer-bind`` says otherwise.
- ``StreamFiles``: the files of one ``vcyto stream`` run, reserved exclusively before any work
  (``vcyto.outputs.reserve_run``) and written at the end, complete or not (the summary's ``status`` says).
- ``close_quietly``: closes the sinks, turning a viewer that went away into a note instead of a crash.
- ``typed``: how to type ``vcyto`` or ``rerun`` in the hints a run prints (their path when the environment is
  not activated).
"""

from __future__ import annotations

import os
import shutil
import signal
import sys
from dataclasses import dataclass, field
from pathlib import Path

from .. import outputs


@dataclass
class View:
    kind: str | None                  # "save", "connect" or None (no Rerun output)
    url: str = ""                     # connect: the viewer's URL
    path: Path | None = None          # save: the .rrd (None: the run's own NAME.rrd, reserved with its files)
    notes: list = field(default_factory=list)
    frames: dict | None = None        # connect: the frames of the live view, handed to it and dropped

    def target(self, run_path=None):
        """The ``RerunLogger`` target tuple."""
        if self.kind == "connect":
            return ("connect", self.url)
        return ("save", self.path or run_path)

    def describe(self, run_path=None) -> str:
        return f"streamed to the viewer at {self.url}" if self.kind == "connect" else \
            f"saved to {self.path or run_path} (open with: {typed('rerun')} {self.path or run_path})"


def typed(command: str) -> str:
    """How to type ``command`` (a script of this environment: ``vcyto``, ``rerun``) so that it runs this
    environment's: its name when PATH finds that one (an activated venv), else its path (relative when shorter)."""
    here = Path(sys.executable).parent / command
    if not here.is_file():
        return command
    found = shutil.which(command)
    if found and Path(found).resolve() == here.resolve():
        return command
    relative = os.path.relpath(here)
    return relative if not relative.startswith("..") else str(here)


def say(message: str) -> None:
    print(f"vcyto: {message}", file=sys.stderr, flush=True)


def choose_view(args, have_default_file: bool, spawn_by_default: bool, error) -> View:
    """The view ``args`` ask for; ``error`` is the exception class for bad input. ``have_default_file``: an
    .rrd can be saved when no viewer is reached (else the view is dropped, with a note)."""
    from . import viewer
    bind = getattr(args, "viewer_bind", None)
    if bind is not None:
        import ipaddress
        try:
            ipaddress.ip_address(bind)
        except ValueError:
            raise error(f"--viewer-bind: {bind[:60]!r} is not an IP address; give one of this machine's, e.g. "
                        "127.0.0.1 (this machine only) or 0.0.0.0 (every interface)") from None
    if getattr(args, "no_viewer", False):
        given = [name for name, value in (("--save", args.save), ("--spawn", getattr(args, "spawn", False)),
                                          ("--connect", getattr(args, "connect", None) is not None)) if value]
        if given:
            raise error(f"--no-viewer: cannot be combined with {' and '.join(given)}; drop one of them")
        return View(None)
    if args.save:
        return View("save", path=_new_file(args.save, "--save", error))
    fallback = View("save") if have_default_file else View(None)
    if args.connect is not None:
        url = args.connect or f"rerun+http://127.0.0.1:{viewer.VIEWER_PORT}/proxy"
        try:
            host, port = viewer.parse_viewer_url(url)
        except ValueError as problem:
            raise error(f"--connect: {problem}") from None
        problem = viewer.viewer_problem(host, port, secure=url.startswith("rerun+https"))
        if problem is None:
            return View("connect", url=url)
        return _fall_back(fallback, f"no Rerun viewer answers at {url}: {problem}")
    if not (args.spawn or spawn_by_default):
        return fallback
    if not viewer.has_display():
        if args.spawn:
            return _fall_back(fallback, "no display for --spawn (DISPLAY and WAYLAND_DISPLAY are unset)")
        return fallback
    try:
        url, done = viewer.start_viewer(bind=getattr(args, "viewer_bind", None) or "127.0.0.1")
    except viewer.ViewerUnavailable as problem:
        return _fall_back(fallback, f"cannot start a Rerun viewer: {problem}")
    return View("connect", url=url, notes=[done])


def _fall_back(fallback: View, why: str) -> View:
    where = "saving the view to an .rrd file instead" if fallback.kind == "save" else "no view is kept"
    say(f"{why}; {where}")
    return fallback


def _new_file(text: str, option: str, error) -> Path:
    """An explicit output file: its directory exists and it does not (a run never overwrites a file)."""
    path = Path(text)
    if path.is_dir():
        raise error(f"{option}: {text} is a directory; give a file name such as {Path(text) / 'run.rrd'}")
    if path.exists():
        raise error(f"{option}: {text} already exists; vcyto never overwrites a file: choose another name")
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise error(f"{option}: cannot write {text}: directory {directory} does not exist")
    if path.suffix != ".rrd":
        raise error(f"{option}: {text} should end in .rrd (a Rerun recording)")
    try:                                # can it be created? (a read-only directory, a full disk; as root too)
        outputs.create_new(path)
        path.unlink()
    except FileExistsError:
        raise error(f"{option}: {text} already exists; vcyto never overwrites a file: choose another name") from None
    except OSError as problem:
        raise error(f"{option}: cannot write {text} ({problem.strerror}); choose a directory you can write to") \
            from None
    return path


class StreamFiles:
    """The files of one stream run in ``directory``: ``ID.mcap`` (when recording), ``ID.rrd`` (when the view is
    saved there), ``ID.fcs``, ``ID.gating.xml``, ``ID.cells.parquet`` (the per-cell table) and ``ID.json``, all
    created exclusively up front."""

    def __init__(self, directory: Path, name: str | None, record: bool, rrd: bool):
        suffixes = (["mcap"] if record else []) + (["rrd"] if rrd else []) + ["fcs", "gating.xml", "cells.parquet",
                                                                                  "json"]
        self.directory = directory
        self.run_id = outputs.reserve_run(directory, suffixes, name)
        self.suffixes = suffixes
        self._checkpoint = None

    def path(self, suffix: str) -> Path | None:
        return self.directory / f"{self.run_id}.{suffix}" if suffix in self.suffixes else None

    def finish(self, result: dict, settings=None, scenario=None) -> tuple[Path, Path]:
        """Write the FCS events, the classification gate (Gating-ML 2.0) and the JSON summary of ``result``
        (complete or partial) into the reserved files."""
        from . import fcs, gatingml
        fcs_path, summary_path = self.path("fcs"), self.path("json")
        keywords = {"VCYTO_COMMAND": _command(), "VCYTO_STATUS": result.get("status", "complete"),
                    "VCYTO_RUN_ID": self.run_id}
        if self._checkpoint is not None and settings is not None and "cells" not in result:
            # a long run: its checkpoint's events and the rest, in bounded memory (not read back from the table)
            self._checkpoint.finish_events(result, keywords)
        else:
            fcs.write_fcs(fcs_path, result, keywords, settings=settings, scenario=scenario)
        if settings is not None:
            gatingml.write_gatingml(self.path("gating.xml"), settings.detector.gate)
        outputs.write_into(summary_path, outputs.strict_json(result) + "\n")
        return fcs_path, summary_path

    def finish_what_can(self, result: dict, settings=None, scenario=None) -> tuple[list[str], list[str]]:
        """``finish`` after a write failed (a full disk): each of the FCS events, the gate and the summary is
        written if it can be, the others are left out (their reservations removed: no placeholder claims a run);
        (the files kept, including the recording and the view as far as they were flushed; the files lost)."""
        from . import fcs, gatingml
        writers = {"fcs": lambda path: fcs.write_fcs(path, result, {
                       "VCYTO_COMMAND": _command(), "VCYTO_STATUS": result.get("status", "failed"),
                       "VCYTO_RUN_ID": self.run_id}, settings=settings, scenario=scenario),
                   "json": lambda path: outputs.write_into(path, outputs.strict_json(result) + "\n")}
        if settings is not None:
            writers["gating.xml"] = lambda path: gatingml.write_gatingml(path, settings.detector.gate)
        kept, lost = [], []
        for suffix in self.suffixes:
            path = self.path(suffix)
            if suffix in writers:
                try:
                    writers[suffix](path)
                except OSError:
                    path.unlink(missing_ok=True)
                    lost.append(str(path))
                    continue
            if path.exists() and path.stat().st_size > 0:
                kept.append(str(path))
            else:
                path.unlink(missing_ok=True)
                lost.append(str(path))
        return kept, lost

    def checkpoint(self, settings, scenario):
        """The ``vcyto.recording.checkpoint.Checkpoint`` that writes this run's summary, FCS events and gate as it
        goes."""
        from .checkpoint import Checkpoint
        self._checkpoint = Checkpoint(self.path("json"), self.path("fcs"), self.path("gating.xml"), self.run_id,
                                      settings, scenario, {"VCYTO_COMMAND": _command(), "VCYTO_RUN_ID": self.run_id})
        return self._checkpoint

    def discard_unwritten(self) -> None:
        """Remove the reserved summary and events that were never written (a run that failed before it ran)."""
        for suffix in ("fcs", "gating.xml", "cells.parquet", "json"):
            path = self.path(suffix)
            if path is not None and path.exists() and (path.stat().st_size == 0 or _is_placeholder(path)):
                path.unlink()


def _command() -> str:
    """The command as typed, for the FCS keyword VCYTO_COMMAND (whose value must not begin or end with the
    delimiter "/", as a path would)."""
    return " ".join(["vcyto", *sys.argv[1:]]).rstrip("/ ") or "vcyto"


def _is_placeholder(path: Path) -> bool:
    try:
        return '"status": "running"' in path.read_text()[:200]
    except (OSError, UnicodeDecodeError):
        return False


def close_quietly(sink, recording=None) -> list[str]:
    """Close ``sink`` (the sinks of a run); a failure of the live view is a note, others propagate."""
    if sink is None:
        return []
    try:
        sink.close()
    except (RuntimeError, ConnectionError) as problem:      # the viewer went away: the MCAP has everything
        again = f"{typed('vcyto')} replay {recording} shows the run again" if recording else \
            "the view of the run is incomplete"
        return [f"the Rerun viewer stopped receiving ({' '.join(str(problem).split())[:160]}); {again}"]
    return []


class _SignalHandlers:
    """Within the block SIGINT and SIGTERM go to ``handle`` (on the main thread; elsewhere nothing changes)."""

    def __init__(self, seen: dict):
        self.seen = seen

    def handle(self, signum, frame):
        raise NotImplementedError

    def __enter__(self):
        self._previous = {}
        for number in (signal.SIGTERM, signal.SIGINT):
            try:
                if signal.getsignal(number) is signal.SIG_IGN:     # told to ignore it (a script's `cmd &`): keep
                    continue
                self._previous[number] = signal.signal(number, self.handle)
            except ValueError:          # not the main thread
                pass
        return self

    def __exit__(self, *exc):
        for number, previous in self._previous.items():
            signal.signal(number, previous)
        return False


class signals_as_interrupt(_SignalHandlers):
    """Within the block SIGTERM raises KeyboardInterrupt, as Ctrl-C does, so files are finished the same way;
    ``seen`` (a dict) gets "last" = the name of the signal that arrived."""

    def handle(self, signum, frame):
        self.seen["last"] = signal.Signals(signum).name
        if in_import_system(frame):
            # raised here it could leave the import system's lock held (its code takes locks outside ``try``, and
            # its weakref callbacks swallow exceptions): the sinks' thread then waits on an import for ever and
            # the loop on the sinks. The signal is raised again, handled at the next instruction, until it is out.
            signal.raise_signal(signum)
            return
        raise KeyboardInterrupt


def in_import_system(frame) -> bool:
    """Whether ``frame`` is the import system's own code (importlib's frozen bootstrap)."""
    return frame is not None and frame.f_code.co_filename.startswith("<frozen importlib")


class interrupts_deferred(_SignalHandlers):
    """Within the block SIGINT and SIGTERM are noted, not raised, so that what must not be cut in half (creating a
    run's files and recorders: an MCAP header half written is a torn file) completes; ``pending`` says whether
    one arrived (``seen["last"]`` names it) and the caller then stops as if it had arrived just after."""

    def __init__(self, seen: dict):
        super().__init__(seen)
        self.pending = False

    def handle(self, signum, frame):
        self.seen["last"] = signal.Signals(signum).name
        self.pending = True


class signals_held(_SignalHandlers):
    """Within the block SIGINT and SIGTERM wait; one that came is raised again right after it, for the handler
    outside (the command line's KeyboardInterrupt). For what an exception must not cut: a queue's lock held
    for ever, a chunk's rows half appended. On a thread other than the main one nothing changes."""

    def __init__(self):
        super().__init__({})
        self.caught: list[int] = []

    def handle(self, signum, frame):
        self.caught.append(signum)

    def __exit__(self, *exc):
        super().__exit__(*exc)
        for number in self.caught:
            signal.raise_signal(number)
        return False


def stopped_summary(settings, reason: str) -> dict:
    """The summary of a run stopped before its loop began (no cell has moved)."""
    return {"status": "interrupted", "reason": reason, "cells": [], "statistics": {"cells": 0},
            "model": settings.model, "seed": settings.seed, "simulated_time_ms": 0.0}
