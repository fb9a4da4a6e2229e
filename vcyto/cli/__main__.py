"""`python -m vcyto.cli`: the command line (the same as `vcyto`)."""

from . import run

run()
