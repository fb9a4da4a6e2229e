"""`vcyto stream`: cells through the closed sorting loop (detector, controller, plant), with the run's files
(MCAP recording, FCS events, Gating-ML gate, JSON summary) and the Rerun view."""

from __future__ import annotations

import argparse
import sys

from controller.protocol import ControllerError

from .. import outputs
from ..arguments import Integer, Number
from ..options import (
    late_pulse_note,
    scenario_from,
    scenario_options,
    short_pulse_note,
    stream_options,
    stream_settings,
    tolerance_options,
    wire_controller,
    wire_options,
)
from ..restored import restored_warning
from .common import (
    EXIT_NUMERICAL,
    EXIT_SIGINT,
    EXIT_SIGTERM,
    RunStopped,
    UsageError,
    emit,
    output_directory,
    output_options,
    settle_collector,
    signals_seen,
)


def add_command(commands):
    stream = commands.add_parser("stream",
                                 help="run cells through the closed sorting loop (detector, controller, plant)")
    scenario_options(stream)
    tolerance_options(stream)
    stream_options(stream)
    stream.add_argument("--output", default="recordings", metavar="DIR",
                        help="where the run's files go: the MCAP recording, FCS 3.1 detector events, the gate "
                             "(Gating-ML 2.0) and a JSON summary (default recordings/; --output '' writes nothing)")
    stream.add_argument("--name", metavar="NAME",
                        help="name the run's files NAME.mcap, NAME.json, NAME.fcs, NAME.gating.xml, NAME.rrd (default "
                             "stream-DATE-TIME-MILLISECONDS-PID); a name whose files exist is refused")
    stream.add_argument("--no-record", action="store_true", help="no MCAP recording")
    stream.add_argument("--flush-every", type=Integer(low=1), default="400", metavar="N",
                        help="write the recording's per-step columns and flush it every N recorded steps (control "
                             "periods; with --tolerance, FE-IB steps): a crash loses at most the last N and the "
                             "steps still queued for the recording's thread (default 400)")
    stream.add_argument("--field-every", type=Integer(low=0), default="200", metavar="N",
                        help="record the velocity field every N recorded steps (control periods; with "
                             "--tolerance, FE-IB steps), 0 = never (default 200)")
    _timing_options(stream)
    _viewer_options(stream)
    output_options(stream)
    stream.set_defaults(handler=command_stream)


def _timing_options(parser: argparse.ArgumentParser):
    group = parser.add_argument_group("timing (docs/controllers.md: deadlines and missed decisions)")
    group.add_argument("--realtime", nargs="?", const="1", default=None, type=Number(low=1e-6, high=1e6),
                       metavar="FACTOR",
                       help="paced real time: device time follows the wall clock (FACTOR device seconds per wall "
                            "second, default 1); an answer later than its event's deadline is a missed decision. "
                            "Default: lock-step (the loop waits for every answer; results depend on the seed only)")
    wire_options(parser)


def _timing(args):
    from ..control import Timing
    return Timing(realtime=True, factor=args.realtime) if args.realtime is not None else Timing()


def _controller(args, settings, timing):
    """The run's controller, built before the run so that a broken one is a usage error (None: the built-in);
    a controller in another process is connected to (or started) here: the caller closes its port."""
    from .. import plugins, stream
    named = [option for option, given in (("--controller-connect", args.controller_connect),
                                          ("--controller-exec", args.controller_exec),
                                          ("--controller-from", settings.controller_from),
                                          ("--no-controller", args.no_controller)) if given is not None and given]
    if len(named) > 1:
        raise UsageError(f"{named[0]}: {named[1]} names the controller too: give one of them")
    reached = wire_controller(args)
    if reached is not None:
        return _wire_port(reached, timing)
    if settings.controller_from is None:
        return None
    try:
        return stream.settings_controller(settings)
    except plugins.PluginError as error:
        raise UsageError(f"--controller-from: {error}") from None


