"""PARDISO factorisations kept in the set-up cache (sim.fast.linalg.Pardiso(kept=True), vcyto.cache's directories): a
restored factor solves to the bits of a fresh one, in this process and in another; a changed matrix misses; a
damaged file is detected and the entry rebuilt; clear and usage see the directories; an unwritable cache warns
once and the factorisation goes on."""

import json
import logging
import os
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

from sim.fast import speed, store
from sim.fast.linalg import Pardiso, pardiso_available
from vcyto.cache import DiskCache, clear, usage

pytestmark = pytest.mark.skipif(not pardiso_available(), reason="MKL PARDISO is not installed")


def saddle_matrix(n: int = 40, shift: float = 4.0) -> sp.csr_matrix:
    """A symmetric indefinite matrix like the fluid's: a shifted 2-D Laplacian with a constraint block."""
    line = sp.diags([-1.0, 2.0 + shift / n, -1.0], [-1, 0, 1], shape=(n, n))
    laplace = sp.kronsum(line, line).tocsr()
    constraint = sp.random(n, n * n, density=4 / n, random_state=3, format="csr")
    return sp.bmat([[laplace, constraint.T], [constraint, None]], format="csr")


@pytest.mark.parametrize("single", [False, True])
def test_a_restored_factor_solves_to_the_bits_of_a_fresh_one(cache, single):
    matrix = saddle_matrix()
    rhs = np.random.default_rng(1).standard_normal(matrix.shape[0])
    fresh = Pardiso(matrix, symmetric=True, single=single, matching=False)
    first = Pardiso(matrix, symmetric=True, single=single, matching=False, kept=True)
    assert not first.restored and cache.misses == 1
    second = Pardiso(matrix, symmetric=True, single=single, matching=False, kept=True)
    assert second.restored and cache.hits == 1
    assert second.factor_nonzeros == fresh.factor_nonzeros and second.perturbed_pivots == fresh.perturbed_pivots
    assert np.array_equal(second.solve(rhs), fresh.solve(rhs))
    for phase in (331, 332, 333):
        assert np.array_equal(second.phase(phase, rhs), fresh.phase(phase, rhs))
    assert np.abs(matrix @ second.solve(rhs) - rhs).max() < (1e-4 if single else 1e-10) * np.abs(rhs).max()
    other = Pardiso(saddle_matrix(shift=5.0), symmetric=True, single=single, matching=False, kept=True)
    assert not other.restored and cache.misses == 2                 # another matrix: another key


def test_a_damaged_factor_file_is_detected_and_rebuilt(cache, caplog):
    matrix = saddle_matrix()
    rhs = np.ones(matrix.shape[0])
    expected = Pardiso(matrix, symmetric=True, kept=True).solve(rhs)
    [handle] = (cache.directory / Pardiso.KIND).glob("*/handle.pds")
    raw = bytearray(handle.read_bytes())
    raw[len(raw) // 2] ^= 0xFF                                       # one flipped byte in the factor
    handle.write_bytes(bytes(raw))
    with caplog.at_level(logging.WARNING, logger="vcyto.cache"):
        again = Pardiso(matrix, symmetric=True, kept=True)
    assert not again.restored and cache.rebuilt == 1
    assert any("does not match" in record.getMessage() for record in caplog.records)
    assert np.array_equal(again.solve(rhs), expected)
    handle.write_bytes(handle.read_bytes()[:1000])                     # truncated
    assert not Pardiso(matrix, symmetric=True, kept=True).restored and cache.rebuilt == 2
    restored = Pardiso(matrix, symmetric=True, kept=True)              # the rewritten entry holds
    assert restored.restored and np.array_equal(restored.solve(rhs), expected)
    assert not list(cache.directory.rglob("*.tmp"))                   # no temporary directory left behind


def test_clear_and_usage_see_the_kept_directories(cache):
    Pardiso(saddle_matrix(), symmetric=True, kept=True)
    report = usage(cache.directory)
    handle = next(cache.directory.rglob("handle.pds"))
    assert report["entries"] == 1 and report["bytes"] > handle.stat().st_size
    assert clear(cache.directory) == 2                                 # handle.pds and entry.npz
    assert usage(cache.directory)["entries"] == 0 and not list((cache.directory / Pardiso.KIND).iterdir())


def test_an_unwritable_cache_warns_once_and_factors(tmp_path, caplog):
    blocked = tmp_path / "a-file"
    blocked.write_text("not a directory")
    previous = store.install(DiskCache(blocked / "cache"))
    try:
        with caplog.at_level(logging.WARNING, logger="vcyto.cache"):
            factors = [Pardiso(saddle_matrix(shift=s), symmetric=True, kept=True) for s in (4.0, 5.0)]
    finally:
        store.install(previous)
    assert not any(f.restored for f in factors) and all(f.factor_nonzeros > 0 for f in factors)
    assert len([r for r in caplog.records if "cannot be written" in r.getMessage()]) == 1


_CHILD = """
import hashlib, json, sys
import numpy as np
sys.path.insert(0, {tests!r})
from sim.fast import store
from sim.fast.linalg import Pardiso
from test_factor_cache import saddle_matrix
from vcyto.cache import DiskCache
store.install(DiskCache({directory!r}))
matrix = saddle_matrix()
factor = Pardiso(matrix, symmetric=True, single=True, matching=False, kept=True)
solution = factor.solve(np.random.default_rng(2).standard_normal(matrix.shape[0]))
print(json.dumps({{"restored": factor.restored, "bits": hashlib.sha256(solution.tobytes()).hexdigest()}}))
"""


def test_a_factor_kept_by_one_process_gives_another_the_same_bits(tmp_path):
    script = _CHILD.format(tests=os.path.dirname(__file__), directory=str(tmp_path / "cache"))
    runs = [json.loads(subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                                      timeout=300).stdout) for _ in range(2)]
    assert [run["restored"] for run in runs] == [False, True]
    assert runs[0]["bits"] == runs[1]["bits"]


