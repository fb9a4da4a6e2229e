"""The per-cell table of a run: one row per admitted cell, written to Parquet as cells leave (pyarrow).

A row is a sort report's per-cell record (``vcyto.sortreport``) with its pairs split into two columns
(``pulse_ms`` -> ``pulse_on_ms``, ``pulse_off_ms``; ``area_ratio_range`` -> ``area_ratio_min``, ``area_ratio_max``;
``spacing_over_h`` -> ``spacing_min_h``, ``spacing_max_h``); missing values are nulls. Rows are in the order the
cells left the channel (then those still in it, then those never injected when a run stops): sort by ``key`` for
arrival order. The writer keeps one row group (``ROWS_PER_GROUP`` rows) in memory, so a run's memory does not grow
with its length; pandas (``read_parquet``), polars and pyarrow read the file.
"""

from __future__ import annotations

import operator
import os
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

ROWS_PER_GROUP = 8192
SCHEMA = pa.schema([
    ("key", pa.int64()), ("type", pa.string()), ("true_class", pa.string()), ("arrival_ms", pa.float64()),
    ("event_id", pa.int64()), ("detected_class", pa.string()), ("detection_time_ms", pa.float64()),
    ("fluorescence", pa.float64()), ("scatter", pa.float64()), ("velocity_mm_s", pa.float64()),
    ("predicted_arrival_ms", pa.float64()), ("decision", pa.string()), ("reason", pa.string()),
    ("pulse_on_ms", pa.float64()), ("pulse_off_ms", pa.float64()), ("outlet", pa.string()),
    ("exit_time_ms", pa.float64()), ("exit_y_um", pa.float64()), ("area_ratio", pa.float64()),
    ("area_ratio_min", pa.float64()), ("area_ratio_max", pa.float64()), ("spacing_min_h", pa.float64()),
    ("spacing_max_h", pa.float64()), ("area_corrected", pa.float64()), ("outcome", pa.string()),
])
PAIRS = {"pulse_ms": ("pulse_on_ms", "pulse_off_ms"), "area_ratio_range": ("area_ratio_min", "area_ratio_max"),
         "spacing_over_h": ("spacing_min_h", "spacing_max_h")}
_SINGLE = tuple(name for name in SCHEMA.names if not any(name in pair for pair in PAIRS.values()))
_ROW = operator.itemgetter(*_SINGLE, *PAIRS)        # a whole record's values, in one call


def flat(record: dict) -> dict:
    """A per-cell record as a table row (its pairs split)."""
    row = {name: value for name, value in record.items() if name not in PAIRS}
    for pair, (low, high) in PAIRS.items():
        values = record.get(pair)
        row[low], row[high] = (values[0], values[1]) if values else (None, None)
    return row


_PAIRED = frozenset(name for pair in PAIRS.values() for name in pair)


def record_of(row: dict) -> dict:
    """A table row as a per-cell record (the inverse of ``flat``)."""
    record = {name: value for name, value in row.items() if name not in _PAIRED}
    for pair, (low, high) in PAIRS.items():
        record[pair] = [row[low], row[high]] if row.get(low) is not None else None
    return record


class CellTable:
    """Rows appended as cells leave, written a row group at a time to ``path`` (created or truncated). The rows
    not yet written are kept as columns (a list per column of the table: ``flat`` of each record, without building
    a dict per row)."""

    def __init__(self, path: Path, rows_per_group: int = ROWS_PER_GROUP):
        from .arrowshim import ready_pyarrow
        ready_pyarrow()                        # in the vcyto command's process: without importing pandas
        self.path = Path(path)
        self.failed = False
        self._writer = None
        self._writer = self._guarded(pq.ParquetWriter, str(self.path), SCHEMA, compression="zstd")
        self._columns: dict[str, list] = {name: [] for name in SCHEMA.names}
        self._single = [self._columns[name] for name in _SINGLE]
        self._pairs = [(self._columns[low], self._columns[high]) for low, high in PAIRS.values()]
        self._pending = 0                      # rows in ``_columns``
        self.rows_per_group = rows_per_group
        self.written = 0

    def _guarded(self, call, *args, **kwargs):
        """``call``; a failed write (a full disk) is an ``OSError`` naming the table's file, raised once: the
        table then takes no more rows."""
        try:
            return call(*args, **kwargs)
        except OSError as error:
            self.failed = True
            number = error.errno or (28 if "No space left" in str(error) else 5)
            raise OSError(number, os.strerror(number), str(self.path)) from None

    def append(self, record: dict):
        """One per-cell record as a row (``flat``: its pairs split, a name it lacks null)."""
        if self.failed:
            return
        try:
            values = _ROW(record)
        except KeyError:                       # a record without some of the names: nulls there
            values = tuple(record.get(name) for name in (*_SINGLE, *PAIRS))
        single = len(_SINGLE)
        for column, value in zip(self._single, values):
            column.append(value)
        for (low, high), pair in zip(self._pairs, values[single:]):
            low.append(pair[0] if pair else None)
            high.append(pair[1] if pair else None)
        self._pending += 1
        if self._pending >= self.rows_per_group:
            self._write()

    def append_columns(self, columns: dict, count: int):
        """``count`` rows given as columns (table rows' names: a sequence, or one value for every row; a name not
        given is null), after the rows appended so far."""
        if self.failed:
            return
        self._write()
        arrays = []
        for column in SCHEMA:
            value = columns.get(column.name)
            if value is None:
                arrays.append(pa.nulls(count, column.type))
            elif isinstance(value, (str, int, float)):
                arrays.append(pa.repeat(pa.scalar(value, column.type), count))
            else:
                arrays.append(pa.array(value, column.type))
        table = pa.Table.from_arrays(arrays, schema=SCHEMA)
        self._guarded(self._writer.write_table, table, row_group_size=self.rows_per_group)
        self.written += count

    def _write(self):
        if self._pending and not self.failed:
            self._guarded(self._writer.write_table, pa.Table.from_pydict(self._columns, schema=SCHEMA))
            self.written += self._pending
            for column in self._columns.values():      # emptied in place (``_single`` and ``_pairs`` hold them)
                column.clear()
            self._pending = 0

    def close(self):
        if self._writer is not None:
            failed_before = self.failed
            try:
                self._write()
            finally:
                writer, self._writer = self._writer, None
                try:
                    self._guarded(writer.close)
                except OSError:
                    if not failed_before:
                        raise


def read_table(path: Path, columns=None) -> pa.Table:
    """The table of ``path`` (only ``columns`` if given)."""
    return pq.read_table(str(path), columns=columns)


def records(path: Path, batch_rows: int = 65536):
    """The per-cell records of the table at ``path``, a row group at a time (memory: one batch)."""
    for batch in pq.ParquetFile(str(path)).iter_batches(batch_size=batch_rows):
        for row in batch.to_pylist():
            yield record_of(row)