def _wire_port(reached, timing):
    """The port to a controller in another process (``vcyto.wire.WireController``): connected, or its process
    started; a bad command is a usage error, a controller that cannot be reached one line and exit 1."""
    option = reached.option
    try:
        return reached.open(timing)
    except (ControllerError, ConnectionError) as error:
        print(f"vcyto: error: {option}: {' '.join(str(error).split())}", file=sys.stderr)
        raise RunStopped(EXIT_NUMERICAL) from None
    except ValueError as error:
        raise UsageError(f"{option}: {error}") from None


def _plant(settings, scenario):
    """A plant of the user's (--plant-from), built before the run (a broken one is a usage error), else None."""
    from .. import plugins, stream
    if settings.plant_from is None:
        return None
    try:
        return stream.make_plant(scenario, settings)
    except plugins.PluginError as error:
        raise UsageError(f"--plant-from: {error}") from None


def _viewer_options(parser: argparse.ArgumentParser, live: bool = True):
    group = parser.add_argument_group("Rerun viewer (default: " + ("start the viewer installed with rerun-sdk if "
                                      "there is a display, else " if live else "") + "save an .rrd)")
    group.add_argument("--spawn", action="store_true",
                       help="start the Rerun viewer installed with rerun-sdk and stream to it (if it cannot start: "
                            "an .rrd instead)")
    group.add_argument("--connect", nargs="?", const="", metavar="URL",
                       help="stream to a running viewer (default rerun+http://127.0.0.1:9876/proxy; unreachable: "
                            "an .rrd instead)")
    group.add_argument("--viewer-bind", metavar="ADDRESS", default="127.0.0.1",
                       help="address a viewer started by vcyto listens on (default 127.0.0.1: this machine only; "
                            "0.0.0.0 opens port 9876 to the network)")
    group.add_argument("--save", metavar="FILE.rrd", help="write the Rerun view to this new file")
    group.add_argument("--no-viewer", action="store_true", help="no Rerun output")


def command_stream(args):
    scenario = scenario_from(args)
    settings = stream_settings(args, scenario)
    output = output_directory(args.output)
    if args.name is not None:
        if output is None:
            raise UsageError("--name: names the run's files in --output, which is '' (nothing is written)")
        try:
            outputs.check_name(args.name)
        except ValueError as error:
            raise UsageError(str(error)) from None
    for note in (late_pulse_note(settings.controller), short_pulse_note(settings.controller, scenario)):
        if note:
            print(f"vcyto: note: {note}", file=sys.stderr)
    timing = _timing(args)
    controller = _controller(args, settings, timing)
    try:
        plant = _plant(settings, scenario)
        return _stream_with(args, scenario, settings, output, dict(controller=controller, plant=plant, timing=timing))
    finally:                         # a controller in another process: said goodbye to (and stopped), whatever happens
        if controller is not None and callable(getattr(controller, "replies", None)):
            controller.close()


def _stream_with(args, scenario, settings, output, loop: dict):
    """The run with its files, once the controller, plant and timing (``loop``) are built."""
    from ..recording import runfiles
    signals_seen.clear()
    view = runfiles.choose_view(args, output is not None, spawn_by_default=True, error=UsageError)
    files = None
    # the run's files and recorders are created whole: a Ctrl-C meanwhile takes effect once they exist
    with runfiles.interrupts_deferred(signals_seen) as setting_up:
        if output is not None:
            try:
                files = runfiles.StreamFiles(output, args.name, record=not args.no_record,
                                             rrd=view.kind == "save" and view.path is None)
            except outputs.NameTaken as error:
                raise UsageError(str(error)) from None
        background = _open_sinks(args, scenario, settings, view, files)
    # a signal after the loop (while the sinks close, a stalled viewer's bounded wait included, and the files are
    # written) waits for them: the run's files are finished and its summary says how it ended, then it exits
    with runfiles.interrupts_deferred(signals_seen) as finishing:
        result, stopped, unwritten = _run_with_sinks(args, scenario, settings, view, files, background,
                                                     setting_up.pending, loop)
        if unwritten is not None:
            _report_write_failure(args, result, unwritten, view, files, settings, scenario)
        _report_stream(args, result, stopped, view, files, settings, scenario)
    if finishing.pending:
        name = signals_seen.get("last", "SIGINT")
        print(f"vcyto: {name} came as the run's files were finished; they are whole and the summary's status is "
              f"{result.get('status', 'complete')!r}", file=sys.stderr)
        return EXIT_SIGTERM if name == "SIGTERM" else EXIT_SIGINT
    return _partial_status(args, result)


