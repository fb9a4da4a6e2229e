"""A figure drawn by a helper process that imports matplotlib while the run computes.

Importing matplotlib costs a ``vcyto paper`` run ~0.4 s of one core (its artists build their docstrings as
their classes are created), and drawing and writing the PNG ~0.25 s more, both after the run, while the user
waits. ``Painter`` starts this module as a helper process when the command starts: it imports matplotlib on
the core the command's own imports leave idle, draws a stand-in figure into memory (a process's first figure
costs ~0.15 s more than the next), then waits for one figure on its standard input (a pickled name, path and
plain data: arrays, lines, texts), draws it with the Agg backend, writes the PNG whole
(``vcyto.outputs.write_whole``: a temporary file moved in place) and ends without the interpreter's teardown
(0.13-0.17 s with matplotlib loaded). The command meanwhile runs; at its end it hands over the figure's data and
waits for the helper to finish, so the PNG exists when the command reports it.

The helper pays only where a core is idle: where one was, the command's wait for its figure fell from 0.39-0.41 s
to 0.16-0.22 s (2026-12-03, CHANGELOG.md); on a shared 2-core host at load average 12-16 it made ``vcyto paper 2``
slower, median wall 7.07 s against 5.58 s drawn in the command (``python examples/process_tricks.py --only
painter --pairs 5``: the helper's imports took CPU the run needed). So the command starts it only when the load
average leaves a core idle (``core_idle``), and otherwise draws the figure itself.

The helper imports only numpy, matplotlib and ``vcyto.outputs`` (no ``sim``), the same ``vcyto`` as the command
(its package's directory first on the helper's path). Whatever happens to it (it could not start, died, failed
to draw or left no figure), the command draws the same figure itself with the same function, as it did before,
so an error (a full disk) is reported exactly as then; the helper only ever saves time. Its output is
discarded. The PNG's bytes are the same either way (tested). It ends with the command: on Ctrl-C, an error or
the normal exit ``close`` stops it (SIGTERM, which it takes as Ctrl-C so that a figure being written leaves no
temporary file; SIGKILL after 2 s), and a helper whose command died sees its standard input close and exits.
"""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
from pathlib import Path

WAIT_S = 300.0          # drawing one figure takes well under a second; longer means the helper hangs


def pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save_figure(figure, path, dpi: int = 120) -> None:
    """Write ``figure`` as a PNG at ``path`` all at once: drawn into a temporary file beside it, then moved in
    place (``os.replace``), so an interrupted or failed save never leaves a truncated image under the name. zlib's
    fastest level: ~25 ms less of a ``vcyto paper`` run's wait for its figure, for a file 40 % larger (~175 kB)."""
    from ..outputs import write_whole
    write_whole(Path(path), lambda temporary: figure.savefig(temporary, format="png", dpi=dpi,
                                                             pil_kwargs={"compress_level": 1}))


def show_speed(axis, speed, extent):
    """The speed field (rows of y upward) over ``extent`` (um) on viridis."""
    return axis.imshow(speed, origin="lower", extent=extent, cmap="viridis", interpolation="bilinear")


def draw_lines(axis, lines):
    """``lines`` (x, y, colour, width in um) on ``axis`` at equal scales, with the axes' labels."""
    for xs, ys, colour, width in lines:
        axis.plot(xs, ys, color=colour, lw=width)
    axis.set_aspect("equal")
    axis.set_xlabel("x (um)")
    axis.set_ylabel("y (um)")


def paper_figure(plt, spec: dict):
    """``vcyto paper``'s figure: the speed field (``spec["speed"]``, rows of y upward, over ``spec["extent"]``)
    with the centroid path, membrane outlines and the device's inlets, outlets and SAW window
    (``spec["lines"]``: x, y, colour, width), the title and a colour bar."""
    # a fixed layout: the constrained layout engine cost ~50 ms of a 2 s command for the same picture
    figure, axis = plt.subplots(figsize=(7.5, 4.6))
    figure.subplots_adjust(left=0.08, right=0.99, bottom=0.11, top=0.92)
    image = show_speed(axis, spec["speed"], spec["extent"])
    draw_lines(axis, spec["lines"])
    axis.set_title(spec["title"])
    figure.colorbar(image, ax=axis, label="speed (m/s)", shrink=0.8)
    return figure


FIGURES = {"paper": paper_figure}


def draw(name: str, path, spec: dict, plt=None) -> None:
    """Draw figure ``name`` from ``spec`` and write it to ``path`` as a PNG, whole (in this process)."""
    plt = plt or pyplot()
    figure = FIGURES[name](plt, spec)
    try:
        save_figure(figure, path)
    finally:
        plt.close(figure)


