"""``results.csv``, the table of a sweep's finished points, written as they finish (a re-run skips them), and
the names of the sweep's other files."""

from __future__ import annotations

import csv
import io
import os
import re
from pathlib import Path

from .model import SweepError, one_line

RESULTS, FIGURE, SUMMARY = "results.csv", "summary.png", "sweep.json"
TEXT_COLUMNS = ("point", "status", "error", "inputs", "vcyto")
INTEGER = re.compile(r"[+-]?[0-9]+")
ROW_STATUSES = ("ok", "failed", "truncated")   # truncated: the run hit a cap before its sample ended


class ResultTable:
    """``results.csv``: a header, then one row per finished point, appended and flushed as points finish."""

    def __init__(self, path: Path, columns: list[str]):
        self.path = path
        self.columns = columns
        self.repaired = 0

    def load(self) -> dict[str, dict]:
        """The rows already written, by point id (the last row of a point wins). A torn last line (a sweep killed
        while writing) is dropped and the file rewritten; a table with other columns is refused."""
        if not self.path.exists() or self.path.stat().st_size == 0:
            self.rewrite([])
            return {}
        text = self.path.read_text()
        lines = text.splitlines(keepends=True)
        header = next(csv.reader([lines[0]]))
        if header != self.columns:
            raise SweepError(f"{self.path} holds the results of a different sweep or of an older vcyto (columns "
                             f"{', '.join(header)}); choose another --output or remove the file")
        rows = {}
        for line in lines[1:]:
            fields = next(csv.reader([line]), [])
            if line.endswith("\n") and len(fields) == len(self.columns) and fields[1] in ROW_STATUSES:
                rows[fields[0]] = {column: field if column in TEXT_COLUMNS else _value(field)
                                   for column, field in zip(self.columns, fields)}
            else:
                self.repaired += 1
        if self.repaired:
            self.rewrite(rows.values())
        return rows

    def append(self, rows):
        with open(self.path, "a", newline="") as file:
            writer = csv.writer(file, lineterminator="\n")
            writer.writerows([_cell(row.get(column)) for column in self.columns] for row in rows)
            file.flush()
            os.fsync(file.fileno())

    def rewrite(self, rows):
        """Replace the table by ``rows`` atomically (a temporary file renamed over it)."""
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerow(self.columns)
        writer.writerows([_cell(row.get(column)) for column in self.columns] for row in rows)
        temporary = self.path.with_suffix(".csv.tmp")
        temporary.write_text(buffer.getvalue())
        os.replace(temporary, self.path)


def _value(text: str):
    """A cell read back as the run wrote it: empty is None, an integer an int, a number a float (NaN too),
    anything else (such as outlet counts "lower=4 upper=2") text."""
    if text == "":
        return None
    if INTEGER.fullmatch(text):
        return int(text)
    try:
        return float(text)
    except ValueError:
        return text


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(float(value))
    return one_line(str(value))