def _open_sinks(args, scenario, settings, view, files):
    """The MCAP and Rerun sinks of the run, on a background thread (their work overlaps the plant's solve), or
    None."""
    from ..recording.sinks import BackgroundSinks, Deferred
    sinks = []
    if files is not None and files.path("mcap") is not None:
        from ..recording.mcap import McapRecorder
        sinks.append(McapRecorder(files.path("mcap"), _run_metadata(scenario, settings),
                                  flush_every=args.flush_every, field_every=args.field_every))
    if view.kind is not None and (view.kind == "connect" or view.path or files is not None):
        # built on the sinks' thread: importing Rerun and opening the recording overlap the plant's set-up
        sinks.append(Deferred(lambda: _rerun_sink(args, scenario, settings, view, files), args.field_every))
    return BackgroundSinks(sinks) if sinks else None


def _run_with_sinks(args, scenario, settings, view, files, background, interrupted: bool, loop: dict):
    """Run the loop with the sinks; (summary, StreamStopped or None, the OSError of a file that could not be
    written or None). The sinks are closed whatever happens; a run stopped by Ctrl-C, SIGTERM, a numerical
    failure or a write that failed (a full disk) returns its partial summary. ``interrupted``: a signal came
    while the files and sinks were created; the run stops before its first step. ``loop``: the
    controller, plant and timing for ``run_stream``."""
    from .. import stream
    from ..progress import Progress
    from ..recording import runfiles
    progress = Progress(quiet=args.quiet or args.json)
    stopped, failed, unwritten = None, True, None
    try:
        with runfiles.signals_as_interrupt(signals_seen):
            try:
                if interrupted:
                    raise KeyboardInterrupt
                result = stream.run_stream(scenario, settings, progress, sinks=[background] if background else [],
                                           table=files.path("cells.parquet") if files is not None else None,
                                           checkpoint=files.checkpoint(settings, scenario) if files else None,
                                           ready=settle_collector, **loop)
            except stream.StreamStopped as error:
                stopped, result = error, error.result
                if isinstance(error.__cause__, OSError) and not isinstance(error.__cause__, ConnectionError):
                    # a file of the run could not be written (a lost controller is a failed run, not a file)
                    stopped, unwritten = None, error.__cause__
            except OSError as error:                       # found after the loop: the summary is not known
                unwritten = error
                result = runfiles.stopped_summary(settings, "stopped: a file of the run could not be written")
            except KeyboardInterrupt:                      # before the loop began (setting up the plant)
                stopped = stream.StreamStopped("interrupted", "interrupted while setting up, before the first step",
                                               runfiles.stopped_summary(settings, "interrupted while setting up"))
                result = stopped.result
                stream.announce_end([background] if background else [], result)   # the recording says so too
            except (ControllerError, ConnectionError) as error:   # the controller's start (the wire's handshake)
                if isinstance(error, BrokenPipeError):
                    raise
                reason = f"controller: {' '.join(str(error).split())}"
                stopped = stream.StreamStopped("failed", reason, {**runfiles.stopped_summary(settings, reason),
                                                                  "status": "failed"})
                result = stopped.result
                stream.announce_end([background] if background else [], result)
        failed = False
    finally:                                               # the sinks are closed once, whatever happened
        notes, closing = _close_run(progress, background, files, failed)
        view.notes += notes
        view.frames = _frames(background)
    if unwritten is None and closing is not None and files is not None:
        unwritten = closing
    elif unwritten is None and closing is not None:
        raise closing
    if unwritten is not None:
        result.update(status="failed", reason=f"cannot write {unwritten.filename or 'a file'}: "
                                              f"{unwritten.strerror or unwritten}")
    return result, stopped, unwritten


