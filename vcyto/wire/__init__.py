"""Controllers in another process: the wire protocol (``vcyto-controller``, version 1) and the port that speaks it.

Length-prefixed JSON over TCP or a Unix socket (``framing``), a handshake that states the protocol's version and
each side's capabilities and hands over the device facts, one ``event`` message per detector event and one
``decisions`` message in answer (``messages``), and ``WirePort`` (``port``), the loop's port to such a
controller: ``connect(address, timeout)`` or ``launch(command, timeout)``, or ``WireController(how, target).open()``
from plain data (what a sweep's workers get). docs/wire-protocol.md is the spec.
"""

from .framing import MAX_MESSAGE, WireError
from .messages import CAPABILITIES, PROTOCOL, VERSION
from .port import DEFAULT_TIMEOUT, ENV_ADDRESS, WireController, WirePort, connect, launch, parse_address

__all__ = ["CAPABILITIES", "DEFAULT_TIMEOUT", "ENV_ADDRESS", "MAX_MESSAGE", "PROTOCOL", "VERSION", "WireController",
           "WireError", "WirePort", "connect", "launch", "parse_address"]
