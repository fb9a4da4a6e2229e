"""The messages of the wire protocol, built and checked (docs/wire-protocol.md lists every field).

vcyto sends ``hello`` (the protocol, its version, vcyto's capabilities, the device facts, the timing mode),
``event`` (a detector event with its deadline and the device clock), ``period`` (to a controller that offers
``drive``: a control period starts) and ``end``; the controller answers ``welcome`` (or ``error``), one
``decisions`` per event, one ``drive`` per period, and ``bye``. Either side may send ``error``. All times
are device times in seconds, lengths in metres, velocities in m/s.
"""

from __future__ import annotations

import math

from controller.events import Decision, DetectorEvent
from controller.protocol import DeviceFacts

from .framing import WireError

PROTOCOL = "vcyto-controller"
VERSION = 1
CAPABILITIES = ("decisions", "drive")   # what this version offers: decisions to each event; the drive each period
REQUIRED = "decisions"             # what a controller must offer
DRIVE = "drive"                    # a controller that offers it sets the IDT drive each control period itself


def hello(facts: DeviceFacts, timing) -> dict:
    from .. import __version__
    return {"type": "hello", "protocol": PROTOCOL, "version": VERSION, "capabilities": list(CAPABILITIES),
            "software": f"vcyto {__version__}", "facts": facts.as_dict(),
            "timing": {"mode": "realtime" if timing.realtime else "lock-step", "factor": timing.factor}}


def event(event: DetectorEvent, deadline: float, clock: float) -> dict:
    numbers = (event.time, event.fluorescence, event.scatter, event.velocity, deadline, clock)
    if not all(map(math.isfinite, numbers)):
        raise WireError(f"event {event.event_id} has a value that is not a finite number ({numbers}): the "
                        "protocol carries finite numbers only")
    return {"type": "event", "event_id": event.event_id, "time": event.time, "fluorescence": event.fluorescence,
            "scatter": event.scatter, "velocity": event.velocity, "classification": event.classification,
            "key": event.key, "deadline": deadline, "clock": clock}


def period(clock: float) -> dict:
    """A control period starts at ``clock``: a controller that offers ``drive`` answers its drive level."""
    return {"type": "period", "clock": clock}


def drive(message: dict) -> tuple[float, float]:
    """The period (its start, s) and the drive level in [0, 1] of a ``drive`` message (``WireError`` names the
    field that is wrong)."""
    clock, level = message.get("clock"), message.get("level")
    for name, value in (("clock", clock), ("level", level)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise WireError(f"drive: {name} must be a finite number (got {value!r})")
    if not 0.0 <= level <= 1.0:
        raise WireError(f"drive: level must be in [0, 1] (got {level!r} for the period at {clock!r} s)")
    return float(clock), float(level)


def end(reason: str) -> dict:
    return {"type": "end", "reason": reason}


def error(message: str) -> dict:
    return {"type": "error", "message": message}


def check_welcome(message: dict) -> tuple[str, str, tuple[str, ...]]:
    """The controller's name, software version and capabilities from its answer to ``hello`` (``WireError`` if
    it refused or speaks another protocol or version)."""
    if message["type"] == "error":
        raise WireError(f"the controller refused the handshake: {shorten(message.get('message'))}")
    if message["type"] != "welcome":
        raise WireError(f"expected a welcome message in answer to hello, got {message['type']!r}")
    if message.get("protocol") != PROTOCOL:
        raise WireError(f"the controller speaks protocol {message.get('protocol')!r}, not {PROTOCOL!r}")
    if message.get("version") != VERSION:
        raise WireError(f"version mismatch: the controller speaks version {message.get('version')!r} of "
                        f"{PROTOCOL}, vcyto speaks {VERSION}")
    capabilities = message.get("capabilities")
    if not (isinstance(capabilities, list) and all(isinstance(item, str) for item in capabilities)):
        raise WireError(f"welcome: capabilities must be a list of strings (got {capabilities!r})")
    if REQUIRED not in capabilities:
        raise WireError(f"the controller does not offer {REQUIRED!r} (its capabilities: {capabilities})")
    name, software = message.get("name"), message.get("software", "")
    if not (isinstance(name, str) and name.strip() and isinstance(software, str)):
        raise WireError(f"welcome: name must be a non-empty string and software a string (got {name!r}, "
                        f"{software!r})")
    return shorten(name, 80), shorten(software, 80), tuple(capabilities)


def decisions(message: dict) -> tuple[int, tuple[Decision, ...]]:
    """The event answered and its decisions (``WireError`` names the field that is wrong)."""
    event_id = message.get("event_id")
    if not _is_integer(event_id):
        raise WireError(f"decisions: event_id must be an integer (got {event_id!r})")
    listed = message.get("decisions")
    if not isinstance(listed, list):
        raise WireError(f"decisions: the answer to event {event_id} needs a list \"decisions\" (got {listed!r})")
    return event_id, tuple(_decision(item, event_id) for item in listed)


def _decision(item, answered: int) -> Decision:
    if not isinstance(item, dict):
        raise WireError(f"decisions: each decision (answer to event {answered}) must be an object (got {item!r})")
    event_id, action = item.get("event_id"), item.get("action")
    if not _is_integer(event_id):
        raise WireError(f"decisions: event_id must be an integer (got {event_id!r}, answer to event {answered})")
    if not isinstance(action, str):
        raise WireError(f"decisions: action must be a string (got {action!r}, event {event_id})")
    arrival = _time(item, "arrival", event_id)
    reason = item.get("reason", "")
    if not isinstance(reason, str):
        raise WireError(f"decisions: reason must be a string (got {reason!r}, event {event_id})")
    return Decision(event_id, action, arrival, _time(item, "pulse_on", event_id), _time(item, "pulse_off", event_id),
                    reason)


def _time(item: dict, name: str, event_id) -> float:
    """A device time (s) of a decision; absent or null: NaN (none given)."""
    value = item.get(name)
    if value is None:
        return math.nan
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise WireError(f"decisions: {name} must be a finite number of seconds or null (got {value!r}, "
                        f"event {event_id})")
    return float(value)


def _is_integer(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def shorten(value, width: int = 200) -> str:
    text = " ".join(str(value).split())
    return text[:width] + ("..." if len(text) > width else "")
