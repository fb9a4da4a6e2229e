"""vcyto.studies.painter: a figure drawn by a helper process started early. The same bytes as drawn in the process
itself; every way the helper can fail falls back to drawing here, which reports errors as before; the helper
never outlives its command."""

import signal
import subprocess
import sys

import numpy as np
import pytest

from vcyto.studies import painter
from vcyto.studies.painter import Painter


def spec():
    rng = np.random.default_rng(4)
    xs = np.linspace(0.0, 300.0, 50)
    return {"speed": rng.uniform(0.0, 0.05, (22, 30)), "extent": (0, 300.0, 0, 220.0),
            "lines": [(xs, 100 + 20 * np.sin(xs / 40), "w", 1.2), ([0.0, 0.0], [40.0, 80.0], "tab:cyan", 4)],
            "title": "paper scenario 2: melanoma leaves by the upper outlet at t = 2.01 ms"}


def test_the_helper_draws_the_same_bytes_as_this_process(tmp_path):
    with Painter() as helper:
        assert helper.paint("paper", tmp_path / "helper.png", spec()) == "helper"
    assert Painter(start=False).paint("paper", tmp_path / "here.png", spec()) == "here"
    drawn = (tmp_path / "helper.png").read_bytes()
    assert drawn.startswith(b"\x89PNG\r\n\x1a\n") and len(drawn) > 10_000
    assert drawn == (tmp_path / "here.png").read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["helper.png", "here.png"]     # no temporary file left


def test_a_helper_that_died_is_replaced_by_drawing_here(tmp_path):
    helper = Painter()
    helper._process.send_signal(signal.SIGKILL)
    helper._process.wait(timeout=30)
    assert helper.paint("paper", tmp_path / "figure.png", spec()) == "here"
    assert (tmp_path / "figure.png").read_bytes().startswith(b"\x89PNG")


def test_a_figure_the_helper_cannot_write_fails_here_with_the_error_naming_the_file(tmp_path):
    missing = tmp_path / "no such directory" / "figure.png"
    with Painter() as helper:
        process = helper._process
        with pytest.raises(OSError) as raised:
            helper.paint("paper", missing, spec())
    assert process.returncode == 1                        # the helper tried and failed; the command then drew it
    assert raised.value.filename == str(missing) and not (tmp_path / "no such directory").exists()


def test_close_stops_a_waiting_helper_and_a_helper_whose_command_went_away_exits():
    helper = Painter()
    process = helper._process
    helper.close()
    assert process.poll() is not None and helper._process is None
    helper.close()                                    # twice is harmless
    # the command's end closes the helper's standard input: it exits by itself, status 1, quietly
    orphan = subprocess.Popen([sys.executable, "-m", "vcyto.studies.painter"], stdin=subprocess.PIPE,
                              stderr=subprocess.PIPE)
    _, err = orphan.communicate(b"", timeout=120)
    assert orphan.returncode == 1 and b"Traceback" not in err and b"vcyto painter" not in err


def test_a_helper_that_fails_to_draw_says_why_on_its_stderr():
    done = subprocess.run([sys.executable, "-m", "vcyto.studies.painter"],
                          input=painter.pickle.dumps(("nothing", "x.png", {})), capture_output=True, timeout=120)
    last = done.stderr.decode().strip().splitlines()[-1]
    assert done.returncode == 1 and last == "vcyto painter: KeyError: 'nothing'"


def test_the_helper_runs_this_vcyto_whatever_the_current_directory_holds(tmp_path, monkeypatch):
    # a package named vcyto in the user's directory, whose painter would "draw" nothing and succeed
    (tmp_path / "vcyto").mkdir()
    (tmp_path / "vcyto" / "__init__.py").write_text("")
    (tmp_path / "vcyto" / "painter.py").write_text("import sys; sys.exit(0)\n")
    monkeypatch.chdir(tmp_path)
    with Painter() as helper:
        assert helper.paint("paper", tmp_path / "figure.png", spec()) == "helper"
    assert (tmp_path / "figure.png").read_bytes().startswith(b"\x89PNG")


def test_a_helper_stopped_while_it_draws_leaves_no_temporary_file(tmp_path):
    import time
    helper = Painter()
    process = helper._process
    heavy = {**spec(), "lines": spec()["lines"] * 400}            # long enough to draw to be caught at it
    process.stdin.write(painter.pickle.dumps(("paper", str(tmp_path / "figure.png"), heavy)))
    process.stdin.close()
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(".figure.png.*.tmp")) and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.001)
    assert list(tmp_path.glob(".figure.png.*.tmp")), "the helper was not caught writing"
    helper.close()                                        # SIGTERM while it writes
    assert process.returncode is not None
    assert list(tmp_path.iterdir()) == []                 # neither the temporary file nor a figure


@pytest.mark.parametrize("cores, load, idle", [(2, 0.3, True), (2, 1.0, True), (2, 1.2, False), (2, 13.0, False),
                                               (8, 6.5, True)])
def test_the_helper_starts_only_where_a_core_is_idle(monkeypatch, cores, load, idle):
    monkeypatch.setattr(painter.os, "cpu_count", lambda: cores)
    monkeypatch.setattr(painter.os, "getloadavg", lambda: (load, load, load))
    assert painter.core_idle() is idle


def test_without_a_load_average_the_figure_is_drawn_here(monkeypatch):
    def unknown():
        raise OSError("no load average")
    monkeypatch.setattr(painter.os, "getloadavg", unknown)
    assert painter.core_idle() is False
