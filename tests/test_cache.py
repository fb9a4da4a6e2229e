"""The set-up cache (vcyto/cache.py + sim/fast/store.py): a cached start equals a cold one, a changed field misses,
a corrupted entry is rebuilt, concurrent writers leave a valid entry. Every test uses its own directory."""

import dataclasses
import multiprocessing
import os
from pathlib import Path

import numpy as np
import pytest

from sim.fast import store
from sim.method.fluid import NavierStokes
from sim.model.scenario import UM, Scenario
from vcyto.cache import DiskCache, clear, usage


def scenario(**fluid):
    base = Scenario().with_numerics(mesh_h=10 * UM)
    return dataclasses.replace(base, fluid=dataclasses.replace(base.fluid, **fluid)) if fluid else base


def first_step(scene):
    fluid = NavierStokes(scene)
    return fluid.step(fluid.steady(0.0), actuation=1.0)


def test_cached_start_gives_the_cold_start_first_step(cache):
    store.install(None)
    cold = first_step(scenario())
    store.install(cache)
    first_step(scenario())                        # fills the cache
    assert cache.misses >= 1 and cache.hits == 0
    warm = first_step(scenario())
    assert cache.hits >= 1
    assert np.allclose(warm.velocity, cold.velocity, rtol=0, atol=1e-12 * np.abs(cold.velocity).max())
    assert np.allclose(warm.pressure, cold.pressure, rtol=0, atol=1e-12 * np.abs(cold.pressure).max())


def test_a_changed_scenario_field_misses(cache):
    first = NavierStokes(scenario()).steady(0.0)
    misses = cache.misses
    other = NavierStokes(scenario(viscosity=5e-3)).steady(0.0)
    # the steady flow misses; the mesh's matrices and the matrix structure (no viscosity in either) hit
    assert cache.misses == misses + 1 and cache.hits == 2
    assert not np.allclose(first.velocity, other.velocity)
    NavierStokes(scenario()).steady(0.0)
    assert cache.hits == 5


def test_changed_solver_code_misses_and_a_module_digest_is_stable_across_processes(cache, monkeypatch):
    """A stored flow names the code that computed it (``sim.method.fluid.solver_code_digest``): a changed kernel or
    solver, whose bits differ, misses instead of giving a warm run a cold run's old bits (found by a reviewer:
    a cache written before the round-6 kernel was reused); the digest is the same in another process (string
    hashing differs between processes)."""
    import subprocess
    import sys

    import sim.method.fluid as fluid_module
    NavierStokes(scenario()).steady(0.0)
    misses = cache.misses
    NavierStokes(scenario()).steady(0.0)
    assert cache.misses == misses
    monkeypatch.setattr(fluid_module, "solver_code_digest", lambda: "edited")
    NavierStokes(scenario()).steady(0.0)
    assert cache.misses == misses + 1
    monkeypatch.undo()
    script = ("import sim.method.fluid, sim.fast.store\n"
              "def f(x):\n    return x in {'alpha', 'beta', 'gamma', 'delta'}\n"
              "print(sim.method.fluid.solver_code_digest(), sim.fast.store.code_digest(f))")
    digests = {subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                              env={**os.environ, "PYTHONHASHSEED": seed},
                              cwd=Path(__file__).resolve().parents[1]).stdout.strip() for seed in ("1", "2", "3")}
    assert len(digests) == 1 and digests.pop().split()[0] == fluid_module.solver_code_digest()


def builder(calls):
    def build():
        calls.append(1)
        return {"x": np.arange(5.0), "y": np.eye(3)}
    return build


def test_a_corrupted_entry_is_detected_and_rebuilt(tmp_path):
    disk, calls = DiskCache(tmp_path), []
    key = {"a": 1}
    disk.fetch("kind", key, builder(calls))
    path = disk.path("kind", key)
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 2] ^= 0xFF                     # one flipped byte inside the data
    path.write_bytes(bytes(raw))
    arrays = disk.fetch("kind", key, builder(calls))
    assert disk.rebuilt == 1 and len(calls) == 2 and np.array_equal(arrays["x"], np.arange(5.0))
    path.write_bytes(path.read_bytes()[:100])      # truncated
    disk.fetch("kind", key, builder(calls))
    assert disk.rebuilt == 2 and len(calls) == 3
    assert disk.fetch("kind", key, builder(calls))["y"].shape == (3, 3) and disk.hits == 1 and len(calls) == 3


