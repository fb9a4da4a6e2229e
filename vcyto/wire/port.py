"""``WirePort``: the loop's port (``vcyto.control``) to a controller in another process, over TCP or a Unix socket.

``connect(address, timeout)`` reaches a running controller (``tcp:HOST:PORT`` or ``unix:PATH``); ``launch(command,
timeout)`` starts one (``{address}`` in the command and the environment variable ``VCYTO_CONTROLLER_ADDRESS`` say
where to listen), waits for it to listen, connects, and stops it when the port closes. A thread reads the
controller's messages as they come and stamps each with the wall time it arrived, so that a reply's latency is
measured when it arrives, not when the loop looks: over TCP the kernel stamps it (``SO_TIMESTAMPNS``, read with
each message), elsewhere a reader thread does (paced real time only; lock-step reads inline). Paced real time
launches its controller on TCP loopback for that reason. Every failure raises ``ControllerError`` (``WireError``) or
``ConnectionError`` with one line naming the cause; every wait is bounded by ``timeout``, closing included.
"""

from __future__ import annotations

import math
import os
import queue
import select
import shlex
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass

from controller.protocol import ControllerError, DeviceFacts

from ..control import Reply, Timing
from . import messages
from .framing import Frames, WireError, encode

ENV_ADDRESS = "VCYTO_CONTROLLER_ADDRESS"    # where a controller started by ``launch`` listens
DEFAULT_TIMEOUT = 10.0                      # s: connect, handshake, each lock-step answer
CLOSE_WAIT = 2.0                            # s at most for the controller's bye, then for its process to exit
RECEIVE_CHUNK = 1 << 16
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35 if sys.platform.startswith("linux") else None)
TIMESPEC = struct.Struct("@qq")             # the kernel's receive time: seconds, nanoseconds (CLOCK_REALTIME)


def parse_address(text: str) -> tuple:
    """``("tcp", host, port)`` or ``("unix", path)`` (``ValueError``: one line saying the forms)."""
    kind, _, rest = str(text).partition(":")
    if kind == "unix" and rest:
        return ("unix", rest)
    if kind == "tcp":
        host, _, port = rest.rpartition(":")
        host = host.strip("[]")
        if host and port.isdigit() and 0 < int(port) < 65536:
            return ("tcp", host, int(port))
    raise ValueError(f"a controller address is tcp:HOST:PORT (e.g. tcp:127.0.0.1:7070) or unix:PATH (got {text!r})")


def _socket(address: tuple, timeout: float) -> socket.socket:
    """A socket connected to ``address`` (``ConnectionError`` naming it and the cause)."""
    shown = ":".join(str(part) for part in address)
    try:
        if address[0] == "unix":
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            target = address[1]
        else:
            family = socket.AF_INET6 if ":" in address[1] else socket.AF_INET
            sock = socket.socket(family, socket.SOCK_STREAM)
            target = address[1:]
    except (OSError, AttributeError) as error:
        raise ConnectionError(f"cannot open a socket for {shown}: {_reason(error)}") from None
    try:
        sock.settimeout(timeout)
        sock.connect(target)
        if address[0] == "tcp":
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)     # small messages go at once
        return sock
    except OSError as error:
        sock.close()
        raise ConnectionError(f"cannot connect to the controller at {shown}: {_reason(error)}") from None


def readable(sock: socket.socket, wait: float) -> bool:
    """Whether ``sock`` has something to read within ``wait`` s: ``select`` waits to the microsecond (a socket's
    own timeout, ``poll``, rounds a wait up to the next millisecond, which would pace a real-time loop badly)."""
    try:
        ready, _, _ = select.select((sock,), (), (), max(wait, 0.0))
    except ValueError:                           # a descriptor beyond select's range: poll, to the millisecond
        poller = select.poll()
        poller.register(sock, select.POLLIN)
        ready = poller.poll(max(0, math.ceil(wait * 1e3)))
    return bool(ready)


def _reason(error: BaseException) -> str:
    if isinstance(error, (socket.timeout, TimeoutError)):
        return "timed out"
    return " ".join(str(getattr(error, "strerror", None) or error).split()) or type(error).__name__


