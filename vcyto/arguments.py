"""Command-line parsing with vcyto's rules: one-line errors, negative numbers as values, typed quantities.

- ``Parser``: argparse's errors become ``vcyto: error: <option>: <what is wrong>`` (exit 2, no usage dump);
  ``-1``, ``-1e-3`` and ``-5ms`` are read as values, not as options.
- ``Quantity``: an option holding a physical quantity (``--lead 0.5`` = 0.5 ms, ``--lead 500us``), read by
  ``vcyto.units.parse_quantity``, checked finite and in range; the parsed value is SI.
- ``Integer`` and ``Number``: whole and plain numbers with a range.
- ``limits``: the sizes (cells, mesh, sweep points) that would exhaust memory, estimated before any work.
"""

from __future__ import annotations

import argparse
import math
import re
import sys

from sim.model.scenario import ScenarioError

from .units import DIMENSIONS, QuantityError, parse_quantity, unit_factor

_NEGATIVE = re.compile(r"^-\.?\d")          # "-1", "-.5", "-1e-3", "-5ms": values, never options


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors and negative numbers read as values."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = _NEGATIVE
        self._has_negative_number_optionals = []

    def error(self, message: str):
        message = " ".join(message.split())
        match = re.match(r"argument ([^:]+): (.*)", message)
        if match:                    # "argument --lead: --lead: ..." -> "--lead: ..."
            option = match.group(1).split("/")[-1]
            detail = match.group(2)
            message = detail if detail.startswith(option + ":") else f"{option}: {detail}"
        elif message.startswith("unrecognized arguments: "):      # "--bogus: unknown option ..."
            words = message.split(": ", 1)[1]
            message = f"{words.split()[0]}: unknown option or extra argument (unrecognized: {words})"
        elif message.startswith("the following arguments are required: "):
            names = message.split(": ", 1)[1]
            message = f"{names}: missing; the command needs it"
        print(f"vcyto: error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)

    def _get_value(self, action, arg_string):
        """argparse's conversion of one value, with a ``Quantity`` told its option's name so that a wrong unit
        says "'3um' is a length, but --delay is a time"."""
        if isinstance(action.type, Quantity) and action.option_strings:
            try:
                return action.type(arg_string, field=action.option_strings[-1])
            except argparse.ArgumentTypeError as error:
                raise argparse.ArgumentError(action, str(error)) from None
        return super()._get_value(action, arg_string)


class _Checked:
    """Shared range check of the option types; ``low``/``high`` bounds in the parsed (SI) value."""

    def __init__(self, low=None, high=None, low_open=False, what=""):
        self.low, self.high, self.low_open, self.what = low, high, low_open, what

    def _check(self, value, text, shown):
        if self.low is not None and (value < self.low or (self.low_open and value == self.low)):
            bound = "positive" if self.low == 0 and self.low_open else \
                f"{'>' if self.low_open else '>='} {shown(self.low)}"
            raise argparse.ArgumentTypeError(f"must be {bound}{self.what} (got {text})")
        if self.high is not None and value > self.high:
            raise argparse.ArgumentTypeError(f"must be at most {shown(self.high)}{self.what} (got {text})")
        return value


class Quantity(_Checked):
    """An option's type: a ``dimension`` quantity, a bare number in ``unit``; the value returned is SI."""

    def __init__(self, dimension: str, unit: str = "", low=None, high=None, low_open=False, what=""):
        super().__init__(low, high, low_open, what)
        self.dimension, self.unit = dimension, unit
        self.__name__ = dimension                  # argparse names the type in some messages

    def __call__(self, text, field: str = "the value") -> float:
        """The SI value of ``text``; ``field`` (the option, or where in a file) is named in a wrong unit's error."""
        try:
            value = parse_quantity(text, self.dimension, self.unit, field=field)
        except QuantityError as error:
            raise argparse.ArgumentTypeError(str(error).split(": ", 1)[1]) from None
        return self._check(value, text, self.shown)

    def shown(self, value: float) -> str:
        """``value`` (SI) in the option's unit, e.g. 0.0005 -> "0.5 ms"."""
        unit = self.unit or DIMENSIONS[self.dimension][0]
        factor = unit_factor(self.unit, self.dimension) if self.unit else 1.0
        return f"{value / factor:g}" + (f" {unit}" if unit else "")


class Number(Quantity):
    """A plain (dimensionless) number with a range."""

    def __init__(self, low=None, high=None, low_open=False, what=""):
        super().__init__("dimensionless", "", low, high, low_open, what)
        self.__name__ = "number"


class Integer(_Checked):
    """A whole number with a range (``10``, ``+3``, ``-1``; not ``1.5`` or ``1e3``)."""

    __name__ = "integer"

    def __call__(self, text) -> int:
        if isinstance(text, bool):
            raise argparse.ArgumentTypeError(f"must be a whole number (got {text!r})")
        if isinstance(text, int):
            value = text
        elif isinstance(text, str) and re.fullmatch(r"\s*[-+]?\d{1,30}\s*", text):
            value = int(text)
        else:
            raise argparse.ArgumentTypeError(f"must be a whole number such as 10 (got {text!r})")
        return self._check(value, text, lambda bound: f"{bound:,}" if abs(bound) >= 10_000 else str(bound))


# --- limits: sizes refused before any work ---------------------------------------------------------

BYTES_PER_DOF = 6_000         # measured: the paper mesh (54,243 DOFs) takes ~220 MB set up, the 6.67 um one ~70 MB
BYTES_PER_CELL = 100          # what a stream holds per cell: the sample of plants that hold it whole (9 bytes),
                              # the ~25 bytes an event a long recorded rom sort still grows by, generously
MAX_SWEEP_POINTS = 100_000    # a sweep larger than this is refused (each point is a run)
MEMORY_SHARE = 0.8            # of the memory available now


def available_memory() -> float:
    """Bytes of memory available now (MemAvailable), or physical memory where /proc is absent."""
    try:
        with open("/proc/meminfo") as file:
            for line in file:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        import os
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 8e9


def mesh_dofs(length: float, height: float, h: float) -> float:
    """Taylor-Hood P2/P1 unknowns of the channel's right-isosceles mesh of size ``h`` (the paper's: 54,243)."""
    nx, ny = math.ceil(min(length / h, 1e150)), math.ceil(min(height / h, 1e150))
    return 2.0 * (2 * nx + 1) * (2 * ny + 1) + float(nx + 1) * (ny + 1)


def check_mesh(length: float, height: float, h: float, field: str = "mesh (channel.length, channel.height, "
               "numerics.mesh_h)") -> None:
    """Refuse a mesh whose estimated memory exceeds what is available, saying the estimate."""
    dofs = mesh_dofs(length, height, h)
    need, have = dofs * BYTES_PER_DOF, available_memory() * MEMORY_SHARE
    if need > have:
        raise ScenarioError(field, f"a {length:.4g} m x {height:.4g} m channel meshed at {h:.4g} m "
                                  f"has about {dofs:.3g} unknowns and would need about {_bytes(need)} of memory "
                                  f"({_bytes(have)} available); use a coarser mesh")


SECONDS_PER_STEP_PER_DOF = 14e-3 / 54_243     # measured: an FE-IB step at the paper's 54,243 DOFs takes ~14 ms
MAX_RUN_HOURS = 24.0


def check_run_time(simulated: float, dt: float, dofs: float, field: str = "--dt", allowed: bool = False) -> None:
    """Refuse an FE-IB run whose estimated wall time (steps x the measured cost per step and unknown) exceeds
    ``MAX_RUN_HOURS``, saying the estimate, unless the user ``allowed`` it (``--allow-long``)."""
    steps = simulated / dt
    hours = steps * dofs * SECONDS_PER_STEP_PER_DOF / 3600
    if hours > MAX_RUN_HOURS and not allowed:
        raise QuantityError(f"{field}: {simulated * 1e3:.4g} ms of device time at dt = {dt * 1e6:.4g} us is about "
                            f"{steps:.3g} FE-IB steps, roughly {hours:,.0f} h on this machine (more than "
                            f"{MAX_RUN_HOURS:g} h); use a larger dt, fewer cells, the rom or auto model, or "
                            "--allow-long to run it anyway")


def check_cells(count: int, field: str = "--count") -> None:
    """Refuse a stream whose per-cell results alone would not fit in memory."""
    need, have = count * BYTES_PER_CELL, available_memory() * MEMORY_SHARE
    if need > have:
        raise QuantityError(f"{field}: {count:,} cells would need about {_bytes(need)} for their results alone "
                            f"({_bytes(have)} available); run at most {int(have // BYTES_PER_CELL):,} cells, or "
                            "split the stream into a sweep over seeds")


def _bytes(value: float) -> str:
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if value >= size:
            return f"{value / size:.3g} {unit}"
    return f"{value / 1e3:.3g} kB"
