"""`python -m vcyto` and the `vcyto` executable: the command line (``vcyto.cli``).

The command line is imported inside ``run``: a Ctrl-C while Python loads the libraries (the first half second)
ends with one line and status 130, as an interrupt does later, instead of a traceback.

The garbage collector is off while the libraries load, and the objects they leave (modules, functions, classes:
they live as long as the process) are then frozen (``gc.freeze``): no later collection walks them again. Measured
on the README's stream with ``--tolerance 1um`` (``python examples/process_tricks.py --only collections``, medians
of three pairs on a loaded 2-core host): 0.0001 s of collections during the imports and 0.010 s during the run,
against 0.070 s and 0.118 s without. Only the process's own entry points do this (``python -m vcyto.cli`` freezes
after its package's import, and the start-up probe ``vcyto.startprobe`` imports as the executable does);
``vcyto.cli.main`` called from Python leaves the collector alone.
"""

import gc
import os
import sys


def load_command_line():
    """``vcyto.cli``, imported with the collector off; what the imports leave is then frozen (the collector is
    then as it was)."""
    collecting = gc.isenabled()
    gc.disable()
    try:
        from . import cli
    finally:
        gc.freeze()
        if collecting:
            gc.enable()
    return cli


def run() -> None:
    try:
        cli = load_command_line()
    except KeyboardInterrupt:               # nothing has been written yet
        sys.stderr.write("vcyto: interrupted\n")
        sys.stderr.flush()
        os._exit(130)
    cli.run()


if __name__ == "__main__":
    run()
