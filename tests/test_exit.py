"""How a command ends. The quick exit of the ``vcyto`` executable (``vcyto.cli.exit_now``): outputs and exit
handlers complete, the status kept, the interpreter's teardown skipped, the ordinary exit where something must
still finish. A reader that went away (141), a Ctrl-C while the libraries load (130, one line), and no empty or
half-written figure left by a run that fails."""

import gc
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

SCRIPT = textwrap.dedent("""
    import atexit, sys, threading, time
    from vcyto.cli import exit_now

    # a file left open: only the interpreter's teardown flushes it (every vcyto output is closed before main
    # returns; this one shows whether the teardown ran)
    LEFT_OPEN = open(sys.argv[2], "w")
    LEFT_OPEN.write("flushed by the teardown")
    atexit.register(lambda: print("exit handler ran"))
    mode = sys.argv[1]
    if mode == "thread":                    # a non-daemon thread still working: the ordinary exit waits for it
        threading.Thread(target=lambda: (time.sleep(0.3), print("thread finished"))).start()
    if mode == "trace":                     # a tracer (coverage, a debugger) keeps the ordinary exit
        sys.settrace(lambda *args: None)
    sys.stdout.write("x" * 200_000 + "\\n")  # more than a pipe's buffer, still in sys.stdout's
    exit_now(3)
""")


def run(mode, tmp_path):
    left_open = tmp_path / f"{mode}.txt"
    done = subprocess.run([sys.executable, "-c", SCRIPT, mode, str(left_open)], capture_output=True, text=True,
                          timeout=120)
    return done, left_open.read_text()


def test_quick_exit_keeps_output_handlers_and_status_and_skips_teardown(tmp_path):
    done, left_open = run("quick", tmp_path)
    assert done.returncode == 3
    assert done.stdout.startswith("x" * 200_000 + "\n") and "exit handler ran" in done.stdout
    assert left_open == ""                          # the teardown was skipped


def test_a_running_thread_or_a_tracer_gets_the_ordinary_exit(tmp_path):
    for mode, expected in (("thread", "thread finished"), ("trace", "exit handler ran")):
        done, left_open = run(mode, tmp_path)
        assert done.returncode == 3
        assert expected in done.stdout and "exit handler ran" in done.stdout
        assert left_open == "flushed by the teardown", mode


