"""vcyto: the virtual cytometer application (scenarios, closed loop, recordings, command line)."""

__version__ = "0.1.0"
