"""A user's controller or plant, named on the command line as ``FILE.py:NAME`` or ``MODULE:NAME``.

``NAME`` is a class or a factory. A controller's is called with the controller settings
(``controller.sorter.ControllerSettings``: the calibration, mode and options of the run) and returns an object
implementing ``controller.protocol.Controller``; a plant's is called with the scenario (``sim.model.scenario.Scenario``)
and returns a plant (``sim.plants.contract.Plant``). A file is loaded as a module of its own (its folder is not put on
``sys.path``); a module is imported as Python imports it. Whatever goes wrong (no such file, a syntax error in it,
no such name, a factory that raises or returns something that is not a controller or a plant) is one line.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import sys
from pathlib import Path

MAX_SPEC = 4096                    # characters of a FILE.py:NAME or MODULE:NAME


class PluginError(ValueError):
    """A controller or plant that cannot be loaded: the message says why and what to give instead."""


def split(spec: str) -> tuple[str, str]:
    """(file or module, name) of ``FILE.py:NAME`` / ``MODULE:NAME`` (the name after the last colon)."""
    if not isinstance(spec, str) or not spec or len(spec) > MAX_SPEC:
        raise PluginError(f"wants FILE.py:NAME or MODULE:NAME (got {str(spec)[:80]!r})")
    where, colon, name = spec.rpartition(":")
    if not colon or not where or not name.isidentifier():
        raise PluginError(f"wants FILE.py:NAME or MODULE:NAME, NAME a Python name (got {spec[:200]!r})")
    return where, name


def load(spec: str):
    """The object ``NAME`` of ``FILE.py:NAME`` or ``MODULE:NAME``."""
    where, name = split(spec)
    module = _load_file(where) if where.endswith(".py") or "/" in where or "\\" in where else _import(where)
    try:
        return getattr(module, name)
    except AttributeError:
        raise PluginError(f"{where} has no {name!r}") from None


def _load_file(path_text: str):
    path = Path(path_text).expanduser()
    if not path.is_file():
        raise PluginError(f"no such file: {path_text}")
    module_name = "vcyto_user_" + hashlib.sha256(str(path.resolve()).encode()).hexdigest()[:16]
    if module_name in sys.modules:
        return sys.modules[module_name]
    spec = importlib.util.spec_from_file_location(module_name, path)
    if spec is None or spec.loader is None:
        raise PluginError(f"cannot load {path_text} as Python (give a .py file)")
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as error:          # the user's code: whatever it raises is reported in one line
        del sys.modules[module_name]
        raise PluginError(f"loading {path_text} failed: {_describe(error)}") from None
    return module


def _import(module_name: str):
    try:
        return importlib.import_module(module_name)
    except Exception as error:
        raise PluginError(f"cannot import {module_name}: {_describe(error)}") from None


def _describe(error: BaseException) -> str:
    text = " ".join(str(error).split())[:300]
    where = ""
    if isinstance(error, SyntaxError) and error.lineno:
        where = f" (line {error.lineno})"
    return f"{type(error).__name__}{where}: {text}" if text else type(error).__name__


def _build(factory, argument, what: str, spec: str):
    if not callable(factory):
        raise PluginError(f"{spec}: is not a class or a factory of a {what}")
    try:
        return factory(argument)
    except Exception as error:
        raise PluginError(f"{spec}: building the {what} failed: {_describe(error)}") from None


def controller(spec: str, settings):
    """The controller that ``spec``'s class or factory builds from ``settings`` (checked against the protocol)."""
    from controller.protocol import Controller
    built = _build(load(spec), settings, "controller", spec)
    if not isinstance(built, Controller):
        raise PluginError(f"{spec}: built a {type(built).__name__}, which has no on_event(event, clock) method "
                          "(controller.protocol.Controller)")
    return built


def plant(spec: str, scenario):
    """The plant that ``spec``'s class or factory builds for ``scenario`` (checked against the plant contract)."""
    from sim.plants.contract import Plant
    built = _build(load(spec), scenario, "plant", spec)
    if not isinstance(built, Plant):
        missing = [name for name in ("reset", "step", "observe", "truth", "done", "control_period")
                   if not hasattr(built, name)]
        raise PluginError(f"{spec}: built a {type(built).__name__}, which is not a plant (sim.plants.contract.Plant): "
                          f"it lacks {', '.join(missing) or 'the contract'}")
    period = getattr(built, "control_period", None)
    if not (isinstance(period, (int, float)) and 0 < period < 1):
        raise PluginError(f"{spec}: the plant's control_period must be a time in s between 0 and 1 (got {period!r})")
    return built
