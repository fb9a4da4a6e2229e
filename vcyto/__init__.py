"""vcyto: the virtual cytometer application (scenarios, closed loop, recordings, command line).

The public Python API (imported on first use, so ``import vcyto`` stays cheap):

- scenarios: ``Scenario`` (the paper's device by default), ``load_scenario(path, overrides)``,
  ``scenario_from_toml(text)``, ``scenario_to_toml(scenario)``;
- the closed loop: ``StreamSettings``, ``Arrivals``, ``DetectorSettings``, ``ControllerSettings``,
  ``run_stream(scenario, settings, sinks=..., controller=..., plant=..., timing=...)`` (a JSON-ready summary),
  ``make_plant(scenario, settings)`` (both use the set-up cache, ``vcyto.cache``), ``MODELS``,
  ``report_lines(result)``;
- controllers (docs/controllers.md): ``Decision``, ``DeviceFacts``, ``SortController`` (the built-in one),
  ``Timing`` (lock-step or paced real time);
- what happened to each cell: ``outcome_class(cell)``, ``OUTCOME_CLASSES``;
- recordings: ``McapRecorder`` (a sink), ``RerunSink`` (a sink), ``BackgroundSinks``, ``write_fcs``,
  ``write_gatingml``.

See docs/usage.md, "Use from Python".
"""

import importlib as _importlib
import time as _time

STARTED = _time.perf_counter()      # for "whole process" wall times
__version__ = "0.1.0"

_EXPORTS = {
    "Scenario": "sim.model.scenario", "Arrivals": "sim.model.arrivals",
    "DetectorSettings": "controller.detector", "ControllerSettings": "controller.sorter",
    "load_scenario": "vcyto.config", "scenario_from_toml": "vcyto.config", "scenario_to_toml": "vcyto.config",
    "StreamSettings": "vcyto.stream", "run_stream": "vcyto.stream", "make_plant": "vcyto.stream",
    "MODELS": "vcyto.stream", "Decision": "controller.events", "DeviceFacts": "controller.protocol",
    "SortController": "controller.sorter", "Timing": "vcyto.control",
    "report_lines": "vcyto.stream", "StreamStopped": "vcyto.stream",
    "outcome_class": "vcyto.outcomes", "OUTCOME_CLASSES": "vcyto.outcomes",
    "McapRecorder": "vcyto.recording.mcap", "RerunSink": "vcyto.recording.rerunlog",
    "BackgroundSinks": "vcyto.recording.sinks",
    "write_fcs": "vcyto.recording.fcs", "write_gatingml": "vcyto.recording.gatingml",
}
__all__ = ["__version__", *_EXPORTS]


def __getattr__(name):
    if name in _EXPORTS:
        value = getattr(_importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'vcyto' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
