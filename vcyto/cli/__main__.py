"""`python -m vcyto.cli`: the command line (the same as `vcyto`). Python has imported this package before this
file runs; what that import left is frozen for the garbage collector, as the `vcyto` executable does
(``vcyto.__main__``)."""

import gc

from . import run

gc.freeze()
run()
