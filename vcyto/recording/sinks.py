"""Sinks of the closed loop (MCAP, Rerun) run on one background thread, in step order.

The loop hands each control period's snapshot (observation, truth, decisions: immutable) to a bounded
queue and goes on with the plant; one worker thread turns them into JSON and Rerun archetypes while the
main thread is in the linear solver (which releases the GIL). The recording is the same, message for
message, as with the sinks called inline; what changes is that their cost overlaps the physics.

- Order: one worker, FIFO: the sinks see the steps in order, as inline.
- Fields: the flow field payload is computed on the loop's thread at the step it belongs to (the plant
  moves on), and only at steps where a sink's ``field_every`` asks for it.
- Batches: the loop's thread hands the steps over in batches (``batch_steps`` steps, or what came in
  ``batch_seconds`` of wall time), so the hand-over (a lock, the signals held) costs once per batch, not per
  step; a sink with ``on_steps(records)`` gets the batch whole (the MCAP recorder writes it as columns and
  flushes), others get ``on_step`` per step.
- Bounded: at most ``depth`` batches wait in the queue (the loop blocks when the sinks fall behind), so a
  killed process loses at most the batch being filled and ``depth`` queued ones beyond the last flush.
- Failures: an exception in a sink (a full disk) stops the loop at its next step with that exception, raised
  once; the sinks are given nothing more after it (a writer that failed would fail again), and ``close`` still
  closes each of them.
- ``close`` waits until every queued step has been written, then closes the sinks (the caller calls it
  on normal exit, Ctrl-C and SIGTERM, as for a single sink).
- Deferred: a ``Deferred`` sink is built on the worker thread as it starts, before any step, so building it
  (importing Rerun and opening its recording: ~0.7-0.9 s) overlaps the plant's set-up instead of preceding it.
- Live: a ``LiveView`` (the view streamed to a viewer) is fed from the worker through its own bounded queue on
  its own thread, and never waits: a batch that finds the queue full is dropped, its steps counted as dropped
  frames, which the run's end (``on_end``: the MCAP's ``run_end``) and the summary report. A recording (the
  MCAP, an ``.rrd``) is complete instead: the loop waits for it.
"""

from __future__ import annotations

import dataclasses
import queue
import threading
import time

from .runfiles import signals_held

_STOP = object()
_END = object()


class Deferred:
    """A sink that ``BackgroundSinks`` builds on its worker thread: ``build()`` returns the sinks (none, one or
    more) it stands for; ``field_every`` is theirs, known before they exist (the loop's thread computes a step's
    flow field when a sink asks for it)."""

    def __init__(self, build, field_every: int = 0):
        self.build, self.field_every = build, field_every


BATCH_STEPS = 256             # steps handed over together
BATCH_SECONDS = 0.25          # wall time after which a partial batch is handed over (the live view's lag)


class BackgroundSinks:
    def __init__(self, sinks, depth: int = 2, batch_steps: int = BATCH_STEPS, batch_seconds: float = BATCH_SECONDS):
        self.sinks = list(sinks)
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self.batch_steps, self.batch_seconds = max(1, batch_steps), batch_seconds
        self._batch: list = []
        self._handed = time.monotonic()
        self._failure: BaseException | None = None
        self._failed = False                # a sink failed: nothing more is given to the sinks
        self._thread = threading.Thread(target=self._work, name="vcyto-sinks", daemon=True)
        self._thread.start()

    def _build(self):
        """Replace each ``Deferred`` by the sinks it builds (a failure to build is a sink's failure)."""
        if not any(isinstance(sink, Deferred) for sink in self.sinks):
            return
        built = []
        try:
            for sink in self.sinks:
                built += sink.build() if isinstance(sink, Deferred) else [sink]
        except BaseException as error:      # reported to the loop's thread at its next step
            self._failure, self._failed = error, True
        self.sinks = built                  # one assignment: the loop's thread reads the list as a whole

    def _work(self):
        self._build()
        while True:
            item = self._queue.get()
            try:
                if item is _STOP:
                    return
                if not self._failed and isinstance(item, tuple) and item[0] is _END:
                    ending = dict(item[1])
                    for sink in self.sinks:             # a live view's frames, settled before the end is written
                        if hasattr(sink, "settle"):
                            ending.update(sink.settle())
                    for sink in self.sinks:
                        if hasattr(sink, "on_end"):
                            sink.on_end(ending)
                elif not self._failed:
                    for sink in self.sinks:
                        steps_of(sink)(item)
            except BaseException as error:     # reported to the loop's thread at its next step
                self._failure, self._failed = error, True
            finally:
                self._queue.task_done()

    def _fields_due(self, step: int) -> bool:
        return any(getattr(sink, "field_every", 0) and step % sink.field_every == 0 for sink in self.sinks)

    def on_step(self, record):
        self._raise_failure()
        if record.fields is not None and self._fields_due(record.step):
            payload = record.fields()
            fields = lambda: payload                       # noqa: E731 - a snapshot of this step's field
        else:
            fields = None
        self._batch.append(dataclasses.replace(record, fields=fields) if record.fields is not None else record)
        if len(self._batch) >= self.batch_steps or time.monotonic() - self._handed > self.batch_seconds:
            self._hand_over()

    def _hand_over(self):
        """Queue the steps gathered so far as one batch."""
        if self._batch:
            batch, self._batch = self._batch, []
            with signals_held():
                self._queue.put(batch)
        self._handed = time.monotonic()

    def on_end(self, ending: dict):
        """The run's end (status, reason, the sort report's figures), after its last step."""
        self._raise_failure()
        self._hand_over()
        with signals_held():
            self._queue.put((_END, ending))

    def drain(self):
        """Wait until every queued step is written; re-raise a sink's failure."""
        if self._thread.is_alive():
            self._hand_over()
            with signals_held():
                self._queue.put(_STOP)
            self._thread.join()
        self._raise_failure()

    def close(self):
        """Write what is queued, then close every sink (even after a failure, and each even if another's close
        fails); re-raise a sink's failure not yet raised, else the first failure to close."""
        failure = None
        try:
            self.drain()
        except BaseException as error:
            failure = error
        for sink in self.sinks:
            try:
                sink.close()
            except BaseException as error:
                failure = failure or error
        if failure is not None:
            raise failure

    def _raise_failure(self):
        if self._failure is not None:
            failure, self._failure = self._failure, None
            raise failure


