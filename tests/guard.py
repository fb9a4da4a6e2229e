"""Run ``vcyto`` in this process with every expensive entry point replaced by a sentinel, so that input that
passes validation stops there instead of building a plant: tests of bad input stay fast and never start a run."""

import contextlib
import io
import re

from vcyto import cli


class WouldRun(BaseException):
    """Raised where real work would begin: the input was accepted."""


HEAVY = {
    "vcyto.stream": ["run_stream"],
    "vcyto.studies.flowtool": ["solve_paths", "calibrate"],
    "vcyto.studies.paper": ["run_paper"],
    "vcyto.studies.stabilitymap": ["stability_map"],
    "vcyto.studies.relaxation": ["relaxation"],
    "vcyto.studies.extremes": ["run_cases"],
    "vcyto.studies.tradeoff": ["tradeoff"],
    "vcyto.sweep": ["run_sweep", "executor"],
    "vcyto.studies.calibrate": ["make_calibration_plant", "calibrate"],
    "vcyto.bench.sort": ["bench_sort"],
    "vcyto.bench.recorders": ["bench_recorders"],
    "vcyto.bench.controller": ["bench_controller"],
    "vcyto.bench.sweep": ["bench_sweep"],
    "vcyto.bench.realtime": ["bench_realtime"],
    "vcyto.bench.wire": ["bench_wire"],
    "vcyto.bench.recording": ["bench_recording"],
    "vcyto.bench.auto": ["bench_auto"],
    "vcyto.bench.gym": ["bench_gym"],
    "vcyto.bench.membrane": ["bench_membrane"],
    "vcyto.bench.coupling": ["bench_coupling"],
    "vcyto.bench.treatments": ["bench_paper_treatments", "bench_treatments"],
    "vcyto.bench.fluid": ["bench_fluid"],
    "vcyto.bench.tolerance": ["bench_tolerance"],
}


def _stop(*args, **kwargs):
    raise WouldRun()


def patch_heavy(monkeypatch):
    import importlib
    for module, names in HEAVY.items():
        loaded = importlib.import_module(module)
        for name in names:
            monkeypatch.setattr(loaded, name, _stop)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.delenv("VCYTO_DEBUG", raising=False)


def vcyto_inline(argv) -> tuple[int | None, str, str]:
    """(exit status or None if the input was accepted, stdout, stderr) of ``vcyto argv`` run in-process."""
    out, err = io.StringIO(), io.StringIO()
    status = None
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            status = cli.main(list(argv))
        except SystemExit as leaving:              # argparse
            status = leaving.code
        except WouldRun:
            status = None
    return status, out.getvalue(), err.getvalue()


def names_what_is_wrong(line: str) -> bool:
    """The documented form ``vcyto: error: <option or field>: <what is wrong>``: the words before the first ": "
    name an option, a field or a file (one word once parenthesised remarks are dropped), not a sentence."""
    head, colon, _ = line.removeprefix("vcyto: error: ").partition(": ")
    return bool(colon) and re.fullmatch(r"\S+", re.sub(r"\s*\([^)]*\)", "", head)) is not None


def assert_one_line_refusal(status, stderr, allowed=(1, 2)):
    lines = stderr.strip().splitlines()
    assert status in allowed, (status, stderr)
    assert len(lines) == 1, stderr
    assert lines[0].startswith("vcyto: error: "), stderr
    assert names_what_is_wrong(lines[0]), stderr
    assert "Traceback" not in stderr and "internal error" not in stderr


def terminated_within(process, bound: float = 3.0) -> str:
    """SIGTERM ``process`` (a ``vcyto stream`` started with stderr piped): it ends with exit 143 within ``bound``
    seconds; its stderr."""
    import signal
    import time
    assert process.poll() is None, process.communicate()
    process.send_signal(signal.SIGTERM)
    sent = time.monotonic()
    try:
        _, err = process.communicate(timeout=60)
    finally:
        process.kill()
    took = time.monotonic() - sent
    assert process.returncode == 143, err
    assert took < bound, (took, err)
    return err