def _frames(background) -> dict | None:
    """The frames of the live view (``vcyto.sinks.LiveView``): handed to it and dropped; None without one."""
    from ..recording.sinks import LiveView
    live = [sink for sink in (background.sinks if background is not None else ()) if isinstance(sink, LiveView)]
    return {"frames": live[0].frames, "frames_dropped": live[0].dropped} if live else None


def _close_run(progress, background, files, failed: bool) -> tuple[list[str], OSError | None]:
    """Close the progress line and the sinks (a full disk surfaces here too); (notes on a viewer that went away,
    the OSError of a file that could not be written or None). Files reserved but never written are removed if
    the run or the closing failed otherwise."""
    from ..recording import runfiles
    progress.close()
    try:
        return runfiles.close_quietly(background, files and files.path("mcap")), None
    except OSError as error:
        return [], error
    except BaseException:
        failed = True
        raise
    finally:
        if failed and files is not None:
            files.discard_unwritten()


def _rerun_sink(args, scenario, settings, view, files) -> list:
    """The Rerun sink of ``view``; if Rerun refuses it (a viewer gone between the check and the connection, a
    file it cannot create), one line says so and the view goes to a new .rrd, else there is none."""
    from ..recording import runfiles
    from ..recording.rerunlog import POINT_LIKE, RerunSink
    from ..recording.sinks import LiveView
    try:
        sink = RerunSink(scenario, settings.detector.window, view.target(files and files.path("rrd")),
                         field_every=args.field_every, membranes=settings.model not in POINT_LIKE)
        return [LiveView(sink) if view.kind == "connect" else sink]      # a viewer never holds the loop
    except (RuntimeError, OSError) as problem:
        reason = " ".join(str(problem).split())[:160]
        if view.kind == "connect" and files is not None:
            view.kind, view.path = "save", outputs.unique_path(files.directory / f"{files.run_id}.rrd")
            runfiles.say(f"the Rerun viewer refused the connection ({reason}); saving the view to {view.path}")
            return _rerun_sink(args, scenario, settings, view, files)
        runfiles.say(f"cannot write the Rerun view ({reason}); the run goes on without it")
        view.kind = None
        return []


def _report_write_failure(args, result, unwritten: OSError, view, files, settings, scenario):
    """A run stopped because one of its files could not be written (a full disk): what can be written is, one
    line names the file, the cause and what was kept, and the exit status is 1 (``RunStopped``)."""
    from ..recording import runfiles
    kept, lost = files.finish_what_can(result, settings, scenario) if files is not None else ([], [])
    if view.kind == "save" and view.path is not None and view.path.exists() and view.path.stat().st_size > 0:
        kept.append(str(view.path))
    for note in view.notes:
        runfiles.say(note)
    marked = "; the summary's status is \"failed\"" if files is not None and str(files.path("json")) in kept else ""
    what = f"kept (what ran up to the failure{marked}): {', '.join(kept)}" if kept else "nothing could be kept"
    lost = f"; not written: {', '.join(lost)}" if lost else ""
    runfiles.say(f"error: {unwritten.filename or 'a file of the run'}: cannot write it: "
                 f"{unwritten.strerror or unwritten}; the run stopped at t = "
                 f"{result.get('simulated_time_ms', 0):.3f} ms; {what}{lost}")
    raise RunStopped(EXIT_NUMERICAL)