def test_the_least_recently_used_factors_go_beyond_the_budget(cache):
    matrices = {name: saddle_matrix(shift=shift) for name, shift in (("a", 4.0), ("b", 5.0), ("c", 6.0))}
    Pardiso(matrices["a"], symmetric=True, kept=True)
    entry = usage(cache.directory)["bytes"]
    cache.budget = int(2.5 * entry)                                                # room for two entries
    Pardiso(matrices["b"], symmetric=True, kept=True)
    assert Pardiso(matrices["a"], symmetric=True, kept=True).restored            # a used after b
    Pardiso(matrices["c"], symmetric=True, kept=True)                              # over budget: b goes
    assert cache.evicted == 1
    assert [Pardiso(matrices[name], symmetric=True, kept=True).restored for name in "ac"] == [True, True]
    assert not Pardiso(matrices["b"], symmetric=True, kept=True).restored
    cache.budget = 0                                                               # keeps no new one
    Pardiso(saddle_matrix(shift=7.0), symmetric=True, kept=True)
    assert not Pardiso(saddle_matrix(shift=7.0), symmetric=True, kept=True).restored


@pytest.mark.parametrize("value", ["-1", "nan", "lots"])
def test_a_bad_factor_budget_is_a_one_line_error(tmp_path, value):
    run = subprocess.run([sys.executable, "-m", "vcyto.cli", "cache"], capture_output=True, text=True,
                         env={**os.environ, "VCYTO_CACHE_DIR": str(tmp_path), "VCYTO_CACHE_FACTORS_MB": value})
    assert run.returncode == 2 and run.stdout == ""
    assert run.stderr.count("\n") == 1 and f"VCYTO_CACHE_FACTORS_MB='{value}'" in run.stderr


@pytest.mark.parametrize("own", ["1", "0"])
def test_the_split_solve_restores_both_halves_to_the_same_bits(cache, own, monkeypatch):
    """The fluid's default solver (two halves factored on two threads) on a mesh large enough for the split, with our
    own substitutions and with PARDISO's: a second set-up restores both halves, and its back-solves give the bits of a
    set-up without a cache."""
    from sim.fast.splitsolve import SplitPardiso
    from sim.fast.supernodal import SupernodalLDL, available
    from sim.method.fluid import NavierStokes
    from sim.model.scenario import UM, Scenario
    if own == "1" and not available():
        pytest.skip("vcyto was installed without its compiled substitution kernels")
    monkeypatch.setattr(speed, "_settings", replace(speed.current(), own_substitutions=own == "1"))
    scenario = Scenario().with_numerics(mesh_h=5 * UM)
    store.install(None)
    cold = NavierStokes(scenario)
    store.install(cache)
    NavierStokes(scenario)                                           # keeps the halves
    warm = NavierStokes(scenario, cold.space)
    split = getattr(warm._constant.factor, "inner", warm._constant.factor)
    assert isinstance(split, SplitPardiso) and all(half.factor.restored for half in split.halves)
    assert all(isinstance(half.factor, SupernodalLDL) == (own == "1") for half in split.halves)
    rhs = np.random.default_rng(5).standard_normal(len(cold.free))
    assert np.array_equal(warm.backsolve(rhs), cold.backsolve(rhs))


