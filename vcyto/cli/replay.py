"""`vcyto replay`: re-log an MCAP recording written by `vcyto stream` to Rerun."""

from __future__ import annotations

from pathlib import Path

from sim.model.scenario import ScenarioError

from .. import outputs
from .common import UsageError, emit, output_options


def add_command(commands):
    replay_parser = commands.add_parser("replay", help="re-log an MCAP recording to Rerun")
    replay_parser.add_argument("file", metavar="FILE.mcap", help="a recording written by vcyto stream")
    replay_parser.add_argument("--spawn", action="store_true", help="start a Rerun viewer (needs a display)")
    replay_parser.add_argument("--connect", nargs="?", const="", metavar="URL", help="stream to a running viewer")
    replay_parser.add_argument("--save", metavar="FILE.rrd", help="write an .rrd file (default: next to the recording)")
    output_options(replay_parser)
    replay_parser.set_defaults(handler=command_replay)


def command_replay(args):
    from ..recording import runfiles
    from ..recording.replay import ReplayError, replay
    path = Path(args.file)
    if not path.is_file():
        raise UsageError(f"FILE: the recording {args.file} does not exist or is not a file; give the path of an "
                         ".mcap that vcyto stream wrote")
    view = runfiles.choose_view(args, True, spawn_by_default=False, error=UsageError)
    if view.kind == "save" and view.path is None:
        try:
            view.path = outputs.unique_path(path.with_suffix(".replay.rrd"))
        except OSError as error:
            raise UsageError(f"cannot write the replay next to the recording ({error.strerror}); give --save "
                             "FILE.rrd in a directory you can write to") from None
    try:
        result = replay(path, view.target())
    except (ReplayError, KeyError, TypeError, ValueError, IndexError, AttributeError) as error:
        if view.kind == "save" and view.path.exists():
            view.path.unlink(missing_ok=True)          # ours: created for this replay
        if isinstance(error, (ReplayError, ScenarioError)):
            raise UsageError(str(error)) from None
        raise UsageError(f"{path}: a message of the recording is malformed ({type(error).__name__}: "
                         f"{' '.join(str(error).split())[:120]}); it was not written by this vcyto") from None
    lines = [f"replayed {result['steps']} steps ({result['messages']} messages, "
             f"up to t = {result['last_time_ms']:.3f} ms) from {path}"]
    if result["damaged"]:
        lines.append(f"  the file is damaged or truncated ({result['problem']}): everything before the damage "
                     "was replayed, the rest is lost")
    if result["run_status"] not in (None, "complete"):
        lines.append(f"  the recorded run is partial: it ended {result['run_status']}"
                     + (f" ({result['run_reason']})" if result["run_reason"] else ""))
    elif result["run_status"] is None and not result["damaged"]:
        lines.append("  the recording has no end record: the run that wrote it was killed or is still running")
    lines.append(f"  Rerun: {view.describe()}")
    result["target"] = view.url if view.kind == "connect" else str(view.path)
    for note in view.notes:
        runfiles.say(note)
    emit(args, result, lines)
