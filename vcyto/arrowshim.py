"""pyarrow's first conversion without importing pandas, in the vcyto command's own process only.

pyarrow's first conversion of a Python sequence imports pandas where it is installed, only to recognise pandas
objects among the values; vcyto gives it none. ``spare_pandas_import`` (called by ``vcyto.cli.run``) lets
``ready_pyarrow`` make that first conversion while pandas cannot be imported (``vcyto.recording.viewer.import_rerun``
says what it saves and why a Python user's process is left alone). Flat, beside the per-cell table and the viewer
that both use it.
"""

from __future__ import annotations

import functools
import sys


class _NoPandasNow:
    """An import finder that refuses pandas (``import_rerun``)."""

    def find_spec(self, name, path=None, target=None):
        if name == "pandas" or name.startswith("pandas."):
            raise ImportError("pandas is not needed for this conversion (vcyto.arrowshim.ready_pyarrow)")
        return None


_spare_pandas = False         # set by the vcyto executable for its own process only (``spare_pandas_import``)


def spare_pandas_import() -> None:
    """In the ``vcyto`` executable's own process (``vcyto.cli.run``), let ``import_rerun`` keep pyarrow from
    importing pandas. Never called for a Python user of vcyto: their pyarrow converts pandas objects as usual."""
    global _spare_pandas
    _spare_pandas = True


@functools.lru_cache(maxsize=None)
def ready_pyarrow():
    """The ``pyarrow`` module, its first conversion made as ``import_rerun`` says (the per-cell table's writer makes
    one too: a run's first row group, or a short run's exit)."""
    import pyarrow
    if _spare_pandas and "pandas" not in sys.modules:
        finder = _NoPandasNow()
        sys.meta_path.insert(0, finder)
        try:
            pyarrow.array([""])
        finally:
            sys.meta_path.remove(finder)
    return pyarrow