def connect(address: str, timeout: float = DEFAULT_TIMEOUT, timing: Timing = Timing()) -> WirePort:
    """A port to the controller listening at ``address`` (``tcp:HOST:PORT`` or ``unix:PATH``)."""
    _check_timeout(timeout)
    parsed = parse_address(address)
    return WirePort(_socket(parsed, timeout), address, timeout, timing)


def launch(command: str, timeout: float = DEFAULT_TIMEOUT, timing: Timing = Timing(),
           address: str | None = None) -> WirePort:
    """Start the controller ``command`` (split as a shell would, run without one), tell it where to listen
    (``{address}`` in the command, and ``VCYTO_CONTROLLER_ADDRESS``; default a Unix socket in a new private
    directory), connect once it listens, and stop it when the port closes."""
    _check_timeout(timeout)
    try:
        argv = shlex.split(command)
    except ValueError as error:
        raise ValueError(f"the controller command {command!r} cannot be split into words: {error}") from None
    if not argv:
        raise ValueError("the controller command is empty")
    directory = tempfile.mkdtemp(prefix="vcyto-wire-")
    # paced real time judges answers by the kernel's receive time, which TCP gives and Unix sockets do not
    address = address or _private_address(directory, tcp=timing.realtime and SO_TIMESTAMPNS is not None)
    parsed = parse_address(address)
    argv = [word.replace("{address}", address) for word in argv]
    try:
        process = subprocess.Popen(argv, env={**os.environ, ENV_ADDRESS: address}, stdin=subprocess.DEVNULL,
                                   stdout=_stderr_or_null(), start_new_session=True)
    except OSError as error:
        shutil.rmtree(directory, ignore_errors=True)
        raise ConnectionError(f"cannot start the controller {argv[0]!r}: {_reason(error)}") from None
    started = time.monotonic()
    try:
        sock = _wait_listening(process, parsed, address, started + timeout)
    except BaseException:
        _stop(process)
        shutil.rmtree(directory, ignore_errors=True)
        raise
    return WirePort(sock, address, timeout, timing, process=process, directory=directory, label="started by vcyto")


def _private_address(directory: str, tcp: bool = False) -> str:
    path = os.path.join(directory, "controller.sock")
    if not tcp and hasattr(socket, "AF_UNIX") and len(path.encode()) < 100:
        return f"unix:{path}"
    probe = socket.socket()           # a free port on this machine (another program could take it first: rare)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    return f"tcp:127.0.0.1:{port}"


def _stderr_or_null():
    """The controller's standard output goes to vcyto's standard error (its stdout may carry --json)."""
    try:
        return sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        return subprocess.DEVNULL


def _wait_listening(process, parsed, address, deadline) -> socket.socket:
    while True:
        status = process.poll()
        if status is not None:
            raise ConnectionError(f"the controller process exited with status {status} before listening on "
                                  f"{address}")
        try:
            return _socket(parsed, max(0.05, min(1.0, deadline - time.monotonic())))
        except ConnectionError as error:
            if time.monotonic() >= deadline:
                raise ConnectionError(f"the controller started but did not listen on {address} within the "
                                      f"timeout ({error})") from None
        time.sleep(0.01)


def _stop(process, wait: float = CLOSE_WAIT) -> None:
    """Stop a controller process vcyto started (and what it started): wait for it to exit, else SIGTERM, else
    SIGKILL, each for at most ``wait`` seconds."""
    for sent in (None, signal.SIGTERM, signal.SIGKILL):
        if sent is not None:
            try:
                os.killpg(process.pid, sent)
            except (ProcessLookupError, PermissionError):
                pass
        try:
            process.wait(timeout=wait)
            return
        except subprocess.TimeoutExpired:
            continue


@dataclass(frozen=True)
class WireController:
    """Where a run finds its controller in another process, as plain data (a sweep's workers open one each):
    ``how`` is ``"connect"`` (``target`` an address) or ``"exec"`` (``target`` a command), as the options
    ``--controller-connect`` and ``--controller-exec`` say."""

    how: str
    target: str
    timeout: float = DEFAULT_TIMEOUT

    def __post_init__(self):
        if self.how not in ("connect", "exec"):
            raise ValueError(f"a controller in another process is reached by connect or exec (got {self.how!r})")
        _check_timeout(self.timeout)
        if self.how == "connect":
            parse_address(self.target)
        elif not str(self.target).strip():
            raise ValueError("the controller command is empty")

    @property
    def option(self) -> str:
        return f"--controller-{self.how}"

    def open(self, timing: Timing = Timing()) -> WirePort:
        """A port to the controller: connected to, or its process started (``ConnectionError`` or
        ``ControllerError``, one line, if it cannot be reached)."""
        if self.how == "connect":
            return connect(self.target, self.timeout, timing)
        return launch(self.target, self.timeout, timing)


