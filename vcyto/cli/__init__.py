"""The `vcyto` command line. Bad input ends with one line on stderr and exit status 2; a numerical
failure with one line and status 1; never a traceback (VCYTO_DEBUG=1 adds one; the exit status stays the same).

One module per command, each with its parser (``add_command``) and its handler (``command_NAME``): flow, paper,
stream, calibrate, replay, stability, relax, extremes, sweep, tradeoff, scenario, cache, bench; ``common`` holds what
they share (exit statuses, output paths, --json). The options of a run and their conversion to a scenario and
stream settings are ``vcyto.options``. Nothing in the package imports the command line."""

from __future__ import annotations

import argparse
import atexit
import os
import sys
import threading
import traceback

from sim.fast.linalg import SolverError
from sim.method.fluid import NumericalBlowUp
from sim.model.scenario import ScenarioError

from .. import units
from ..arguments import Parser
from ..cache import CacheSettingError
from ..cache import install_default as install_cache
from ..recording import runfiles
from ..speedsettings import install as install_speed_settings
from ..stream import StreamStopped
from . import (
    bench,
    cache,
    calibrate,
    extremes,
    flow,
    paper,
    relax,
    replay,
    scenario,
    stability,
    stream,
    sweep,
    tradeoff,
)
from .common import (
    EXIT_INPUT,
    EXIT_INTERNAL,
    EXIT_NUMERICAL,
    EXIT_PIPE,
    EXIT_SIGINT,
    EXIT_SIGTERM,
    RunStopped,
    UsageError,
    check_switches,
    own_process,
    signals_seen,
)