def test_no_flipped_byte_anywhere_in_an_entry_gives_wrong_arrays(tmp_path):
    """The zip format's CRC-32 of each array (checked as it is read) and the stored key guard the entry: a flipped
    byte at any of 400 places across the file (headers, arrays, directory) gives either the right arrays (a byte
    no array depends on: a timestamp) or a rebuild, never other values."""
    disk, calls = DiskCache(tmp_path), []
    key = {"a": 1}
    disk.fetch("kind", key, builder(calls))
    path = disk.path("kind", key)
    good = path.read_bytes()
    expected = builder([])()
    for position in np.linspace(0, len(good) - 1, 400).astype(int):
        raw = bytearray(good)
        raw[position] ^= 0xFF
        path.write_bytes(bytes(raw))
        arrays = disk.fetch("kind", key, builder(calls))
        assert set(arrays) == set(expected), position
        assert all(np.array_equal(arrays[name], expected[name]) for name in expected), position
    assert disk.rebuilt >= 300 and disk.hits + disk.rebuilt == 400       # most bytes are arrays' or headers'


def test_keys_name_everything(tmp_path):
    disk, calls = DiskCache(tmp_path), []
    disk.fetch("kind", {"a": 1, "b": 2.0}, builder(calls))
    disk.fetch("kind", {"b": 2.0, "a": 1}, builder(calls))          # same key, other order: a hit
    disk.fetch("kind", {"a": 1, "b": 2.0000000001}, builder(calls))  # any field: a miss
    disk.fetch("other", {"a": 1, "b": 2.0}, builder(calls))
    assert len(calls) == 3 and disk.hits == 1


def _writer(directory, seed):
    disk = DiskCache(directory)
    big = np.random.default_rng(0).standard_normal(200_000)    # the same content from every writer
    for _ in range(5):
        disk._save(disk.path("kind", {"k": 1}), disk._full_key("kind", {"k": 1}), {"big": big})


def test_concurrent_writers_leave_a_valid_entry(tmp_path):
    context = multiprocessing.get_context("spawn")
    writers = [context.Process(target=_writer, args=(tmp_path, seed)) for seed in range(4)]
    for writer in writers:
        writer.start()
    for writer in writers:
        writer.join(60)
        assert writer.exitcode == 0
    disk = DiskCache(tmp_path)
    arrays = disk.fetch("kind", {"k": 1}, lambda: pytest.fail("the entry should be valid"))
    assert disk.hits == 1 and arrays["big"].shape == (200_000,)
    assert not list(Path(tmp_path).rglob("*.tmp"))                 # no temporary file left behind
    assert usage(tmp_path)["entries"] == 1 and clear(tmp_path) == 1 and usage(tmp_path)["entries"] == 0


def test_cache_command_reports_and_clears_the_configured_directory(tmp_path):
    import json
    import os
    import subprocess
    import sys
    environment = {**os.environ, "VCYTO_CACHE_DIR": str(tmp_path)}
    DiskCache(tmp_path).fetch("kind", {"a": 1}, lambda: {"x": np.zeros(3)})
    run = subprocess.run([sys.executable, "-m", "vcyto.cli", "cache", "clear", "--json"], capture_output=True,
                         text=True, env=environment)
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout)
    assert report["directory"] == str(tmp_path) and report["removed"] == 1 and report["entries"] == 0
    run = subprocess.run([sys.executable, "-m", "vcyto.cli", "cache"], capture_output=True, text=True,
                         env={**environment, "VCYTO_CACHE": "off"})
    assert "off" in run.stdout


def test_constant_matrices_come_from_the_cache_bit_for_bit(cache):
    from sim.method.taylorhood import TaylorHood
    from sim.model.mesh import channel_mesh
    base = scenario()
    store.install(None)
    cold = TaylorHood(channel_mesh(base.channel, base.numerics.mesh_h))
    store.install(cache)
    TaylorHood(channel_mesh(base.channel, base.numerics.mesh_h))                # fills the cache
    warm = TaylorHood(channel_mesh(base.channel, base.numerics.mesh_h))
    assert len(list((cache.directory / "matrices").glob("*.npz"))) == 1 and cache.hits == 1
    for name in ("mass", "laplace"):
        assert (getattr(warm, name) != getattr(cold, name)).nnz == 0
    assert all((w != c).nnz == 0 and w.shape == c.shape for w, c in zip(warm.divergence, cold.divergence))
    TaylorHood(channel_mesh(base.channel, 12 * UM))                            # another mesh: a miss
    assert len(list((cache.directory / "matrices").glob("*.npz"))) == 2 and cache.hits == 1


