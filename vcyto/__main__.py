"""`python -m vcyto` and the `vcyto` executable: the command line (``vcyto.cli``).

The command line is imported inside ``run``: a Ctrl-C while Python loads the libraries (the first half second)
ends with one line and status 130, as an interrupt does later, instead of a traceback.
"""

import os
import sys


def run() -> None:
    try:
        from .cli import run as run_command_line
    except KeyboardInterrupt:               # nothing has been written yet
        sys.stderr.write("vcyto: interrupted\n")
        sys.stderr.flush()
        os._exit(130)
    run_command_line()


if __name__ == "__main__":
    run()
