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


def test_every_module_of_sim_lies_in_a_wing_of_the_layers_and_no_cycle_is_waived():
    """A module of sim belongs to one wing (the plants, the method, the model, the machinery), so the layers contract
    covers it; and the no-cycle contract ignores nothing (no waiver)."""
    wings = next(c for c in _contracts() if c.get("containers") == ["sim"])
    assert wings["type"] == "layers" and wings["layers"][-1] == "fast"
    outside = [str(path.relative_to(ROOT)) for path in (ROOT / "sim").rglob("*.py")
               if path.parent == ROOT / "sim" and path.name != "__init__.py"
               or path.parent != ROOT / "sim" and path.relative_to(ROOT / "sim").parts[0] not in wings["layers"]]
    assert outside == []
    acyclic = next(c for c in _contracts() if c["type"] == "acyclic_siblings")
    assert "ignore_imports" not in acyclic
    assert all("ignore_imports" not in c for c in _contracts() if c.get("containers") == ["sim"])


def test_the_machinery_importing_the_model_breaks_the_layers(tmp_path):
    """The layers contract is not vacuous: a copy of sim whose machinery imports the scenario fails it."""
    import shutil
    shutil.copytree(ROOT / "sim", tmp_path / "sim", ignore=shutil.ignore_patterns("*.so", "__pycache__"))
    (tmp_path / "sim" / "fast" / "late.py").write_text("from ..model import scenario\n")
    contract = next(c for c in _contracts() if c.get("containers") == ["sim"])
    (tmp_path / "pyproject.toml").write_text(
        '[tool.importlinter]\nroot_packages = ["sim"]\n\n[[tool.importlinter.contracts]]\nname = "wings"\n'
        f'type = "layers"\ncontainers = ["sim"]\nlayers = {contract["layers"]!r}\n'.replace("'", '"'))
    result = _lint_imports(tmp_path, env={**os.environ, "PYTHONPATH": str(tmp_path)})
    assert result.returncode != 0, result.stdout
    assert "BROKEN" in result.stdout and "sim.fast.late" in result.stdout
