"""A run's summary and FCS events written as it goes, so that a run killed outright (SIGKILL, a power cut) leaves
them readable up to its last checkpoint.

``vcyto stream`` writes its JSON summary, FCS events and gate when the run ends (complete, interrupted or failed);
a process killed before that could leave only its reservations. A ``Checkpoint`` rewrites them every
``CHECKPOINT_SECONDS`` of wall time (longer when a checkpoint costs more than ``1 / SPACING`` of that time), each
whole (``vcyto.outputs.write_whole``: a kill mid-write leaves the previous checkpoint):

- the summary: ``"status": "running"``, ``"partial": true`` and ``checkpoint`` (how far the run had got: simulated
  and wall time, the cells that had left, the events in the FCS file), with the statistics of the cells that had
  left by then (``sortreport.Tally``), so nothing in it claims a finished run;
- the FCS events: every detected cell that had left, up to the earliest detection of a cell still in the channel
  (so that the events stay in time order as later ones are added), keyword ``VCYTO_STATUS`` = ``running``; each
  checkpoint copies the previous file's events and adds the new ones (memory: the events since the last one);
- the gate (Gating-ML), once: it depends on the settings only.

The run's end replaces all three. The per-cell table (Parquet) is readable only once the run closes it.
"""

from __future__ import annotations

import shutil
import time

import numpy as np

from .. import outputs
from ..sortreport import rejected_by
from . import fcs, gatingml

CHECKPOINT_SECONDS = 1.0       # wall time between checkpoints
SPACING = 50                   # ... at least this many times what the last one cost


class Checkpoint:
    """The summary (``summary_path``), FCS events (``fcs_path``) and gate (``gate_path``) of a run in progress; its
    ``SortLedger`` gives it each per-cell record (``add``) and asks it to write when ``due``."""

    def __init__(self, summary_path, fcs_path, gate_path, run_id: str, settings, scenario, keywords: dict,
                 interval: float = CHECKPOINT_SECONDS):
        self.paths = {"summary": summary_path, "fcs": fcs_path, "gate": gate_path}
        self.run_id, self.settings, self.scenario, self.interval = run_id, settings, scenario, interval
        self.keywords = {**keywords, "VCYTO_STATUS": "running"}
        self.started = time.monotonic()
        self.next = self.started + interval
        self.rows: list = []                # events of cells that left, not yet in the file
        self.count, self.head = 0, 0        # events in the file; where its data begin
        self.largest = np.zeros(len(fcs.CHANNELS))
        self.gate_written = False

    def add(self, record: dict):
        if record["detected_class"] is not None:
            self.rows.append(fcs.event_row(record))

    def due(self) -> bool:
        return time.monotonic() >= self.next

    def write(self, ledger):
        """Write the checkpoint of ``ledger`` (``sortreport.SortLedger``) at its time."""
        started = time.monotonic()
        if not self.gate_written:
            gatingml.write_gatingml(self.paths["gate"], self.settings.detector.gate)
            self.gate_written = True
        self._events(ledger.earliest_open_event())
        outputs.write_into(self.paths["summary"], outputs.strict_json(self._summary(ledger)) + "\n")
        self.next = time.monotonic() + max(self.interval, SPACING * (time.monotonic() - started))

    def finish_events(self, result: dict, keywords: dict):
        """The run's final FCS events (all of them, ``result``'s keywords and ``keywords``): the events already in the
        file are copied, not read back into memory, so the run's end costs no more memory for a longer run."""
        self.keywords = keywords
        self._events(np.inf, result, whole=True)

    def _events(self, before: float, result: dict | None = None, whole: bool = False):
        """Add to the FCS file the events detected before ``before`` (s), in time order (``whole``: rewritten even
        with none to add)."""
        rows = np.array(self.rows, dtype="<f8").reshape(-1, len(fcs.CHANNELS))
        rows = rows[np.argsort(rows[:, 0], kind="stable")]
        ready = rows[:, 0] < round(before / fcs.TIMESTEP) if np.isfinite(before) else np.ones(len(rows), bool)
        new, self.rows = rows[ready], rows[~ready].tolist()
        if not len(new) and self.count and not whole:
            return
        self.largest = np.maximum(self.largest, new.max(axis=0, initial=0.0))
        result = result or {"model": self.settings.model, "seed": self.settings.seed,
                            "wall_time_s": time.monotonic() - self.started}
        head = fcs.fcs_head(self.count + len(new), len(fcs.CHANNELS),
                            fcs.fcs_keywords(result, self.largest, self.keywords, self.settings, self.scenario))
        previous, size = self.paths["fcs"], self.count * len(fcs.CHANNELS) * 8

        def write(temporary):
            with open(temporary, "wb") as handle:
                handle.write(head)
                if size:
                    with open(previous, "rb") as old:
                        old.seek(self.head)
                        shutil.copyfileobj(_Limited(old, size), handle)
                handle.write(np.ascontiguousarray(new).tobytes())
        outputs.write_whole(self.paths["fcs"], write)
        self.count, self.head = self.count + len(new), len(head)

    def _summary(self, ledger) -> dict:
        now = ledger.time
        statistics = ledger.tally.statistics(now, rejected_by(ledger.sample.rejected, now), self.scenario,
                                             ledger.unexpected)
        return {"status": "running", "partial": True,
                "reason": (f"the run had not finished at its last checkpoint (t = {now * 1e3:.3f} ms of simulated "
                           "time): if no vcyto process is running it, it was killed then; the figures are those of "
                           "the cells that had left"),
                "run_id": self.run_id,
                "checkpoint": {"simulated_time_ms": now * 1e3, "wall_time_s": time.monotonic() - self.started,
                               "written_unix_s": time.time(), "cells_left": statistics["cells"],
                               "fcs_events": self.count},
                "simulated_time_ms": now * 1e3, "model": self.settings.model, "seed": self.settings.seed,
                "statistics": statistics}


class _Limited:
    """The next ``size`` bytes of a file, read in parts (``shutil.copyfileobj``)."""

    def __init__(self, handle, size: int):
        self.handle, self.left = handle, size

    def read(self, length: int = -1) -> bytes:
        part = self.handle.read(self.left if length < 0 else min(length, self.left))
        self.left -= len(part)
        return part
