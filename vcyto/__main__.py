"""`python -m vcyto`: the command line (the same as `vcyto`)."""

import sys

from .cli import main

sys.exit(main())