def test_bench_fluid_measures_the_kept_factorisation():
    from sim.method.fluid import NavierStokes
    from sim.model.scenario import UM, Scenario
    from vcyto.bench.fluid import _kept_factorisation
    scenario = Scenario().with_numerics(mesh_h=5 * UM)
    previous = store.install(None)
    try:
        base = NavierStokes(scenario)
    finally:
        store.install(previous)
    rhs = np.random.default_rng(6).standard_normal(len(base.free))
    result = _kept_factorisation(scenario, base.space, base, rhs)
    assert result["restored_factor_identical"] is True
    assert result["factorisation_kept_s"] > 0 and result["factorisation_restored_s"] > 0


def test_clear_and_usage_touch_only_the_caches_own_files(tmp_path):
    """A cache directory set by mistake to a folder holding other things: clear deletes the entries, nothing else."""
    directory = tmp_path / "misset"
    previous = store.install(DiskCache(directory))
    try:
        Pardiso(saddle_matrix(), symmetric=True, kept=True)
    finally:
        store.install(previous)
    foreign = [directory / "project" / "src" / "a.py", directory / "project" / "data.npz",
               directory / "project" / "notes" / "old.tmp", directory / Pardiso.KIND / "readme.txt"]
    for path in foreign:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("the user's")
    (directory / Pardiso.KIND / "my-folder").mkdir()
    assert usage(directory)["entries"] == 1
    assert clear(directory) == 2 and all(path.read_text() == "the user's" for path in foreign)
    assert (directory / Pardiso.KIND / "my-folder").is_dir() and usage(directory)["entries"] == 0


def test_an_entry_that_passes_its_checks_but_cannot_be_restored_is_replaced(cache, caplog):
    matrix = saddle_matrix()
    rhs = np.ones(matrix.shape[0])
    expected = Pardiso(matrix, symmetric=True, kept=True).solve(rhs)
    [entry] = (cache.directory / Pardiso.KIND).iterdir()
    handle = entry / "handle.pds"
    handle.write_bytes(handle.read_bytes()[:4096])                    # unusable, and its checksum made to match
    with np.load(entry / "entry.npz") as data:
        arrays = {name: data[name] for name in data.files}
    files = json.loads(str(arrays["_files"]))
    from vcyto.cache import _file_sum
    files["handle.pds"] = list(_file_sum(handle))
    arrays["_files"] = np.array(json.dumps(files))
    with open(entry / "entry.npz", "wb") as file:
        np.savez(file, **arrays)
    with caplog.at_level(logging.WARNING, logger="vcyto.cache"):
        again = Pardiso(matrix, symmetric=True, kept=True)
    assert not again.restored and cache.rebuilt == 1 and np.array_equal(again.solve(rhs), expected)
    assert any("could not restore" in record.getMessage() for record in caplog.records)
    restored = Pardiso(matrix, symmetric=True, kept=True)              # the entry was written again
    assert restored.restored and np.array_equal(restored.solve(rhs), expected)


def test_a_refactored_factor_is_not_kept(cache):
    factor = Pardiso(saddle_matrix(), symmetric=True, matching=True)
    factor.refactor(saddle_matrix(shift=5.0))
    factor.keep()
    assert not list(cache.directory.rglob("handle.pds"))


def test_the_budget_comes_from_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("VCYTO_CACHE_FACTORS_MB", "12.5")
    assert DiskCache(tmp_path).budget == 12_500_000
    monkeypatch.delenv("VCYTO_CACHE_FACTORS_MB")
    assert DiskCache(tmp_path).budget == 2_048_000_000
