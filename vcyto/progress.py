"""Progress on stderr: a live line on a terminal, a line every few seconds otherwise, nothing when quiet; a long
run's bar (tqdm) with its rate, real-time factor and ETA."""

from __future__ import annotations

import sys
import time


class Progress:
    def __init__(self, quiet: bool = False, interval: float = 0.25, stream=None):
        self.quiet = quiet
        stream = stream if stream is not None else sys.stderr      # the stderr of now, not of the import
        self.stream = stream
        self.live = stream.isatty()
        self.interval = interval if self.live else 5.0
        self._last = 0.0
        self._pending = False
        self._bar = None

    def note(self, message: str):
        """A one-off message (a phase starting)."""
        if self.quiet:
            return
        self._end_live_line()
        if getattr(self, "_bar", None) is not None:
            self._bar.write(f"  .. {message}", file=self.stream)
            return
        print(f"  .. {message}", file=self.stream, flush=True)

    def run(self, total: int, simulated: float = 0.0):
        """A run of ``total`` cells: a bar of the cells that left, with events/s, the real-time factor (simulated
        over wall time) and tqdm's ETA from the rate the cells leave; ``advance`` moves it."""
        if self.quiet:
            return
        from tqdm import tqdm
        self._end_live_line()
        self._bar = tqdm(total=total, unit="cell", file=self.stream, mininterval=self.interval, dynamic_ncols=True,
                         leave=True, ascii=not self.live, smoothing=0.1, desc="  ..")
        self._started = time.perf_counter()
        self._state = (0, simulated)

    def advance(self, left: int, events: int, simulated_s: float):
        """The run's state: ``left`` cells out of the channel, ``events`` detected, ``simulated_s`` of device time."""
        bar = getattr(self, "_bar", None)
        if bar is None:
            return
        self._state = (events, simulated_s)
        now = time.perf_counter()
        if now - self._last >= self.interval:
            self._last = now
            self._postfix(now)
        bar.update(left - bar.n)

    def _postfix(self, now: float):
        events, simulated_s = self._state
        wall = max(now - self._started, 1e-9)
        self._bar.set_postfix_str(f"{events / wall:,.0f} events/s, {simulated_s / wall:.2f}x real time, "
                                  f"t = {simulated_s:.3f} s", refresh=False)

    def update(self, message: str):
        """A frequent status; shown at most every ``interval`` seconds."""
        if self.quiet:
            return
        now = time.perf_counter()
        if now - self._last < self.interval:
            return
        self._last = now
        if self.live:
            print(f"\r  .. {message}\033[K", end="", file=self.stream, flush=True)
            self._pending = True
        else:
            print(f"  .. {message}", file=self.stream, flush=True)

    def _end_live_line(self):
        if self._pending:
            print(file=self.stream)
            self._pending = False

    def close(self):
        if getattr(self, "_bar", None) is not None:
            self._postfix(time.perf_counter())
            self._bar.close()
            self._bar = None
        if not self.quiet:
            self._end_live_line()

    def __call__(self, message: str):
        self.note(message)


def rows_until_interrupted(measure) -> tuple[list, bool]:
    """``measure(rows)`` appends each row as it finishes; the rows, and whether an interrupt (Ctrl-C, or SIGTERM
    turned into one) ended it early: the rows finished before it are still results (a table marked PARTIAL)."""
    rows: list = []
    try:
        measure(rows)
    except KeyboardInterrupt:
        return rows, True
    return rows, False
