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