SPIN = 100e-6      # s a lock-step wait polls for the answer before it sleeps, where a processor is idle


def _spin_default() -> float:
    """``SPIN`` where the machine has a processor to spare (load average below its processors less one half),
    else 0. Polling first spares the two wake-ups of a sleep, which on a virtual machine's idle processor can cost
    tens of microseconds to milliseconds (the lock-step loop over the wire was 4.8x real time sleeping, 5.8x
    polling first on a quiet 2-core host); on a busy one it would take the processor the controller needs (2.2x
    against 1.7x at load 10). It changes how fast a run goes, never its result."""
    processors = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except OSError:
        return 0.0
    return SPIN if processors >= 2 and load < processors - 0.5 else 0.0


def _check_timeout(timeout: float) -> None:
    if not (isinstance(timeout, (int, float)) and math.isfinite(timeout) and 0 < timeout <= 3600):
        raise ValueError(f"the controller timeout must be a time in (0, 3600] s (got {timeout!r})")


class WirePort:
    """The port (``vcyto.control``) to a controller across a socket: ``start`` shakes hands, ``post`` sends an
    event, ``replies`` gives the answers that came, ``close`` says goodbye and stops a launched process."""

    def __init__(self, sock: socket.socket, address: str, timeout: float, timing: Timing = Timing(),
                 process=None, directory: str | None = None, label: str | None = None):
        self.address, self.timeout, self.timing = address, timeout, timing
        self.name = f"wire controller at {address}"
        self.capabilities: tuple[str, ...] = ()
        self.spin = _spin_default()    # s of busy waiting for an answer before sleeping on the socket
        self.drives = False            # whether the controller sets the drive itself (the ``drive`` capability)
        self._level = 0.0              # the drive level it last set
        self._periods: dict[float, float] = {}        # period start -> wall time its ``period`` was sent
        self._held: list[Reply] = []                  # answers that came while the loop waited for a drive
        self._label = label or address
        self._sock, self._process, self._directory = sock, process, directory
        self._sock.settimeout(timeout)
        self._inbox: queue.SimpleQueue = queue.SimpleQueue()      # (message, wall time it came) or an exception
        self._posted: dict[int, float] = {}                       # event_id -> wall time it was sent
        self._facts: DeviceFacts | None = None
        self._frames = Frames()
        self._closing = threading.Event()
        self._closed = False
        self._failure: BaseException | None = None     # why the connection can no longer be used
        self._reader: threading.Thread | None = None
        self._stamped = timing.realtime and self._kernel_stamps()
        if timing.realtime:
            self._listen_in_background()

    def _kernel_stamps(self) -> bool:
        """Ask the kernel to stamp what it receives (TCP on Linux); False where it cannot."""
        if SO_TIMESTAMPNS is None or self._sock.family not in (socket.AF_INET, socket.AF_INET6):
            return False
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        except OSError:
            return False
        return True

    def _now(self) -> float:
        """The wall clock replies are judged by: the kernel's (CLOCK_REALTIME) when it stamps them, else
        ``perf_counter``."""
        return time.time_ns() * 1e-9 if self._stamped else time.perf_counter()

    def _listen_in_background(self) -> None:
        """Read on a thread from now on, which stamps each message with the wall time it came: paced real time
        judges a reply by that time, not by when the loop looks (lock-step reads inline: one thread hop less).
        Where the kernel stamps messages, no thread is needed: the loop reads them when it looks."""
        if self._reader is None and not self._stamped:
            self._reader = threading.Thread(target=self._read, name="vcyto-wire-reader", daemon=True)
            self._reader.start()

    # --- the port contract (vcyto.control)
    def start(self, facts: DeviceFacts) -> None:
        """The handshake: hello (versions, capabilities, device facts, timing) and the controller's welcome."""
        self._facts = facts
        self._send(messages.hello(facts, self.timing))
        message, _ = self._next(self.timeout, "welcome")
        name, software, self.capabilities = messages.check_welcome(message)
        self.drives = messages.DRIVE in self.capabilities
        self.name = f"{name}{' ' + software if software else ''} (wire, {self._label})"

    def post(self, event, clock: float) -> None:
        if self._facts is None:
            raise ControllerError("an event posted before the handshake (start) ran")
        self._posted[event.event_id] = self._now()
        self._send(messages.event(event, self._facts.deadline(event), clock))

    def replies(self, wait: float = 0.0) -> list[Reply]:
        """The answers that came, waiting up to ``wait`` s for the first (inf: up to the timeout, then
        ``ControllerError``: a controller that never answers stops the run)."""
        if not math.isinf(wait):            # a caller that polls (paced real time) needs arrivals stamped
            self._listen_in_background()
        replies, self._held = self._held, []
        if replies:
            wait = 0.0
        bounded = self.timeout if math.isinf(wait) else max(0.0, wait)
        end = time.perf_counter() + bounded
        while not replies:                  # drive answers are taken on the way; a decision ends the wait
            first = self._next(max(0.0, end - time.perf_counter()), "answer" if math.isinf(wait) else None)
            if first is None:
                return []
            if (reply := self._reply(*first)) is not None:
                replies.append(reply)
        while True:
            try:
                item = self._inbox.get_nowait()
            except queue.Empty:
                return replies
            if (reply := self._reply(*self._checked(item))) is not None:
                replies.append(reply)

    def drive(self, clock: float) -> float | None:
        """The drive for the control period from ``clock`` (None if the controller does not set it). Lock-step:
        its answer to ``period``, waited for. Paced real time: the level it last set by now (an answer applies
        from the first period that starts after it came)."""
        if not self.drives:
            return None
        self._send(messages.period(clock))
        self._periods[clock] = self._now()
        if not self.timing.realtime:
            while clock in self._periods:
                message = self._next(self.timeout, "drive")
                if (reply := self._reply(*message)) is not None:
                    self._held.append(reply)
        else:
            while (item := self._next(0.0, None)) is not None:
                if (reply := self._reply(*item)) is not None:
                    self._held.append(reply)
        return self._level

    def close(self) -> None:
        """Say goodbye (``end``; the controller answers ``bye``), close the socket and stop a launched process;
        every wait bounded. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._facts is not None and self._failure is None:
                self._send(messages.end("the run is over"))
                self._await_bye(min(self.timeout, CLOSE_WAIT))
        except (ControllerError, ConnectionError, OSError):
            pass                                     # going away anyway: the run's own error says what happened
        finally:
            self._closing.set()
            try:
                self._sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self._sock.close()
            if self._reader is not None:
                self._reader.join(CLOSE_WAIT)
            if self._process is not None:
                _stop(self._process)
            if self._directory is not None:
                shutil.rmtree(self._directory, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # --- messages
    def _send(self, message: dict) -> None:
        if self._failure is not None:
            raise self._failure
        try:
            self._sock.sendall(encode(message))
        except (socket.timeout, TimeoutError):
            self._failure = ControllerError(f"the controller took no message for {self.timeout:g} s "
                                            "(--controller-timeout): it has stopped reading")
            raise self._failure from None
        except OSError as error:
            self._failure = ConnectionError(self._lost(_reason(error)))
            raise self._failure from None

    def _next(self, wait: float, waiting_for: str | None):
        """The next message and the wall time it came, within ``wait`` s; None if none came and ``waiting_for``
        is None, else ``ControllerError`` saying what never came."""
        try:
            item = self._take(wait)
        except queue.Empty:
            if waiting_for is None:
                return None
            raise ControllerError(f"the controller did not answer within {self.timeout:g} s "
                                  f"(--controller-timeout): no {waiting_for} came") from None
        return self._checked(item)

    def _take(self, wait: float):
        """The next item of the inbox within ``wait`` s (``queue.Empty`` if none); without a reader thread the
        socket is read here."""
        if self._reader is not None:
            return self._inbox.get(timeout=wait) if wait > 0 else self._inbox.get_nowait()
        end = time.perf_counter() + wait
        if self.spin > 0 and wait > 0:      # a short busy wait first: an answer that comes soon costs no sleep
            spun = min(end, time.perf_counter() + self.spin)
            while time.perf_counter() < spun and not readable(self._sock, 0.0):
                pass
        while self._inbox.empty():
            if self._failure is not None:
                raise self._failure
            left = end - time.perf_counter()
            if (wait > 0 and left <= 0) or not self._pump(max(left, 0.0)) or wait <= 0:
                break
        return self._inbox.get_nowait()

    def _checked(self, item):
        if isinstance(item, BaseException):
            self._failure = item
            raise item
        return item

    def _reply(self, message: dict, received: float) -> Reply | None:
        """The answer in ``message``; None for a drive answer (which sets the level)."""
        kind = message["type"]
        if kind == "drive" and self.drives:
            clock, level = messages.drive(message)
            if self._periods.pop(clock, None) is None:
                raise WireError(f"a drive for the period at {clock!r} s, which was not asked about or was answered "
                                "before")
            self._level = level
            return None
        if kind == "decisions":
            event_id, decisions = messages.decisions(message)
            posted = self._posted.pop(event_id, None)
            if posted is None:
                raise WireError(f"an answer to event {event_id}, which was not asked about or was answered before")
            return Reply(event_id, decisions, max(0.0, received - posted))
        if kind == "error":
            self._failure = ControllerError(f"the controller reported an error: "
                                            f"{messages.shorten(message.get('message'))}")
        elif kind == "bye":
            self._failure = ConnectionError("the controller said bye before the run ended")
        else:
            self._failure = WireError(f"unexpected message type {kind!r} during the run (expected decisions)")
        raise self._failure

    def _await_bye(self, wait: float) -> None:
        end = time.monotonic() + wait
        while (left := end - time.monotonic()) > 0:
            try:
                item = self._take(left)
            except queue.Empty:
                return
            if isinstance(item, BaseException) or item[0]["type"] == "bye":
                return

    def _read(self) -> None:
        """The reader thread: messages off the socket into the inbox until the port closes or breaks."""
        while not self._closing.is_set() and self._pump(None):
            pass

    def _pump(self, wait: float | None) -> bool:
        """Read what the socket has (waiting up to ``wait`` s; None: the socket's timeout) into the inbox, each
        message stamped with the wall time it came; False once the connection has ended (the inbox says why)."""
        try:
            if wait is not None and not readable(self._sock, wait):
                return True
            try:
                data, received = self._receive()
            except (socket.timeout, TimeoutError):
                return True
            if not data:
                if not self._closing.is_set():
                    cut = f" in the middle of a message ({self._frames.partial} bytes)" if self._frames.partial else ""
                    self._fail(ConnectionError(self._lost(f"the controller closed the connection{cut}")))
                return False
            while True:
                self._frames.feed(data)
                while (message := self._frames.pop()) is not None:
                    self._inbox.put((message, received))
                if not (self._stamped and self._frames.partial):
                    return True
                if not readable(self._sock, 0.0):
                    return True
                data, received = self._receive()   # the rest of a message begun: stamped by its last bytes
                if not data:
                    return True    # closed: the next read says so
        except WireError as error:
            self._fail(error)
        except OSError as error:
            if not self._closing.is_set():
                self._fail(ConnectionError(self._lost(_reason(error))))
        return False

    def _receive(self) -> tuple[bytes, float]:
        """Bytes off the socket and the wall time they came. Kernel-stamped: at most the rest of the message
        begun, so that each message carries the time of its own bytes, not of a later one's."""
        if not self._stamped:
            data = self._sock.recv(RECEIVE_CHUNK)
            return data, time.perf_counter()
        data, ancillary, _, _ = self._sock.recvmsg(self._frames.wanted(), socket.CMSG_SPACE(TIMESPEC.size))
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(payload) >= TIMESPEC.size:
                seconds, nanoseconds = TIMESPEC.unpack_from(payload)
                return data, seconds + nanoseconds * 1e-9
        return data, self._now()

    def _fail(self, error: BaseException) -> None:
        self._inbox.put(error)
        self._failure = error

    def _lost(self, cause: str) -> str:
        said = f"lost the connection to the controller at {self.address}: {cause}"
        if self._process is not None:
            try:
                status = self._process.wait(timeout=0.5)
                said += f" (its process exited with status {status})"
            except subprocess.TimeoutExpired:
                pass
        return said
