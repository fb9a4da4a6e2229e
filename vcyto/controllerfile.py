"""Controller settings files: the TOML that `vcyto calibrate` writes and `vcyto stream --controller FILE` reads.

One table, ``[controller]``, with the fields of ``controller.sorter.ControllerSettings``; times may carry a unit
("0.3 ms", "300us"), bare numbers are SI (s, m/s). Unknown fields and values of the wrong kind are errors that
name the field.
"""

from __future__ import annotations

import os
from pathlib import Path

from controller.sorter import ControllerSettings
from sim.model.scenario import ScenarioError

from .config import _build, read_toml

MAX_BYTES = 1 << 20
MAX_TIME = 10e-3        # s: the longest delay, lead, pulse, timing error or envelope offset (as the options')
TIMES = ("delay", "lead", "pulse", "timing_error")


def load_controller(path: str | os.PathLike, field: str = "--controller") -> ControllerSettings:
    """The settings in the controller file ``path``; ScenarioError (one line, naming the field) if it is wrong."""
    path = Path(path)
    if not path.is_file():
        raise ScenarioError(field, f"'{path}' is not a file (write one with vcyto calibrate)")
    document = read_toml(path, "controller file", field, MAX_BYTES)
    unknown = set(document) - {"controller", "calibration"}
    if "controller" not in document or unknown:
        raise ScenarioError(field, f"'{path}' needs one [controller] table (and optionally [calibration]); "
                                            f"found {', '.join(sorted(document)) or 'nothing'}")
    try:
        settings = _build(ControllerSettings, document["controller"], "controller")
    except ValueError as error:
        if isinstance(error, ScenarioError):
            raise
        raise ScenarioError("controller", str(error)) from None
    check_times(settings, "controller.")
    return settings


def check_times(settings: ControllerSettings, prefix: str = "--") -> None:
    """Refuse times beyond ``MAX_TIME`` (a delay of days would have the controller plan days of queue)."""
    for name in TIMES:
        if getattr(settings, name) > MAX_TIME:
            raise ScenarioError(f"{prefix}{name.replace('_', '-' if prefix == '--' else '_')}",
                                f"{getattr(settings, name) * 1e3:g} ms is more than {MAX_TIME * 1e3:g} ms, several "
                                "times a cell's passage through the device; give at most that")
    if max(abs(value) for value in settings.envelope) > MAX_TIME:
        raise ScenarioError(f"{prefix}envelope", f"offsets {settings.envelope[0] * 1e3:g}, "
                            f"{settings.envelope[1] * 1e3:g} ms reach beyond +-{MAX_TIME * 1e3:g} ms; give smaller")


def controller_toml(settings: ControllerSettings, provenance: dict) -> str:
    """The settings as a controller file; ``provenance`` (plain strings and numbers) becomes [calibration]."""
    ms = 1e3
    lines = ["# vcyto controller settings (vcyto stream --controller FILE); times carry their unit, velocity in m/s",
             "[controller]",
             f'mode = "{settings.mode}"',
             f'delay = "{settings.delay * ms:.6g} ms"       # detection -> SAW window centre at reference_velocity',
             f"reference_velocity = {settings.reference_velocity:.6g}",
             f'lead = "{settings.lead * ms:.6g} ms"        # pulse starts this long before the predicted arrival',
             f'pulse = "{settings.pulse * ms:.6g} ms"',
             f'envelope = ["{settings.envelope[0] * ms:.6g} ms", "{settings.envelope[1] * ms:.6g} ms"]'
             "   # offsets from the target at which a type-I cell is deflected too",
             f'timing_error = "{settings.timing_error * ms:.6g} ms"   # of one predicted arrival',
             "", "[calibration]"]
    for key, value in provenance.items():
        lines.append(f"{key} = {_literal(value)}")
    return "\n".join(lines) + "\n"


def _literal(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'
