"""The quick exit of the ``vcyto`` executable (``vcyto.cli.exit_now``): outputs and exit handlers complete, the
status kept, the interpreter's teardown skipped, and the ordinary exit where something must still finish."""

import json
import subprocess
import sys
import textwrap

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
