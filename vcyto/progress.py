"""Progress on stderr: a live line on a terminal, a line every few seconds otherwise, nothing when quiet."""

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

    def note(self, message: str):
        """A one-off message (a phase starting)."""
        if self.quiet:
            return
        self._end_live_line()
        print(f"  .. {message}", file=self.stream, flush=True)

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
