"""The import contracts of pyproject.toml ([tool.importlinter]): sim stands alone, the controller sees only the
plant's contract, no package has an import cycle, nothing imports the command line. Checked by import-linter;
the second test shows that the checker does fail on a cycle made of a deferred (in-function) import."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _lint_imports(cwd, env=None):
    command = [str(Path(sys.executable).parent / "lint-imports"), "--no-cache"]
    return subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=300, env=env)


def test_the_import_contracts_of_the_package_hold():
    result = _lint_imports(ROOT)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "0 broken" in result.stdout


def test_a_cycle_through_a_deferred_import_breaks_the_contract(tmp_path):
    package = tmp_path / "looped"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "first.py").write_text("from looped import second\n")
    (package / "second.py").write_text("def late():\n    from looped import first\n    return first\n")
    (tmp_path / "pyproject.toml").write_text('[tool.importlinter]\nroot_packages = ["looped"]\n\n'
                                             '[[tool.importlinter.contracts]]\nname = "no cycles"\n'
                                             'type = "acyclic_siblings"\nancestors = ["looped"]\n')
    result = _lint_imports(tmp_path, env={**os.environ, "PYTHONPATH": str(tmp_path)})
    assert result.returncode != 0, result.stdout
    assert "BROKEN" in result.stdout and "first" in result.stdout and "second" in result.stdout


def _contracts() -> list[dict]:
    import tomllib
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]


def test_the_machinery_contract_covers_every_module_of_sim_and_no_cycle_is_waived():
    """A new module of sim is either machinery, the plain data the machinery may import, or forbidden to it; and
    the no-cycle contract ignores nothing (no waiver)."""
    machinery = next(c for c in _contracts() if c["name"].startswith("the machinery"))
    plain_data = {"sim.fast.speed", "sim.fast.store"}
    modules = {f"sim.{path.stem}" for path in (ROOT / "sim").glob("*.py") if path.stem != "__init__"}
    named = set(machinery["source_modules"]) | set(machinery["forbidden_modules"])
    assert named | plain_data == modules, sorted(modules ^ (named | plain_data))
    assert not set(machinery["source_modules"]) & set(machinery["forbidden_modules"])
    acyclic = next(c for c in _contracts() if c["type"] == "acyclic_siblings")
    assert "ignore_imports" not in acyclic