def steps_of(sink):
    """A function that gives ``sink`` a list of steps: its ``on_steps``, or ``on_step`` for each."""
    whole = getattr(sink, "on_steps", None)
    if whole is not None:
        return whole

    def each(records):
        for record in records:
            sink.on_step(record)
    return each


LIVE_DEPTH = 2                # batches waiting for a live view; more are dropped
LIVE_CHUNK = 64               # steps a live view is given at once (``on_steps``), between looks at the run's end
SETTLE_SECONDS = 0.25         # how long the run's end waits for the live view's step in progress


class LiveView:
    """``sink`` (a live view) on its own thread behind a bounded queue that never blocks the one feeding it: a batch
    of steps that finds ``depth`` batches waiting is dropped and its steps counted (``dropped``; ``frames``: every
    step handed over); the sink is given the steps ``LIVE_CHUNK`` at a time (its ``on_steps``, else ``on_step``
    for each). After a gap the sink's ``after_gap(record)``, if it has one, is called with the first step shown
    again (it forgets the cells that left meanwhile). ``settle`` ends the showing: the waiting batches are
    dropped and the step in progress is given ``SETTLE_SECONDS``; ``close`` then closes the sink, unless it is
    still busy (``ConnectionError``: the view is left as it is). A failure of the sink is raised to the feeder at
    its next batch, as a sink's of ``BackgroundSinks``."""

    def __init__(self, sink, depth: int = LIVE_DEPTH):
        self.sink, self.field_every = sink, getattr(sink, "field_every", 0)
        self.frames = self.dropped = 0
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._gap = self._settling = self._failed = False
        self._failure: BaseException | None = None
        self._counting = threading.Lock()          # the feeder and the view's thread both count dropped frames
        self._thread = threading.Thread(target=self._work, name="vcyto-live-view", daemon=True)
        self._thread.start()

    def on_steps(self, records):
        if self._failure is not None:
            failure, self._failure = self._failure, None
            raise failure
        self.frames += len(records)
        if self._settling or self._failed:
            self._drop(len(records))
            return
        try:
            self._queue.put_nowait((records, self._gap))
            self._gap = False
        except queue.Full:
            self._drop(len(records))
            self._gap = True

    def _drop(self, count: int):
        with self._counting:
            self.dropped += count

    def _work(self):
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            records, gap = item
            try:
                if gap and hasattr(self.sink, "after_gap") and records and not self._failed:
                    self.sink.after_gap(records[0])
                show = steps_of(self.sink)
                for shown in range(0, len(records), LIVE_CHUNK):
                    if self._settling or self._failed:
                        self._drop(len(records) - shown)
                        break
                    show(records[shown:shown + LIVE_CHUNK])
            except BaseException as error:
                self._failure, self._failed = error, True

    def settle(self) -> dict:
        """Stop showing: drop what waits, give the step in progress ``SETTLE_SECONDS``; the frames shown and
        dropped."""
        if not self._settling:
            self._settling = True
            while True:
                try:
                    records, _ = self._queue.get_nowait()
                except queue.Empty:
                    break
                self._drop(len(records))
            self._queue.put(_STOP)
            self._thread.join(SETTLE_SECONDS)
        return {"view_frames": self.frames, "view_frames_dropped": self.dropped}

    def close(self):
        self.settle()
        if self._thread.is_alive():
            raise ConnectionError(f"the view was still drawing a step {SETTLE_SECONDS:g} s after the run ended")
        failure, self._failure = self._failure, None
        try:
            self.sink.close()
        finally:
            if failure is not None:
                raise failure