def _report_stream(args, result, stopped, view, files, settings, scenario):
    """Write the FCS events and the summary (partial ones marked), print the report and the paths; a stopped
    run then ends with its exit status (130 SIGINT, 143 SIGTERM, 1 numerical failure)."""
    from .. import stream
    from ..recording import runfiles
    if stopped is not None and stopped.status == "interrupted":
        result["reason"] = f"interrupted by {signals_seen.get('last', 'SIGINT')}"
    lines = stream.report_lines(result) if "statistics" in result and "events" in result["statistics"] else []
    result["files"] = {}
    if files is not None and files.path("mcap") is not None:
        mcap = files.path("mcap")
        result["files"]["mcap"] = str(mcap)
        lines.append(f"recording: {mcap} (MCAP; replay with: {runfiles.typed('vcyto')} replay {mcap})")
    if view.kind is not None and (view.kind == "connect" or view.path or files is not None):
        rrd = files.path("rrd") if files is not None else None
        result["files"]["rerun"] = view.url if view.kind == "connect" else str(view.path or rrd)
        lines.append(f"Rerun: {view.describe(rrd)}")
        if view.frames is not None:
            result["view"] = view.frames
            lines[-1] += _dropped_words(view.frames)
    if files is not None:
        result["run_id"] = files.run_id
        result["files"].update({"fcs": str(files.path("fcs")), "gatingml": str(files.path("gating.xml")),
                                "cells": str(files.path("cells.parquet")), "summary": str(files.path("json"))})
        files.finish(result, settings, scenario)
        lines.append(f"detector events: {files.path('fcs')} (FCS 3.1; classification gate: "
                     f"{files.path('gating.xml')}, Gating-ML 2.0); per-cell table: {files.path('cells.parquet')} "
                     f"(Parquet); summary: {files.path('json')}")
    for note in view.notes:
        runfiles.say(note)
    if (warning := restored_warning((result.get("statistics") or {}).get("area_restored"))) is not None:
        runfiles.say(warning)
    emit(args, result, lines)
    if stopped is None:
        return
    written = ", ".join(result["files"][key] for key in ("mcap", "summary", "fcs", "rerun") if key in result["files"]
                        and not result["files"][key].startswith(("rerun+http", "http", "tcp")))
    kept = f"; what ran is in {written}" if written else ""
    if stopped.status == "failed":
        runfiles.say(f"error: the run failed in the step after t = {result.get('simulated_time_ms', 0):.3f} ms: "
                     f"{' '.join(stopped.reason.split())}{kept}")
        raise RunStopped(EXIT_NUMERICAL)
    signal_name = signals_seen.get("last", "SIGINT")
    runfiles.say(f"interrupted by {signal_name} at t = {result.get('simulated_time_ms', 0):.3f} ms{kept} "
                 "(the summary's status is \"interrupted\")")
    raise RunStopped(EXIT_SIGTERM if signal_name == "SIGTERM" else EXIT_SIGINT)


def _dropped_words(frames: dict) -> str:
    """What the live view missed, said after where it went."""
    if not frames["frames_dropped"]:
        return f"; every one of its {frames['frames']:,} frames shown"
    return (f"; {frames['frames_dropped']:,} of its {frames['frames']:,} frames dropped (the view did not keep up; "
            "the run never waits for it)")


def _partial_status(args, result) -> int:
    """Exit status of a finished run: 0, or 1 for a run cut short that the user did not cap (docs/usage.md)."""
    if result.get("status", "complete") == "complete":
        return 0
    asked = getattr(args, "allow_partial", False)
    print(f"vcyto: {'note' if asked else 'error'}: the run is partial ({result['status']}): {result['reason']}"
          + ("" if asked else "; its statistics are not those of the whole sample (--allow-partial to accept it)"),
          file=sys.stderr)
    return 0 if asked else EXIT_NUMERICAL


def _run_metadata(scenario, settings) -> dict:
    import numpy
    import scipy
    import skfem

    from .. import __version__
    from ..config import scenario_to_toml
    return {"scenario_toml": scenario_to_toml(scenario), "seed": settings.seed, "model": settings.model,
            "arrivals": settings.arrivals, "detector": settings.detector, "controller": settings.controller,
            "command_line": " ".join(sys.argv), "vcyto": __version__, "numpy": numpy.__version__,
            "scipy": scipy.__version__, "scikit-fem": skfem.__version__, "python": sys.version.split()[0]}
