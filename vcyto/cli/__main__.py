"""`python -m vcyto.cli`: the command line (the same as `vcyto`)."""

import sys

from . import main

sys.exit(main())