def core_idle() -> bool:
    """Whether this machine has a core to spare for the helper: the 1-minute load average at least one below the
    number of cores (False where the load average is unknown)."""
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):
        return False
    return (os.cpu_count() or 1) - load >= 1.0


class Painter:
    """The helper process of one figure (module docstring). ``paint`` draws it there, or here if that fails."""

    def __init__(self, start: bool = True):
        self._process = None
        if not start or not sys.executable:
            return
        # this vcyto, installed or not, first on the helper's path: ``python -m`` would put the current directory
        # there, where another ``vcyto`` (or a ``numpy.py``) could stand
        package_parent = str(Path(__file__).resolve().parents[1])
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-c", "import runpy, sys; sys.path[0] = sys.argv.pop(1); "
                 "runpy.run_module('vcyto.studies.painter', run_name='__main__', alter_sys=True)", package_parent],
                # its standard output (nothing is written there) is read to its end: ``communicate`` then returns
                # as the helper exits, where with none to read it polls for the exit (up to 50 ms late)
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        except (OSError, ValueError):     # no helper: the figure is drawn here
            self._process = None

    def paint(self, name: str, path, spec: dict) -> str:
        """Write figure ``name`` to ``path``; returns where it was drawn ("helper" or "here")."""
        process = self._process
        if process is not None:
            try:
                process.communicate(pickle.dumps((name, str(path), spec), protocol=pickle.HIGHEST_PROTOCOL),
                                    timeout=WAIT_S)
                if process.returncode == 0 and os.path.getsize(path) > 0:
                    return "helper"
            except (OSError, subprocess.TimeoutExpired):       # it died before reading, or hangs
                pass
            finally:                                           # (an interruption here stops it too)
                self.close()
        draw(name, path, spec)
        return "here"

    def close(self):
        """Stop the helper if it is still waiting (an interrupted or failed run draws nothing)."""
        process, self._process = self._process, None
        if process is not None:
            _stop(process)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _stop(process: subprocess.Popen) -> None:
    """End the helper: asked first (SIGTERM: a figure being written removes its temporary file), then killed."""
    for end in (process.terminate, process.kill):
        if process.poll() is not None:
            break
        end()
        try:
            process.wait(timeout=2)
        except subprocess.TimeoutExpired:
            pass
    for pipe in (process.stdin, process.stdout):
        if pipe is not None:
            try:
                pipe.close()
            except OSError:            # (a pipe whose reader went away)
                pass


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def _main() -> int:
    """The helper: import matplotlib, read one figure, draw it; exit 0 when it is written, 1 otherwise (the
    command then draws it itself and reports any error), quietly when the command went away or stopped it."""
    signal.signal(signal.SIGTERM, _interrupt)      # as Ctrl-C: ``write_whole`` removes its temporary file
    try:
        plt = pyplot()
        _warm_up(plt)
        name, path, spec = pickle.load(sys.stdin.buffer)
        draw(name, path, spec, plt)
    except (EOFError, KeyboardInterrupt, BrokenPipeError):
        return 1
    except Exception as error:            # the command draws the figure itself and reports its own error, if any
        print(f"vcyto painter: {type(error).__name__}: {error}", file=sys.stderr)
        return 1
    # written and closed (``write_whole``): the interpreter's teardown with matplotlib loaded took 0.13-0.17 s,
    # which the command waited for (measured); nothing is left for it to do
    sys.stderr.flush()
    os._exit(0)


def _warm_up(plt) -> None:
    """Draw a stand-in of ``vcyto paper``'s figure into memory while the command computes: a process's first figure
    costs ~0.15 s more than the next (fonts, text layout), which the command would otherwise wait for at its end.
    Nothing of it reaches the real figure's bytes (tests/test_painter.py compares them with a figure drawn here)."""
    import io

    import numpy as np
    ramp = np.linspace(0.0, 1.0, 220 * 300).reshape(220, 300)
    spec = {"speed": ramp, "extent": (0.0, 300.0, 0.0, 220.0), "title": "Scenario: warming up the helper (t = 0 ms)",
            "lines": [(np.array([0.0, 300.0]), np.array([0.0, 220.0]), "white", 1.0)]}
    figure = paper_figure(plt, spec)
    try:
        figure.savefig(io.BytesIO(), format="png", dpi=120, pil_kwargs={"compress_level": 1})
    finally:
        plt.close(figure)


if __name__ == "__main__":
    sys.exit(_main())