def test_code_digest_names_the_code():
    def form(u, v):
        return 2.0 * u * v

    def same(u, v):
        return 2.0 * u * v

    def other_constant(u, v):
        return 3.0 * u * v

    def nested(u, v):
        return sum(x * 2.0 for x in (u, v))

    def nested_other(u, v):
        return sum(x * 3.0 for x in (u, v))

    assert store.code_digest(form) == store.code_digest(same)
    assert store.code_digest(form) != store.code_digest(other_constant)
    assert store.code_digest(nested) != store.code_digest(nested_other)      # inside a nested code object

    def banded(x, band=(0.35, 0.65)):
        return x * band[0]

    def banded_other(x, band=(0.30, 0.70)):
        return x * band[0]
    assert store.code_digest(banded) != store.code_digest(banded_other)       # a default value

    def factory(flag):
        def kernel(x):
            return x if flag else -x
        return kernel
    assert store.code_digest(factory(True)) != store.code_digest(factory(False))   # a value closed over
    assert store.code_digest(factory(True)) == store.code_digest(factory(True))


def test_an_unwritable_cache_says_so_once_and_the_run_goes_on(tmp_path, caplog):
    """A cache directory that cannot be written (here a file's path) warns once per process, not once per entry,
    every fetch still builds its arrays, and `vcyto cache` reports it as not writable."""
    import logging


    blocked = tmp_path / "a-file"
    blocked.write_text("not a directory")
    cache = DiskCache(blocked / "cache")
    with caplog.at_level(logging.WARNING, logger="vcyto.cache"):
        first = cache.fetch("test", {"n": 1}, lambda: {"x": np.arange(3)})
        second = cache.fetch("test", {"n": 2}, lambda: {"x": np.arange(4)})
    assert list(first["x"]) == [0, 1, 2] and list(second["x"]) == [0, 1, 2, 3]
    warnings = [r for r in caplog.records if "cannot be written" in r.getMessage()]
    assert len(warnings) == 1 and "VCYTO_CACHE_DIR" in warnings[0].getMessage()
    assert usage(blocked / "cache")["writable"] is False and usage(tmp_path / "ok")["writable"] is True


def test_an_array_digest_hashes_dtype_shape_and_bytes_without_copying_them():
    """``sim.fast.store.digest`` (the key part of a matrix, a cut, a mesh) is the SHA-256 of each array's dtype, shape
    and C-order bytes: the same for a strided view as for its copy, different when only the shape or dtype differs."""
    import hashlib

    from sim.fast.store import digest

    arrays = [np.arange(12.0).reshape(3, 4).T, np.zeros(0, np.int32), np.array([True, False]), np.array(3.0)]
    expected = hashlib.sha256()
    for array in map(np.ascontiguousarray, arrays):       # (which makes a 0-d array one of shape (1,))
        expected.update(f"{array.dtype.str}{array.shape}".encode() + array.tobytes())
    assert digest(*arrays) == expected.hexdigest()
    assert digest(arrays[0]) == digest(arrays[0].copy())
    assert digest(np.arange(6.0)) != digest(np.arange(6.0).reshape(2, 3)) != digest(np.arange(6))


def test_a_stored_start_is_the_one_this_solver_computes_whatever_ran_first(cache):
    """The steady start of a solver with another time step or scheme (whose systems are scaled otherwise, which sets
    the last bits) is not another's stored start: with the cache it is its cold start bit for bit, whichever solver
    filled the cache first (a --tolerance stream after a fixed-step one took the latter's start)."""
    euler = scenario()
    bdf2 = euler.with_numerics(time_scheme="bdf2", dt=4 * euler.numerics.dt)
    store.install(None)
    cold = {name: NavierStokes(scene).steady(1.0) for name, scene in (("euler", euler), ("bdf2", bdf2))}
    assert not np.array_equal(cold["euler"].velocity, cold["bdf2"].velocity)      # the bits differ: it can fail
    store.install(cache)
    for order in (("euler", "bdf2"), ("bdf2", "euler")):
        clear(cache.directory)
        for name in order:
            warm = NavierStokes({"euler": euler, "bdf2": bdf2}[name]).steady(1.0)
            assert np.array_equal(warm.velocity, cold[name].velocity), (order, name)
            assert np.array_equal(warm.pressure, cold[name].pressure), (order, name)


def test_a_steady_start_does_not_depend_on_what_the_solver_solved_before():
    """A plant computes the IDT-off start, then the IDT-on one, on one solver; a run whose IDT-off start came from
    the cache computes only the IDT-on one. Both must give the same bits (each steady solve analyses its first
    Newton system afresh), or the stored start would depend on which run stored it."""
    previous = store.install(None)
    try:
        scene = scenario()
        alone = NavierStokes(scene).steady(1.0)
        solver = NavierStokes(scene)
        solver.steady(0.0)
        after = solver.steady(1.0)
    finally:
        store.install(previous)
    assert np.array_equal(after.velocity, alone.velocity) and np.array_equal(after.pressure, alone.pressure)
