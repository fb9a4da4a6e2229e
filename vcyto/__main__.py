"""`python -m vcyto`: the command line (the same as `vcyto`)."""

from .cli import run

run()
