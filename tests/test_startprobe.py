"""A warm start (python -m vcyto.startprobe): the second run of a scenario reaches its first step from the cache
without importing pint; the first run filled the matrices, steady-flow and unit entries."""

import json
import os
import subprocess
import sys


def probe(directory, *arguments):
    run = subprocess.run([sys.executable, "-m", "vcyto.startprobe", *arguments], capture_output=True, text=True,
                         env={**os.environ, "VCYTO_CACHE_DIR": str(directory), "VCYTO_CACHE": "on"}, timeout=600)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.strip().splitlines()[-1])


def test_a_warm_start_reads_the_cache_and_never_imports_pint(tmp_path):
    arguments = ("paper", "2", "--no-png", "--quiet", "--mesh-h", "10um")
    cold = probe(tmp_path, *arguments)
    assert cold["reached_first_step"] and cold["pint_imported"]
    kinds = {path.parent.name for path in tmp_path.rglob("*.npz")}
    assert {"matrices", "steady-flow"} <= kinds, kinds
    assert list((tmp_path / "units").glob("pint-*.json"))
    warm = probe(tmp_path, *arguments)
    assert warm["reached_first_step"] and not warm["pint_imported"] and warm["steps"] == 0
    assert warm["cpu_s"] > 0
    through = probe(tmp_path, "--steps", "2", *arguments)        # the start through the first two steps
    assert through["reached_first_step"] and through["steps"] == 2 and through["wall_s"] > 0
