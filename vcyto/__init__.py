"""vcyto: the virtual cytometer application (scenarios, closed loop, recordings, command line)."""

import time as _time

STARTED = _time.perf_counter()      # for "whole process" wall times
__version__ = "0.1.0"
