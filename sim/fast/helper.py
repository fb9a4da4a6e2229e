"""The helper thread of the fluid steps: one daemon thread per process that runs what it is given, in order.

A fluid step hands it the next step's momentum integrals (``sim.method.fluid.NavierStokes.prefetch``), so that
they are computed while the caller moves the membranes; ``SpeedSettings.prefetch`` False (``sim.fast.speed``)
computes them in the step instead (the same bits).
"""

from __future__ import annotations

import atexit
import os
import queue
import sys
import threading
from concurrent.futures import Future

from . import speed


def prefetch_wanted() -> bool:
    """Whether a step computes the next step's momentum integrals ahead on a helper thread (``NavierStokes.step``);
    ``SpeedSettings.prefetch`` False (``sim.fast.speed``) computes them in the step itself (the same bits: for
    measurements and tests)."""
    return speed.current().prefetch


class Helper:
    """One daemon thread that runs the tasks submitted to it one at a time, in order, each through a
    ``concurrent.futures.Future`` (cancellable until it starts).

    A daemon, unlike ``ThreadPoolExecutor``'s workers: an idle helper must not hold the process open. The
    executable ends with ``os._exit`` once everything is written (``vcyto.cli.exit_now``), but only when no
    non-daemon thread is alive; a pool's idle worker sent every FE-IB run through the interpreter's teardown
    instead (0.15 s; 0.4 s with a Rerun recording; measured). At exit (``atexit``: both the quick and the ordinary
    exit run it) the helper finishes what it was given, at most a step's integrals (~1 ms), and stops, so the
    interpreter's teardown never meets it inside a kernel."""

    def __init__(self):
        self._tasks: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="vcyto-momentum", daemon=True)
        self._thread.start()
        self._stopped = False
        atexit.register(self.stop)

    def stop(self, timeout: float = 10.0):
        """Let the queued tasks finish, then end the thread (waiting at most ``timeout`` seconds); later
        submissions are refused (``RuntimeError``: the caller computes them itself)."""
        self._stopped = True
        self._tasks.put(None)
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def submit(self, function, *arguments) -> Future:
        if self._stopped or sys.is_finalizing():     # as ThreadPoolExecutor: no new work at shutdown
            raise RuntimeError("cannot schedule new work after interpreter shutdown")
        future: Future = Future()
        self._tasks.put((future, function, arguments))
        return future

    def _run(self):
        while (task := self._tasks.get()) is not None:
            future, function, arguments = task
            if future.set_running_or_notify_cancel():
                try:
                    future.set_result(function(*arguments))
                except BaseException as error:      # handed to the caller's ``result()``
                    future.set_exception(error)
            # hold nothing while waiting: the task's arguments (a solver's buffers) would stay alive here
            task = future = function = arguments = None


_HELPER: Helper | None = None                 # the process's helper (``helper``)
_HELPER_LOCK = threading.Lock()


def helper() -> Helper:
    """The one helper thread the fluid steps of a process share (``NavierStokes.prefetch``): one thread, so its
    tasks run one at a time, in order."""
    global _HELPER
    with _HELPER_LOCK:
        if _HELPER is None:
            _HELPER = Helper()
        return _HELPER


def _forget_helper():
    """A forked child builds its own helper (the parent's thread is not in it), under a lock of its own."""
    global _HELPER, _HELPER_LOCK
    _HELPER, _HELPER_LOCK = None, threading.Lock()


os.register_at_fork(after_in_child=_forget_helper)