COMMANDS = (flow, paper, stream, calibrate, replay, stability, relax, extremes, sweep, tradeoff, scenario, cache, bench)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="vcyto", description="A virtual cytometer: a simulated SAW cell sorter. Quantities take a "
                                               "unit (25us, 0.5ms, 1kHz, 30um); a bare number is in the unit each "
                                               "option names. Exit status: 0 done, 1 numerical failure or a "
                                               "file that fails to write during the run, 2 bad input (an "
                                               "output that cannot be created is refused before the run), "
                                               "130/143 interrupted "
                                               "(SIGINT/SIGTERM).")
    from .. import __version__
    parser.add_argument("--version", action="version", version=f"vcyto {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:                # in the order of `vcyto --help`
        command.add_command(commands)
    return parser


# Python's threads take turns with the interpreter lock at least this often (Python's default: 5 ms). A command's
# threads that run Python (the loop; the recording sinks; the split solve's and the momentum's helpers between their
# kernels) then wait ~0.2 ms, not up to 5 ms, for one that holds it: the README stream with --tolerance 1um and its
# recordings took a median 16.5 s against 18.2 s at 5 ms, per-pair ratio 0.93 (``python examples/process_tricks.py
# --only switch``, three pairs on a loaded 2-core host).
SWITCH_INTERVAL_S = 2e-4


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    interval = sys.getswitchinterval()
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        return _main(args)
    finally:
        sys.setswitchinterval(interval)      # as it was (``main`` may be called in a process that goes on)


def _main(args) -> int:
    try:
        install_speed_settings()
        check_switches()
        install_cache()
        with runfiles.signals_as_interrupt(signals_seen):     # SIGTERM ends every command as Ctrl-C does
            status = args.handler(args)
    except (ScenarioError, UsageError, units.QuantityError, CacheSettingError) as error:
        return _fail(error, EXIT_INPUT)
    except (NumericalBlowUp, SolverError) as error:
        return _fail(error, EXIT_NUMERICAL)
    except RunStopped as stopped:
        return stopped.status
    except StreamStopped as stopped:            # a loop run by another command than stream (bench, tradeoff)
        if stopped.status != "interrupted":
            return _fail(stopped, EXIT_NUMERICAL)
        print("vcyto: interrupted", file=sys.stderr)
        return EXIT_SIGTERM if signals_seen.get("last") == "SIGTERM" else EXIT_SIGINT
    except KeyboardInterrupt:
        print("vcyto: interrupted", file=sys.stderr)
        return EXIT_SIGTERM if signals_seen.get("last") == "SIGTERM" else EXIT_SIGINT
    except MemoryError as error:
        return _fail(MemoryError("memory: the run needs more memory than this machine has; use a coarser "
                                 "mesh, fewer cells or fewer sweep points"), EXIT_NUMERICAL, error)
    except BrokenPipeError:           # stdout's reader went away (`vcyto ... | head`): no error to report
        _stdout_to_devnull()
        return EXIT_PIPE
    except OSError as error:          # a disk that fills up, a file that vanished: the environment, not a bug
        where = getattr(error, "filename", None) or "file"
        return _fail(OSError(f"{where}: cannot write or read it: {error.strerror or error}"), EXIT_NUMERICAL, error)
    except Exception as error:  # a bug, not bad input: say so in one line, keep the traceback on request
        _traceback_on_request(error)
        print(f"vcyto: internal error: {type(error).__name__}: {' '.join(str(error).split())} (set VCYTO_DEBUG=1 for "
              "the traceback; please report it)", file=sys.stderr)
        return EXIT_INTERNAL
    return status or 0


def run() -> None:
    """The ``vcyto`` executable (and ``python -m vcyto``): ``main``, then ``exit_now`` with its status (argparse's
    exits for --help, --version and bad usage included). This process is the command's own, so the Rerun sink may
    keep pyarrow from importing pandas (``vcyto.recording.viewer.spare_pandas_import``)."""
    from ..arrowshim import spare_pandas_import
    spare_pandas_import()
    own_process()
    try:
        status = main()
    except SystemExit as stop:
        if not (stop.code is None or isinstance(stop.code, int)):
            raise
        status = stop.code
    except KeyboardInterrupt:           # outside a command's own handling (while the options are read)
        print("vcyto: interrupted", file=sys.stderr)
        status = EXIT_SIGINT
    exit_now(status or 0)


def exit_now(status: int) -> None:
    """End the process with ``status`` once everything is written, without the interpreter's teardown.

    Tearing down the interpreter (freeing every module's objects and the libraries' threads) is time a user waits
    for nothing: from ``main``'s return to the process's end after ``vcyto paper 2 --no-png``, 0.045 s median with
    ``os._exit`` against 0.105 s ordinarily (``python examples/process_tricks.py --only exit``, three pairs). The
    rules this relies on: every output file is closed by the time ``main`` returns (a file left to the garbage
    collector would lose its buffered data), and every thread kept for the life of the process is a daemon. Here
    the exit handlers run (logging, rerun's flush, temporary directories), stdout and stderr are flushed, and
    ``os._exit`` ends the process. With a non-daemon thread still running, or under a profiler or tracer (``python
    -m cProfile``, which writes its results after ``main``), the ordinary exit."""
    working = [thread for thread in threading.enumerate()
               if thread.is_alive() and not thread.daemon and thread is not threading.main_thread()]
    if sys.getprofile() is not None or sys.gettrace() is not None or working:
        sys.exit(status)
    atexit._run_exitfuncs()
    for output in (sys.stdout, sys.stderr):
        try:
            output.flush()
        except BrokenPipeError:           # the reader went away (`vcyto --help | head`): as main says for a run
            status = EXIT_PIPE if output is sys.stdout and status == 0 else status
        except (OSError, ValueError):     # nothing more can reach it
            pass
    os._exit(status)


def _stdout_to_devnull():
    """Point stdout at /dev/null: what is still buffered for a reader that has gone can go nowhere else."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):      # stdout is not a file descriptor (a test's capture)
        pass


def _fail(error: Exception, status: int, cause: Exception | None = None) -> int:
    """The one-line error for ``error`` (reworded from ``cause``, whose traceback VCYTO_DEBUG shows) and ``status``."""
    _traceback_on_request(cause or error)
    print(f"vcyto: error: {' '.join(str(error).split())}", file=sys.stderr)
    return status


def _traceback_on_request(error: Exception):
    """With VCYTO_DEBUG set, the traceback of ``error`` on stderr; the one-line error and the exit status follow
    as without it (bad input stays 2)."""
    if os.environ.get("VCYTO_DEBUG"):
        traceback.print_exception(type(error), error, error.__traceback__)
