"""`vcyto sweep`: a parameter study of the closed sorting loop, point by point, on any executor.

A spec (TOML) has four tables:

- ``[base]``: the run every point starts from, in the words of ``vcyto stream``: ``scenario`` (a scenario file,
  relative to the spec), ``set`` (a list of ``FIELD=VALUE`` overrides, as ``--set``) and any other stream or
  scenario option by its name (``cells``, ``count``, ``mix``, ``rate``, ``lead``, ``pulse``, ``model``, ``seed``,
  ``mesh_h``, ``saw_model``, ...), in the option's unit (ms for times).
- ``[parameters]``: what varies. A name is a ``[base]`` option (``lead``) or a dotted scenario field
  (``saw.streaming_force``, ``channel.inlets.1.v_hat``); its values a list, a range ``{start, stop, num}`` or
  ``{start, stop, step}`` (``log = true`` for geometric spacing), or, with random sampling, a distribution
  ``{uniform = [a, b]}``, ``{log_uniform = [a, b]}`` or ``{integers = [a, b]}``.
- ``[sweep]``: ``metrics`` (columns of the table), ``plot`` (the metric of the summary figure),
  ``sampling = "grid"`` (every combination) or ``"random"`` (``samples`` draws with ``sampling_seed``).

Every point runs with the base seed unless ``seed`` is a parameter (common random numbers: points differ by
their parameters, not by their noise), so a spec determines every result wherever it runs. A point's identity
is a hash of its effective inputs (the scenario as TOML and the stream settings): a re-run skips the points
already in the table. Points sharing a plant run in chunks on one worker, and each worker process keeps the
plants it built, so a plant (mesh, steady flows) is built once per worker and scenario, not once per point.

The package, by concern: ``model`` (the data: parameters, points, the sweep, ``SweepError``), ``spec`` (reading a
spec), ``points`` (a point as a run, and its id), ``metrics`` (what a row holds), ``worker`` (a chunk of points
on a worker and its plant cache), ``table`` (``results.csv``), ``run`` (the sweep on an executor, its summary),
``executors`` (local pool, Dask) and ``plot`` (the summary figure). What the command line and the benchmark use is
re-exported here.
"""

from .executors import check_scheduler, executor
from .metrics import metric_value
from .model import Parameter, Point, Sweep, SweepError
from .plot import save_plot
from .points import code_identity
from .run import report_lines, run_sweep
from .spec import load_sweep, parse_sweep
from .table import FIGURE, RESULTS, SUMMARY, ResultTable
from .worker import evaluate, simulate, worker_plant

__all__ = ["FIGURE", "RESULTS", "SUMMARY", "Parameter", "Point", "ResultTable", "Sweep", "SweepError",
           "check_scheduler", "code_identity", "evaluate", "executor", "load_sweep", "metric_value", "parse_sweep",
           "report_lines", "run_sweep", "save_plot", "simulate", "worker_plant"]