def test_the_executable_exits_with_mains_status_through_a_pipe():
    """``python -m vcyto`` (what the ``vcyto`` script runs): JSON complete on stdout, bad usage still 2."""
    shown = subprocess.run([sys.executable, "-m", "vcyto", "scenario", "--json"], capture_output=True, text=True,
                           timeout=120)
    assert shown.returncode == 0 and json.loads(shown.stdout)
    bad = subprocess.run([sys.executable, "-m", "vcyto", "paper", "3"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and bad.stderr.startswith("vcyto: error:") and "Traceback" not in bad.stderr


GC_SCRIPT = textwrap.dedent("""
    import atexit, gc, sys
    sys.argv = ["vcyto", *sys.argv[1:]]
    atexit.register(lambda: print(gc.get_freeze_count(), gc.isenabled()))
    from vcyto.__main__ import run
    run()
""")


def test_the_executable_freezes_what_the_imports_leave_and_keeps_collecting():
    """The entry point loads the libraries with the collector off, freezes what they leave, and turns the
    collector back on; ``vcyto.cli.main`` called from Python (as the tests do) leaves it alone."""
    done = subprocess.run([sys.executable, "-c", GC_SCRIPT, "scenario", "--json"], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    frozen, enabled = done.stdout.strip().splitlines()[-1].split()
    assert int(frozen) > 50_000 and enabled == "True"
    from vcyto.cli import main
    already = gc.get_freeze_count()
    assert main(["scenario", "--json"]) == 0
    assert gc.get_freeze_count() == already and gc.isenabled()
    # a caller that had the collector off (the start-up probe from Python) keeps it off
    kept = subprocess.run([sys.executable, "-c", "import gc; gc.disable(); from vcyto.__main__ import "
                           "load_command_line; load_command_line(); print(gc.isenabled(), gc.get_freeze_count())"],
                          capture_output=True, text=True, timeout=120)
    enabled, frozen = kept.stdout.split()
    assert enabled == "False" and int(frozen) > 50_000


def test_a_reader_that_went_away_gives_status_141_and_no_error(tmp_path):
    """`vcyto ... | true`: stdout's pipe is closed before vcyto writes; no error line, no traceback, 141."""
    for args in (["scenario", "--json"], ["cache", "--json"]):
        read, write = os.pipe()
        os.close(read)
        try:
            done = subprocess.run([sys.executable, "-m", "vcyto", *args], stdout=write, stderr=subprocess.PIPE,
                                  text=True, timeout=120)
        finally:
            os.close(write)
        assert done.returncode == 141, (args, done.stderr)
        assert done.stderr == "", args


def test_ctrl_c_while_the_libraries_load_is_one_line_and_130():
    process = subprocess.Popen([sys.executable, "-m", "vcyto", "paper", "2", "--no-png"], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    time.sleep(0.25)            # Python is up (~0.05 s); vcyto's imports take ~0.5 s
    process.send_signal(signal.SIGINT)
    out, err = process.communicate(timeout=120)
    assert process.returncode == 130, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and "interrupted" in err


def test_a_failed_paper_run_leaves_no_empty_png(tmp_path):
    """The default PNG name is reserved before the run; a run that fails (here a time step far past the
    melanoma's stability limit) removes it, so no empty file takes the name."""
    done = subprocess.run([sys.executable, "-m", "vcyto", "paper", "2", "--mesh-h", "10um", "--dt", "1ms", "--quiet"],
                          capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 1 and done.stderr.startswith("vcyto: error:")
    assert not list((tmp_path / "recordings").glob("*.png"))


def test_a_figure_is_saved_whole_or_not_at_all(tmp_path):
    """``figures.save_figure`` draws into a temporary file and moves it in place: a save that fails half-way
    leaves neither a truncated PNG nor the temporary file."""
    from vcyto.studies.figures import pyplot, save_figure
    plt = pyplot()
    figure, axis = plt.subplots()
    axis.plot([0, 1], [0, 1])
    save_figure(figure, tmp_path / "whole.png")
    assert (tmp_path / "whole.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "whole.png").stat().st_mode & 0o777 == 0o666 & ~umask      # not mkstemp's 0600

    def broken_savefig(target, **kwargs):
        with open(target, "wb") as file:
            file.write(b"\x89PNG half")
        raise KeyboardInterrupt

    figure.savefig = broken_savefig
    try:
        save_figure(figure, tmp_path / "half.png")
    except KeyboardInterrupt:
        pass
    plt.close(figure)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["whole.png"]


def test_an_interrupted_paper_run_says_where_and_leaves_no_png(tmp_path):
    """SIGTERM (as SIGINT) during the steps: one line naming the step and time, 143, no PNG left behind."""
    command = [sys.executable, "-m", "vcyto", "paper", "1", "--mesh-h", "10um", "--dt", "1us", "--max-time", "1000"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    deadline = time.time() + 300
    seen = ""
    while "step " not in seen and time.time() < deadline:       # progress lines: the steps have started
        seen += process.stderr.readline()
    process.send_signal(signal.SIGTERM)
    out, err = process.communicate(timeout=120)
    assert process.returncode == 143, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("vcyto: interrupted by SIGTERM at step ") and "saves nothing" in last
    assert "Traceback" not in err and not list((tmp_path / "recordings").glob("*.png"))


def test_a_signal_while_a_run_creates_its_files_is_deferred_not_lost():
    """``runfiles.interrupts_deferred``: SIGINT/SIGTERM inside the block raise nothing there (a recorder's header
    is never cut in half), are noted as pending with their name, and the handlers are restored after."""
    from vcyto.recording.runfiles import interrupts_deferred
    before = signal.getsignal(signal.SIGINT)
    seen = {}
    with interrupts_deferred(seen) as block:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)                     # the handler runs here: it must not raise
        assert block.pending and seen["last"] == "SIGTERM"
    assert signal.getsignal(signal.SIGINT) is before
    with interrupts_deferred({}) as quiet:
        pass
    assert not quiet.pending


def test_a_signal_as_the_sinks_close_waits_for_the_files_and_the_summary(tmp_path, monkeypatch):
    """SIGTERM after the loop, while the sinks close (a stalled viewer's bounded wait): the files are finished, the
    summary says the run was complete, one line says so, and the exit status is the signal's (143)."""
    from guard import vcyto_inline

    import vcyto.cli.stream as stream_cli

    close = stream_cli._close_run

    def signalled_close(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)                     # the handler runs here: it must not raise
        return close(*args, **kwargs)

    monkeypatch.setattr(stream_cli, "_close_run", signalled_close)
    status, _, stderr = vcyto_inline(["stream", "--model", "rom", "--cells", "RBC,melanoma", "--output", str(tmp_path),
                                      "--name", "run", "--quiet", "--no-viewer"])
    assert status == 143, stderr
    assert "SIGTERM came as the run's files were finished; they are whole and the summary's status is 'complete'" \
        in stderr, stderr
    summary = json.loads((tmp_path / "run.json").read_text())
    assert summary["status"] == "complete" and summary["statistics"]["cells"] == 2
    assert (tmp_path / "run.mcap").stat().st_size > 0 and (tmp_path / "run.fcs").stat().st_size > 0


def test_a_write_that_fails_half_way_keeps_the_old_contents_and_names_the_file(tmp_path):
    """``outputs.write_whole`` (summaries, FCS, Gating-ML, PNGs): a disk that fills up in the middle leaves the
    reserved placeholder as it was, no temporary file, and an error naming the file the user will look for."""
    import errno

    from vcyto.outputs import write_into, write_whole
    summary = tmp_path / "run.json"
    summary.write_text('{"status": "running"}\n')

    def fill_up(temporary):
        Path(temporary).write_text('{"status": "complete", "cells": [')
        raise OSError(errno.ENOSPC, "No space left on device")

    try:
        write_whole(summary, fill_up)
    except OSError as error:
        assert error.filename == str(summary) and error.errno == errno.ENOSPC
    else:
        raise AssertionError("the failed write was not reported")
    assert summary.read_text() == '{"status": "running"}\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.json"]
    write_into(summary, '{"status": "complete"}\n')
    assert json.loads(summary.read_text()) == {"status": "complete"}


def test_a_signal_the_process_was_told_to_ignore_stays_ignored():
    """A script's `vcyto ... &` starts with SIGINT ignored: the command's handlers leave it so (as every program
    does there) and still turn SIGTERM into an interrupt."""
    from vcyto.recording import runfiles
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    seen: dict = {}
    try:
        with runfiles.signals_as_interrupt(seen):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)                          # ignored: nothing is raised
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(1)
                raise AssertionError("SIGTERM was not turned into an interrupt")
            except KeyboardInterrupt:
                assert seen["last"] == "SIGTERM"
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


STEPPED_SCRIPT = textwrap.dedent("""
    import sys, threading
    from sim.method.fluid import NavierStokes
    from sim.model.scenario import UM, Scenario
    from vcyto.cli import exit_now

    LEFT_OPEN = open(sys.argv[1], "w")
    LEFT_OPEN.write("flushed by the teardown")
    solver = NavierStokes(Scenario().with_numerics(mesh_h=20 * UM / 3))
    state = solver.step(solver.steady(0.0), actuation=1.0)     # starts the next step's integrals on the helper
    state = solver.step(state, actuation=1.0)
    solver._ahead[1].result()
    print(sorted(thread.name for thread in threading.enumerate()
                 if thread.is_alive() and not thread.daemon and thread is not threading.main_thread()))
    exit_now(0)
""")


def test_a_process_that_stepped_the_fluid_still_takes_the_quick_exit(tmp_path):
    """The fluid's helper thread (``NavierStokes.prefetch``) is a daemon: once the steps are done it holds nothing
    open, so ``exit_now`` skips the teardown after an FE-IB run too (a non-daemon helper sent every run through it:
    0.15-0.4 s, measured)."""
    left_open = tmp_path / "stepped.txt"
    done = subprocess.run([sys.executable, "-c", STEPPED_SCRIPT, str(left_open)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]"      # no thread but the main one holds the process
    assert left_open.read_text() == ""                       # the teardown was skipped


# --- a disk that fills up mid-run: exit 1, one line, what was written kept and named ---------------------------

@pytest.fixture
def small_filesystem(tmp_path):
    """A 120 MB tmpfs (the output check asks for 100 MB free), mounted for the test: needs root, else skipped."""
    import shutil
    if shutil.which("mount") is None or os.geteuid() != 0:
        pytest.skip("mounting a small filesystem needs root")
    mount = tmp_path / "small"
    mount.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=120m", "tmpfs", str(mount)],
                      capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)


def test_a_disk_that_fills_mid_run_keeps_what_it_can_and_says_which(small_filesystem):
    """The run streams into a small filesystem; once its recording has begun, a filler file takes every byte
    left. The run stops with exit 1 and one line naming the file and the cause, the files that hold what ran
    (the MCAP up to its last flush, the .rrd) are kept and named, those that could not be written are named
    too, and no placeholder is left claiming a run."""
    output = small_filesystem / "out"
    env = {key: value for key, value in os.environ.items() if key not in ("DISPLAY", "WAYLAND_DISPLAY")}
    process = subprocess.Popen([sys.executable, "-m", "vcyto", "stream", "--model", "rom", "--count", "5000", "--mix",
                                "RBC:0.9,melanoma:0.1", "--rate", "500", "--output", str(output), "--name", "run",
                                "--quiet"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        recording = output / "run.mcap"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not (recording.exists() and recording.stat().st_size > 100_000):
            time.sleep(0.1)
        assert process.poll() is None, process.communicate()
        with open(small_filesystem / "filler", "wb") as filler:
            with pytest.raises(OSError):
                while True:
                    filler.write(b"\0" * (1 << 20))
                    filler.flush()
        _, err = process.communicate(timeout=300)
    finally:
        process.kill()
    assert process.returncode == 1, err
    lines = err.strip().splitlines()
    # the first file to fail is named (the MCAP or the per-cell table, whichever wrote first on the full disk)
    assert len(lines) == 1 and lines[0].startswith(f"vcyto: error: {output}/run.") and ": cannot write it: " in \
        lines[0], err
    assert "No space left on device" in lines[0] and "Traceback" not in err
    kept = lines[0].split("kept (what ran up to the failure", 1)[1].split("; not written: ")[0]
    assert str(recording) in kept and str(output / "run.rrd") in kept
    named = {Path(word.strip(",;")) for word in lines[0].replace(": ", " ").split() if word.startswith(str(output))}
    assert {path for path in output.iterdir()} <= named           # every file there is named, kept or not
    for suffix in ("fcs", "gating.xml", "json"):                   # kept with its content, or absent
        path = output / f"run.{suffix}"
        assert not path.exists() or (str(path) in kept and path.stat().st_size > 0)
    replayed = subprocess.run([sys.executable, "-m", "vcyto", "replay", str(recording), "--save",
                               str(small_filesystem.parent / "replayed.rrd")], capture_output=True, text=True,
                              timeout=300)
    assert replayed.returncode == 0 and "replayed" in replayed.stdout, replayed.stderr
    assert int(replayed.stdout.split("replayed ", 1)[1].split()[0]) > 0


# --- SIGTERM ends a long run within a second, whatever it is doing ---------------------------------------------

def test_a_signal_inside_the_import_systems_own_code_waits_until_it_is_out(monkeypatch):
    """Raised in importlib's bootstrap (between taking a lock and its ``try``, or in a weakref callback that
    swallows exceptions) the interrupt could leave the import lock held, and the sinks' thread would wait for it
    for ever (seen once in twenty SIGTERMs of a 100,000-cell run's start): there the handler raises the signal
    again instead, to be handled at the next instruction; anywhere else it interrupts."""
    from vcyto.recording import runfiles
    again = []
    monkeypatch.setattr(signal, "raise_signal", again.append)
    seen: dict = {}
    handler = runfiles.signals_as_interrupt(seen)
    handler.handle(signal.SIGTERM, _Frame("<frozen importlib._bootstrap>"))
    assert again == [signal.SIGTERM] and seen["last"] == "SIGTERM"
    with pytest.raises(KeyboardInterrupt):
        handler.handle(signal.SIGTERM, sys._getframe())
    assert again == [signal.SIGTERM]


class _Frame:
    """A stand-in for a frame of the code in ``filename``."""

    def __init__(self, filename):
        self.f_code = type("Code", (), {"co_filename": filename})()


LONG_STREAM = ["stream", "--model", "rom", "--count", "100000", "--mix", "RBC:0.9,melanoma:0.1", "--rate", "2000",
               "--name", "run", "--quiet"]


@pytest.mark.parametrize("moment", ["setting up", "mid-run"])
def test_sigterm_ends_a_100000_cell_stream_within_the_bound(tmp_path, moment):
    """SIGTERM to a 100,000-cell rom stream (MCAP and .rrd) while it sets up or mid-run: exit 143 within 3 s on a
    loaded machine (measured 0.1-2.0 s on a shared 2-core host with a load average of 10-16), its summary
    "interrupted"."""
    from guard import terminated_within
    env = {key: value for key, value in os.environ.items() if key not in ("DISPLAY", "WAYLAND_DISPLAY")}
    process = subprocess.Popen([sys.executable, "-m", "vcyto", *LONG_STREAM, "--output", str(tmp_path)], env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        summary, recording = tmp_path / "run.json", tmp_path / "run.mcap"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not (summary.exists() and (
                moment == "setting up" or (recording.exists() and recording.stat().st_size > 100_000))):
            time.sleep(0.05)
        time.sleep(0.3 if moment == "setting up" else 1.0)
        terminated_within(process, 3.0)
    finally:
        process.kill()
    assert json.loads(summary.read_text())["status"] == "interrupted"


# --- a run killed outright leaves its summary and events readable up to its last checkpoint ---------------------

KILLED_STREAM = ["stream", "--model", "rom", "--count", "8000", "--mix", "RBC:0.9,melanoma:0.1", "--rate", "2000",
                 "--no-viewer", "--name", "run", "--quiet"]


def test_a_run_killed_with_sigkill_leaves_its_summary_and_events_readable_up_to_its_last_checkpoint(tmp_path):
    """SIGKILL once a checkpoint holds events: the summary parses, says "running" and partial and how far the run
    got (never complete); the FCS file reads with flowio, says "running" and holds the first events of the whole
    run (the same seed run to its end), in time order; the gate is written."""
    from vcyto.recording.fcs import read_fcs
    killed, whole = tmp_path / "killed", tmp_path / "whole"
    killed.mkdir()
    process = subprocess.Popen([sys.executable, "-m", "vcyto", *KILLED_STREAM, "--output", str(killed)],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline, summary = time.monotonic() + 180, {}
        while time.monotonic() < deadline and process.poll() is None and \
                not summary.get("checkpoint", {}).get("fcs_events"):
            time.sleep(0.05)
            try:
                summary = json.loads((killed / "run.json").read_text())
            except (OSError, ValueError):              # not yet reserved (a checkpoint replaces the file whole)
                pass
        assert process.poll() is None, "the run ended before it could be killed mid-way"
        process.kill()
        process.wait(timeout=30)
    finally:
        process.kill()
    summary = json.loads((killed / "run.json").read_text())
    assert summary["status"] == "running" and summary["partial"] is True and "killed" in summary["reason"]
    got = summary["checkpoint"]
    assert 0 < got["simulated_time_ms"] == summary["simulated_time_ms"] < 4000.0       # 8000 cells at 2000/s: 4 s
    assert summary["statistics"]["cells"] == got["cells_left"] > 0
    names, events, keywords = read_fcs(killed / "run.fcs")
    assert keywords["vcyto_status"] == "running" and len(events) >= got["fcs_events"] > 0
    assert (np.diff(events[:, 0]) >= 0).all()
    assert (killed / "run.gating.xml").stat().st_size > 0
    whole.mkdir()
    done = subprocess.run([sys.executable, "-m", "vcyto", *KILLED_STREAM, "--output", str(whole)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    names_whole, events_whole, keywords_whole = read_fcs(whole / "run.fcs")
    assert names == names_whole and keywords_whole["vcyto_status"] == "complete"
    assert len(events) < len(events_whole)
    np.testing.assert_array_equal(events, events_whole[:len(events)])
